"""Smooth-region merge: 2x2 (4x4, ...) blocks of one grid's pixels that are flat and carry no texture
become one moment-matched Gaussian with the block's optical depth (:func:`smooth_merge_blocks`)."""

from __future__ import annotations

from dataclasses import dataclass, fields
from functools import lru_cache

import numpy as np

from .. import geometry as geo
from ..depth_gaussians import SURFEL_SCALE_FACTOR
from ..gaussians import SH_C0, Gaussians
from ..threads import map_threads
from .maths import SYM, max3, min3, outer6, plane_ok_c, rows4, scale_rotation6, smallest_eigenpair, sum3, sym3_eigvals
from .options import CompactionOptions
from .provenance import Provenance

#: Largest opacity a merged Gaussian gets (the renderer caps alpha at 0.99).
MERGED_OPACITY_MAX = 0.99
_LI2_X = np.linspace(0.0, MERGED_OPACITY_MAX, 4096)


def _dilog(x: np.ndarray) -> np.ndarray:
    """Li2(x) = sum_k x^k / k^2 for x in [0, 1) (reflection above 1/2, 48-term series below)."""
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0 - 1e-12)
    hi = x > 0.5
    y = np.where(hi, 1.0 - x, x)
    k = np.arange(1, 49, dtype=np.float64)
    series = np.sum(y[..., None] ** k / k**2, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        refl = np.pi**2 / 6 - np.log(np.maximum(x, 1e-300)) * np.log(np.maximum(1.0 - x, 1e-300)) - series
    return np.where(hi, refl, series)


_LI2_Y = _dilog(_LI2_X)
_LI2_SLOPE = (_LI2_Y[1:] - _LI2_Y[:-1]) / (_LI2_X[1:] - _LI2_X[:-1])


def opacity_depth(alpha: np.ndarray) -> np.ndarray:
    """Li2(alpha): a Gaussian's optical depth -ln(1 - alpha g) integrated over its footprint, per unit area.

    ``int -ln(1 - a exp(-q/2)) dA = 2 pi sigma_1 sigma_2 Li2(a)``; summed over
    overlapping Gaussians it is the mean optical depth of a surface patch.

    ``np.interp`` in the table with its arithmetic (the same bits, NaN in NaN out), the interval found from
    the table's even spacing instead of a binary search (several times faster).
    """
    x = np.asarray(np.clip(alpha, 0.0, MERGED_OPACITY_MAX), dtype=np.float64)
    last = _LI2_X.size - 2
    with np.errstate(invalid="ignore"):  # NaN: any interval, NaN out
        j = np.clip((x * (last + 1) / MERGED_OPACITY_MAX).astype(np.intp), 0, last)
    j -= _LI2_X[j] > x  # the estimate is at most one interval off
    j += _LI2_X[j + 1] <= x
    j = np.minimum(j, last)
    out = _LI2_SLOPE[j] * (x - _LI2_X[j]) + _LI2_Y[j]
    return np.where(x >= _LI2_X[-1], _LI2_Y[-1], out)


def opacity_for_depth(depth: np.ndarray) -> np.ndarray:
    """Inverse of :func:`opacity_depth` on [0, MERGED_OPACITY_MAX] (larger depths give the cap)."""
    return np.interp(depth, _LI2_Y, _LI2_X)


@dataclass
class _Units:
    """Merge candidates at one level: moment sums about their own weighted mean (float64).

    Symmetric 3x3 matrices are stored as 6 components (xx, yy, zz, xy, xz, yz).
    Positions are relative to the block's reference camera.
    """

    w: np.ndarray        # (m,) sum of weights (opacity x footprint area)
    mu: np.ndarray       # (m, 3) weighted mean position
    m2: np.ndarray       # (m, 6) sum w (p - mu)(p - mu)^T
    cov: np.ndarray      # (m, 6) sum w Sigma
    sh: np.ndarray       # (m, K, 3) sum w sh
    depth: np.ndarray    # (m,) sum of render area x Li2(opacity)
    cmin: np.ndarray     # (m, 3) DC min / max
    cmax: np.ndarray
    amin: np.ndarray     # (m,) opacity min / max
    amax: np.ndarray

    def take(self, idx) -> "_Units":
        return _Units(*(getattr(self, f.name)[idx] for f in fields(self)))


def _blocks(ids: np.ndarray) -> np.ndarray:
    """(P, h, w) unit ids -> (P, h//2, w//2, 4) ids of each 2x2 block (odd last row/column left out)."""
    p, h, w = ids.shape
    h2, w2 = h // 2, w // 2
    b = ids[:, : 2 * h2, : 2 * w2].reshape(p, h2, 2, w2, 2)
    return b.transpose(0, 1, 3, 2, 4).reshape(p, h2, w2, 4)


def _combine(u: _Units, members: np.ndarray) -> _Units:
    """Units of 2x2 blocks of ``u`` (members (m, 4) indices): sums, parallel-axis scatter, min/max."""
    parts = [u.take(members[:, k]) for k in range(4)]
    w = sum(p.w for p in parts)
    wsafe = np.where(w > 0, w, 1.0)
    mu = sum(p.w[:, None] * p.mu for p in parts) / wsafe[:, None]
    m2 = sum(p.m2 + outer6(p.mu - mu, p.w) for p in parts)
    return _Units(w, mu, m2, sum(p.cov for p in parts), sum(p.sh for p in parts), sum(p.depth for p in parts),
                  np.minimum.reduce([p.cmin for p in parts]), np.maximum.reduce([p.cmax for p in parts]),
                  np.minimum.reduce([p.amin for p in parts]), np.maximum.reduce([p.amax for p in parts]))


def _block_views(a: np.ndarray, p: int, h: int, w: int) -> list[np.ndarray]:
    """The four (P, h//2, w//2, ...) views of a full-layout array (member order of :func:`_blocks`)."""
    h2, w2 = h // 2, w // 2
    b = a.reshape((p, h, w) + a.shape[1:])[:, : 2 * h2, : 2 * w2].reshape((p, h2, 2, w2, 2) + a.shape[1:])
    return [b[:, :, i, :, j] for i in range(2) for j in range(2)]


@lru_cache(maxsize=8)
def _block_tops(p: int, h: int, w: int) -> np.ndarray:
    """(P * (h//2) * (w//2),) layout position of each 2x2 block's top-left pixel (read-only, cached)."""
    tops = (np.arange(p)[:, None, None] * h + 2 * np.arange(h // 2)[None, :, None]) * w + 2 * np.arange(w // 2)
    tops = tops.reshape(-1).astype(np.int64)
    tops.setflags(write=False)
    return tops


def _block_min_max(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Min and max over each 2x2 block of (3 P, h, w) colour planes, as (3, P * (h//2) * (w//2)).

    Row pairs first (contiguous inner loops), then column pairs; min / max are exact, so the order
    does not change the result.
    """
    c, h, w = a.shape
    h2, w2 = h // 2, w // 2
    r = a[:, : 2 * h2, : 2 * w2].reshape(c, h2, 2, 2 * w2)
    lo, hi = np.minimum(r[:, :, 0], r[:, :, 1]), np.maximum(r[:, :, 0], r[:, :, 1])
    lo = np.minimum(lo[..., 0::2], lo[..., 1::2])
    hi = np.maximum(hi[..., 0::2], hi[..., 1::2])
    return lo.reshape(3, -1), hi.reshape(3, -1)


def _level1_merge(gaussians: Gaussians, prov: Provenance, alive: np.ndarray, colour_tol: float, opacity_tol: float,
                  plane_tol: float, cos_incidence: float, pitch: float, budget: int | None = None):
    """2x2 blocks that merge: (block ids into the (P, H/2, W/2) block grid, their units, (m, 4) member indices,
    and the (3, P, H, W) DC colour planes and (P, H, W) alive mask of the layout).

    ``budget``: Gaussians the merge should remove (three per block). When the blocks that pass the texture
    test remove fewer, blocks that pass every other test merge too, least textured first, up to that count.

    The colour, opacity and all-alive tests run on the block-reshaped layout
    (no per-pixel gathers); only the blocks passing them are gathered, in
    member-major float64 component arrays, and the plane test's eigenvectors
    and the covariance / SH / optical-depth sums are computed only for the
    blocks that get that far. Same decisions and sums as the per-block
    formulas in :class:`_Units` (the same float64 operations in the same order).
    """
    n = len(gaussians)
    n_grids, h, w = prov.views * len(prov.grids), prov.height, prov.width
    sh = gaussians.sh
    if prov.index is None:
        prov.flat_index(n)
        slot = None
        al, op = alive, gaussians.opacities
        dct = np.ascontiguousarray(sh[:, 0, :].T)  # (3, N) colour channel-major (long inner loops)
    else:
        flat = prov.flat_index(n)
        slot = np.full(prov.full_count, -1, dtype=np.int64)
        slot[flat[alive]] = np.flatnonzero(alive)
        al = slot >= 0
        dct = np.zeros((3, prov.full_count), dtype=np.float32)
        dct[:, flat] = sh[:, 0, :].T
        op = np.zeros(prov.full_count, dtype=np.float32)
        op[flat] = gaussians.opacities
    a4 = _block_views(al, n_grids, h, w)
    ok = a4[0] & a4[1] & a4[2] & a4[3]
    o4 = _block_views(op, n_grids, h, w)
    amin = np.minimum(np.minimum(np.minimum(o4[0], o4[1]), o4[2]), o4[3])
    amax = np.maximum(np.maximum(np.maximum(o4[0], o4[1]), o4[2]), o4[3])
    ok &= amax - amin <= np.float32(opacity_tol)
    cmin, cmax = _block_min_max(dct.reshape(3 * n_grids, h, w))
    crange = cmax - cmin
    ok &= (np.maximum(np.maximum(crange[0], crange[1]), crange[2]) <= np.float32(colour_tol / SH_C0)).reshape(
        ok.shape)  # colour tolerance in DC units
    planes = dct.reshape(3, n_grids, h, w), al.reshape(n_grids, h, w)
    t, whole, contrast = block_texture_contrast(*planes, 1)
    tex_ok = _texture_passes(t, whole, contrast, TEXTURE_TOL)
    ok &= tex_ok if budget is None else whole
    blk = np.flatnonzero(ok)
    top = _block_tops(n_grids, h, w)[blk]  # layout position of each candidate's top-left pixel
    plane = top // (h * w)
    mem = np.stack([top, top + 1, top + w, top + w + 1])  # (4, m) layout positions
    if slot is not None:
        mem = slot[mem]
    cams = np.repeat(prov.c2w[:, :3, 3], len(prov.grids), axis=0)
    parts = map_threads(lambda i: _level1_chunk(gaussians, mem[:, i:i + _CHUNK], cams[plane[i:i + _CHUNK]], plane_tol,
                                                cos_incidence, pitch), range(0, blk.size, _CHUNK))
    sel = np.concatenate([p[0] for p in parts]) if parts else np.zeros(0, bool)
    b = blk[sel]
    k = gaussians.sh.shape[1]
    cat = (lambda j, shape: np.concatenate([p[j] for p in parts]) if parts else np.zeros(shape))
    units = _Units(cat(1, (0,)), cat(2, (0, 3)), cat(3, (0, 6)), cat(4, (0, 6)), cat(5, (0, k, 3)), cat(6, (0,)),
                   cmin[:, b].T.astype(np.float64), cmax[:, b].T.astype(np.float64),
                   amin.reshape(-1)[b].astype(np.float64), amax.reshape(-1)[b].astype(np.float64))
    members = mem[:, sel].T
    if budget is not None:  # each block's arithmetic is its own: the blocks kept merge as they would alone
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = (t / contrast).reshape(-1)[b]
        take = _least_textured(tex_ok.reshape(-1)[b], np.nan_to_num(ratio, nan=np.inf), -(-budget // 3))
        b, units, members = b[take], units.take(take), members[take]
    return b, units, members, planes


#: Luma weights (Rec. 601) of the texture test: the eye (and the sharpness metric) sees luma detail most.
LUMA = np.array([0.299, 0.587, 0.114], dtype=np.float32)
#: A block merges when its texture is at most this many times its grid's mean block texture at that level
#: (:func:`texture_ok`). 1.4 keeps the Gaussian count of the earlier absolute colour-range test within +8% on
#: the dev scenes (docs/design.md, Compaction).
TEXTURE_TOL = 0.1


def _luma(x: np.ndarray) -> np.ndarray:
    """LUMA-weighted sum over the first axis of (3, ...) float32 colour planes, as three array passes (no BLAS
    call: its worker threads spin on after it, taking a core from the rest of the request)."""
    return LUMA[0] * x[0] + LUMA[1] * x[1] + LUMA[2] * x[2]


def _up2(m: np.ndarray, valid: np.ndarray, axis: int) -> np.ndarray:
    """Bilinear 2x upsampling of block values along ``axis`` (half-pixel centres: 3/4 of the block, 1/4 of the
    nearer neighbour); a neighbour that is not ``valid`` (or off the edge) is replaced by the block itself."""
    n = m.shape[axis]
    every = bool(valid.all())
    out = []
    for idx in (np.r_[0, np.arange(n - 1)], np.r_[np.arange(1, n), n - 1]):  # the neighbour before, after
        nb = np.take(m, idx, axis=axis)
        if not every:
            nb = np.where(np.take(valid, idx, axis=axis - 1), nb, m)
        out.append(0.75 * m + 0.25 * nb)
    shape = list(m.shape)
    shape[axis] = 2 * n
    return np.stack(out, axis=axis + 1).reshape(shape)


def _means2(x: np.ndarray) -> np.ndarray:
    """Means of the 2x2 blocks of (C, G, h, w) planes (odd last row / column left out): four strided views
    added as numpy's mean over the block axes adds them, (x00 + x01) + (x10 + x11), then / 4 (the same bits,
    several times faster than the reduction over two short axes)."""
    h, w = x.shape[2] // 2 * 2, x.shape[3] // 2 * 2
    top = x[:, :, 0:h:2, 0:w:2] + x[:, :, 0:h:2, 1:w:2]
    top += x[:, :, 1:h:2, 0:w:2] + x[:, :, 1:h:2, 1:w:2]
    top /= np.asarray(4, dtype=top.dtype)
    return top


def _all2(p: np.ndarray) -> np.ndarray:
    """(G, h//2, w//2): all four pixels of each 2x2 block of a (G, h, w) mask."""
    h, w = p.shape[1] // 2 * 2, p.shape[2] // 2 * 2
    return p[:, 0:h:2, 0:w:2] & p[:, 0:h:2, 1:w:2] & p[:, 1:h:2, 0:w:2] & p[:, 1:h:2, 1:w:2]


def block_texture(dc: np.ndarray, present: np.ndarray, level: int) -> tuple[np.ndarray, np.ndarray]:
    """Texture of each block of side 2**level, the detail one Gaussian loses, and which blocks are whole.

    ``dc``: (3, G, h, w) DC colour planes of the layout; ``present``: (G, h, w) pixels that have a
    Gaussian. At level L the block's four children (pixels at L = 1, the means of 2**(L-1) blocks
    above) are compared with the bilinear upsampling of the block means (a neighbour that is not whole
    counts as the block itself), i.e. with what merged Gaussians that overlap their neighbours draw:
    texture = luma-weighted (:data:`LUMA`) mean |child - prediction| over the four children. A colour
    ramp has none; a checkerboard, stripes or grain have it at any contrast. Returns ((G, h >> L, w >> L)
    texture, the same-shaped mask of blocks whose pixels are all present).
    """
    x, p = dc.astype(np.float32), np.asarray(present, bool)
    for _ in range(int(level) - 1):
        x, p = _means2(x), _all2(p)
    m, whole = _means2(x), _all2(p)
    c, g, h2, w2 = m.shape
    pred = _up2(_up2(m, whole, 2), np.repeat(whole, 2, axis=1), 3)
    r = np.abs(x[:, :, : 2 * h2, : 2 * w2] - pred)
    return _luma(_means2(r)), whole


def block_texture_contrast(dc: np.ndarray, present: np.ndarray, level: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(:func:`block_texture`'s texture and whole-block mask, each grid's contrast (G, 1, 1)): the luma-weighted
    mean |colour - the grid's mean colour| over its present pixels."""
    t, whole = block_texture(dc, present, level)
    p = np.asarray(present, bool)
    n = np.maximum(p.reshape(p.shape[0], -1).sum(axis=1), 1)
    every = bool(p.all())  # the same sums without the masking passes
    mean = (dc if every else np.where(p, dc, 0)).reshape(3, p.shape[0], -1).sum(axis=2) / n  # (3, G)
    dev = np.abs(dc - mean[:, :, None, None])
    dev = (dev if every else np.where(p, dev, 0)).reshape(3, p.shape[0], -1).sum(axis=2) / n
    return t, whole, _luma(dev.astype(np.float32))[:, None, None]


def texture_ok(dc: np.ndarray, present: np.ndarray, level: int, tol: float) -> np.ndarray:
    """(G, h >> level, w >> level) bool: whole blocks whose :func:`block_texture` is at most ``tol`` x their
    grid's contrast (:func:`block_texture_contrast`).

    Scale-free: scaling every colour about mid-grey (the DC planes by a factor) scales texture and
    contrast alike and leaves each decision unchanged. A ramp merges at any steepness, a faint grain
    on a plain wall is kept where the room's own contrast is faint too.
    """
    return _texture_passes(*block_texture_contrast(dc, present, level), tol)


def _texture_passes(texture: np.ndarray, whole: np.ndarray, contrast: np.ndarray, tol: float) -> np.ndarray:
    """:func:`texture_ok`'s test on :func:`block_texture_contrast`'s parts."""
    return whole & (texture <= np.float32(tol) * contrast)


def _least_textured(tex_ok: np.ndarray, ratio: np.ndarray, blocks: int) -> np.ndarray:
    """Indices (ascending) of the blocks to merge: every one that passes the texture test, and when they are
    fewer than ``blocks``, the least textured others (by ``ratio``, texture / contrast) up to that count."""
    extra = blocks - int(tex_ok.sum())
    rest = np.flatnonzero(~tex_ok)
    if extra <= 0 or rest.size == 0:
        return np.flatnonzero(tex_ok)
    if extra < rest.size:
        rest = rest[np.argpartition(ratio[rest], extra - 1)[:extra]]
    keep = tex_ok.copy()
    keep[rest] = True
    return np.flatnonzero(keep)


#: Candidate blocks per chunk of :func:`_level1_chunk` (its float64 temporaries then stay in the CPU cache).
_CHUNK = 16384


def _level1_chunk(gaussians: Gaussians, mem: np.ndarray, cam: np.ndarray, plane_tol: float, cos_incidence: float,
                  pitch: float):
    """Plane test and moment sums of candidate 2x2 blocks with member indices ``mem`` (4, m).

    Returns (ok mask (m,), and for the blocks that merge: w, mu (., 3), m2 (., 6), weighted covariance
    sum (., 6), weighted SH sum (., K, 3), optical depth sum), the same float64 arithmetic as
    :func:`outer6` / :func:`plane_ok_c` / :func:`quat_to_rotmat` / :func:`_render_area` per member.
    """
    sc = np.take(gaussians.scales, mem, axis=0)  # (4, m, 3) float32 (np.take: faster than fancy indexing)
    s0, s1, s2 = (sc[..., k].astype(np.float64) for k in range(3))
    area = s0 * s1 * s2 / np.maximum(np.minimum(np.minimum(s0, s1), s2), 1e-300)  # two largest
    opa = np.take(gaussians.opacities, mem).astype(np.float64)
    wk = opa * area
    mp = np.take(gaussians.means, mem, axis=0)
    px, py, pz = (mp[..., k] - cam[:, k] for k in range(3))  # float64, camera-relative
    wt = rows4(wk)
    wsafe = np.where(wt > 0, wt, 1.0)
    mux, muy, muz = (rows4(wk * pc) / wsafe for pc in (px, py, pz))
    dx, dy, dz = px - mux, py - muy, pz - muz
    tx, ty = wk * dx, wk * dy
    m2 = [rows4(tx * dx), rows4(ty * dy), rows4((wk * dz) * dz), rows4(tx * dy), rows4(tx * dz), rows4(ty * dz)]
    good = (wt > 0) & plane_ok_c(wsafe, mux, muy, muz, m2, plane_tol, cos_incidence)
    sel = np.flatnonzero(good)
    m = mem[:, sel]
    wk, s0, s1, s2, opa, px, py, pz = (np.take(a, sel, axis=1) for a in (wk, s0, s1, s2, opa, px, py, pz))
    # member covariances R diag(s^2) R^T (quat_to_rotmat's arithmetic, component by component)
    q = np.take(gaussians.quats, m, axis=0)  # (4, ms, 4) float32
    qw, qx, qy, qz = (q[..., k].astype(np.float64) for k in range(4))
    qn = np.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)  # np.linalg.norm's order
    if (qn > 1e-12).all():
        qw, qx, qy, qz = qw / qn, qx / qn, qy / qn, qz / qn
    else:
        nz, qs = qn > 1e-12, np.maximum(qn, 1e-12)
        qw, qx, qy, qz = (np.where(nz, c / qs, d) for c, d in ((qw, 1.0), (qx, 0.0), (qy, 0.0), (qz, 0.0)))
    r = ((1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)),
         (2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)),
         (2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)))
    ss = (s0 ** 2, s1 ** 2, s2 ** 2)
    rs = [[r[i][k] * ss[k] for k in range(3)] for i in range(3)]
    cov = np.empty((m.shape[1], 6))
    for c, (i, j) in enumerate(SYM):
        cov[:, c] = rows4(wk * (rs[i][0] * r[j][0] + rs[i][1] * r[j][1] + rs[i][2] * r[j][2]))
    shs = rows4(wk[..., None, None] * np.take(gaussians.sh, m, axis=0).astype(np.float64))
    rng = np.sqrt(px ** 2 + py ** 2 + pz ** 2)
    s_max = np.maximum(np.maximum(s0, s1), s2)
    s_min = np.minimum(np.minimum(s0, s1), s2)
    s_mid = s0 + s1 + s2 - s_max - s_min
    low = COVERAGE_LOW_PASS * (rng * pitch) ** 2
    depth = rows4(np.sqrt((s_mid**2 + low) * (s_max**2 + low)) * opacity_depth(opa))
    return (good, wt[sel], np.stack([mux[sel], muy[sel], muz[sel]], axis=1), np.stack([c[sel] for c in m2], axis=1),
            cov, shs, depth)


#: Screen-space low-pass (pixel^2) assumed when matching coverage: half the renderer's 0.3
#: (rasterizer.splat.LOW_PASS), as the pixel size of a later render is unknown. On the dev
#: scenes 0 matched the target views' mean alpha best where opacities are low (zind), 0.3
#: where they are high (m3d); 0.15 is within 0.02 of the uncompacted mean alpha on both.
COVERAGE_LOW_PASS = 0.15


def _render_area(scales: np.ndarray, pixel: np.ndarray) -> np.ndarray:
    """Footprint area (sigma_1 sigma_2 of the two largest scales) after a low-pass at this pixel size."""
    low = COVERAGE_LOW_PASS * pixel**2
    s_max, s_min = max3(scales), min3(scales)
    s_mid = sum3(scales) - s_max - s_min
    return np.sqrt((s_mid**2 + low) * (s_max**2 + low))


#: Merged blocks are widened in-plane to a standard deviation of at least this fraction of their
#: size, the overlap of the encoder's surfels (``SURFEL_SCALE_FACTOR`` neighbour steps): moment
#: matching alone leaves a 2x2 block's lattice at 0.43 of its spacing (16 Gaussians' at 0.34), which
#: lets the background through between opaque merged Gaussians (plain compositing) and ripples when
#: magnified (a synthetic wall seen at 2x: 26 dB -> 36 dB at 0.45 for 4x4 blocks).
MIN_OVERLAP = SURFEL_SCALE_FACTOR


def _merged_cov6(u: _Units, side: int) -> np.ndarray:
    """(m, 6) merged covariance: mean covariance + spread, widened in-plane.

    The widening adds isotropic in-plane variance (about the plane normal) up to
    MIN_OVERLAP^2 x block size^2, the size taken from the in-plane spread
    (a full b x b block has spread (b^2 - 1) / 12 pitch^2 per axis).
    """
    cov = (u.cov + u.m2) / u.w[:, None]
    if side >= 2 and MIN_OVERLAP > 0:
        spread = u.m2 / u.w[:, None]
        lam0, n, _ = smallest_eigenpair(spread)
        inplane_spread = 0.5 * (spread[:, 0] + spread[:, 1] + spread[:, 2] - lam0)
        nn = np.stack([n[:, i] * n[:, j] for i, j in SYM], axis=1)
        cur = 0.5 * (cov[:, 0] + cov[:, 1] + cov[:, 2] - (nn * cov * np.array([1, 1, 1, 2, 2, 2])).sum(1))
        target = MIN_OVERLAP**2 * 12.0 * side**2 / (side**2 - 1) * inplane_spread
        delta = np.maximum(target - cur, 0.0)
        eye = np.array([1.0, 1, 1, 0, 0, 0])
        cov = cov + delta[:, None] * (eye - nn)
    return cov


def _needed_depth(u: _Units, pitch: float, side: int = 1) -> np.ndarray:
    """Li2(opacity) a merged unit needs to keep its optical depth (> Li2(0.99): it cannot)."""
    lo, mid, hi, _ = sym3_eigvals(_merged_cov6(u, side))
    sig = np.sqrt(np.maximum(np.stack([lo, mid, hi], axis=1), 0.0))
    rng = np.sqrt(sum3(u.mu * u.mu))
    return u.depth / np.maximum(_render_area(sig, rng * pitch), 1e-300)


def merged_gaussians(u: _Units, cam: np.ndarray, pitch: float, side: int = 2) -> Gaussians:
    """One Gaussian per block: moment-matched mean and covariance, mean colour, coverage-preserving opacity.

    Mean = weighted mean of the means (weight = opacity x footprint area);
    covariance = weighted mean of the covariances + weighted spread of the
    means; scales and rotation from its eigen-decomposition; SH = weighted
    mean; the covariance is widened in-plane to :data:`MIN_OVERLAP` of the
    block size, so merged neighbours overlap as the surfels did. Opacity keeps the block's mean optical depth: a Gaussian of
    opacity a and footprint area A (sigma_1 sigma_2) has optical depth
    -ln(1 - a g) integrating to 2 pi A Li2(a) (:func:`opacity_depth`), and
    overlapping Gaussians add, so the merged opacity solves
    A' Li2(a') = sum_i A_i Li2(a_i) (areas with the low-pass at the grid's
    own pixel size, :data:`COVERAGE_LOW_PASS`), capped at 0.99 (blocks
    whose widened Gaussian would need more are not merged at 4x4 and up).
    """
    w = u.w[:, None]
    mu = u.mu
    rng = np.sqrt(sum3(mu * mu))
    scales, quats = scale_rotation6(_merged_cov6(u, side), min_scale=1e-12)
    scales = np.maximum(scales, 1e-9 * rng[:, None])  # no zero scale (log-scale in the PLY)
    need = u.depth / np.maximum(_render_area(scales, rng * pitch), 1e-300)
    return Gaussians(mu + cam, scales, quats, opacity_for_depth(need), u.sh / w[..., None])


@dataclass(frozen=True)
class SmoothMerge:
    """Result of :func:`smooth_merge_blocks`.

    drop: (N,) bool, Gaussians replaced by a merged one; gaussians: the merged
    Gaussians; index: (M,) flat layout position of each merged block's
    top-left pixel; block: (M,) block side in pixels (2, 4, ...);
    blocks: {side: count}.
    """

    drop: np.ndarray
    gaussians: Gaussians
    index: np.ndarray
    block: np.ndarray
    blocks: dict


def smooth_merge_blocks(gaussians: Gaussians, prov: Provenance, alive: np.ndarray, *,
                        levels: int = CompactionOptions.smooth_levels,
                        colour_tol: float = CompactionOptions.smooth_colour_tol,
                        opacity_tol: float = CompactionOptions.smooth_opacity_tol,
                        plane_tol: float = CompactionOptions.smooth_plane_tol,
                        max_incidence_deg: float = CompactionOptions.smooth_max_incidence_deg,
                        budget: int | None = None) -> SmoothMerge:
    """Replace 2x2 (then 4x4, ... up to 2**levels) blocks of one grid's pixels by one Gaussian each.

    A block merges when all its pixels are alive, its texture is at most
    :data:`TEXTURE_TOL` times its grid's mean (:func:`texture_ok`: scale-free,
    luma-weighted, against the bilinear prediction from the block means),
    every DC colour channel varies by at most ``colour_tol`` (an absolute cap;
    1 leaves the texture test alone) and opacity by at most ``opacity_tol``
    over it, and its (weighted) centres lie on a plane (rms residual <=
    ``plane_tol`` x range) whose normal is within ``max_incidence_deg`` of
    the ray to the block. Larger blocks are built from four merged children
    and tested on all their pixels (sums of moments, so no pixel is visited
    twice), and must keep their optical depth (see :func:`merged_gaussians`);
    the largest merged block wins. Blocks never cross grid borders (nor the
    ERP seam); an odd last row or column stays as it is.

    Why the incidence limit: on the dev scenes the loss came from floors and
    ceilings seen obliquely (often with wrong, unconfident depth); 45
    degrees kept the merge within 0.03 dB of no merge on every target.

    ``budget`` (a count cap's excess, Gaussians): when the 2x2 blocks that pass the texture test remove
    fewer, the least textured of those that pass every other test merge too, up to it. Merged blocks keep
    the coverage where dropping Gaussians would open holes (docs/design.md, Compaction).
    """
    n = len(gaussians)
    n_grids = prov.views * len(prov.grids)
    h, w = prov.height, prov.width
    cam_of_plane = np.repeat(prov.c2w[:, :3, 3], len(prov.grids), axis=0)  # (P, 3)
    cos_inc = float(np.cos(np.radians(max_incidence_deg)))
    pitch = (np.pi if prov.grids[0] == "erp" else 2 * geo.YIN_LAT_MAX) / h  # angular pixel pitch
    per_level: list[tuple[np.ndarray, _Units, np.ndarray]] = []  # (block ids map, units, children ids)
    ids_shape = (n_grids, h, w)
    for level in range(1, int(levels) + 1):
        if ids_shape[1] < 2 or ids_shape[2] < 2:
            break
        shape = (ids_shape[0], ids_shape[1] // 2, ids_shape[2] // 2)
        if level == 1:
            # children: the (m, 4) input indices of each merged block's pixels
            chosen, units, children, planes = _level1_merge(gaussians, prov, alive, colour_tol, opacity_tol,
                                                            plane_tol, cos_inc, pitch, budget)
        else:
            ids = np.full(ids_shape[0] * ids_shape[1] * ids_shape[2], -1, dtype=np.int64)
            ids[per_level[-1][0]] = np.arange(per_level[-1][0].size)
            blocks = _blocks(ids.reshape(ids_shape)).reshape(-1, 4)
            cand = np.flatnonzero(np.all(blocks >= 0, axis=1))
            u = _combine(per_level[-1][1], blocks[cand])
            ok = ((max3(u.cmax - u.cmin) <= np.float32(colour_tol / SH_C0))
                  & (u.amax - u.amin <= np.float32(opacity_tol)) & (u.w > 0)
                  & texture_ok(*planes, level, TEXTURE_TOL).reshape(-1)[cand])
            ok &= plane_ok_c(np.where(u.w > 0, u.w, 1.0), u.mu[:, 0], u.mu[:, 1], u.mu[:, 2],
                              [u.m2[:, k] for k in range(6)], plane_tol, cos_inc)
            sel = np.flatnonzero(ok)
            units = u.take(sel)
            if sel.size:
                # 4x4 and up only where one Gaussian can carry the block's optical depth (see merged_gaussians)
                fine = _needed_depth(units, pitch, 2**level) <= _LI2_Y[-1]
                sel, units = sel[fine], units.take(fine)
            chosen = cand[sel]
            children = blocks[chosen]
        per_level.append((chosen, units, children))
        ids_shape = shape
        if chosen.size == 0:
            break
    # top-down: a block absorbed into a merged parent is not emitted itself
    drop = np.zeros(n, dtype=bool)
    parts, index, side, counts = [], [], [], {}
    absorbed = None
    slot = None
    for level in range(len(per_level), 0, -1):
        chosen, units, children = per_level[level - 1]
        emit = np.ones(chosen.size, dtype=bool) if absorbed is None else ~absorbed
        bs = 2 ** level
        hl, wl = h // bs, w // bs
        plane, pix = np.divmod(chosen[emit], hl * wl)
        bi, bj = np.divmod(pix, wl)
        if emit.any():
            parts.append(merged_gaussians(units if absorbed is None else units.take(emit), cam_of_plane[plane],
                                          pitch, bs))
            index.append((plane * h + bi * bs) * w + bj * bs)
            side.append(np.full(int(emit.sum()), bs, dtype=np.int64))
        counts[bs] = int(emit.sum())
        if level > 1:
            absorbed = np.zeros(per_level[level - 2][0].size, dtype=bool)
            absorbed[children.ravel()] = True
        # members of emitted blocks: every pixel of the block in the layout
        if emit.any() and level == 1:
            drop[children[emit].ravel()] = True
        elif emit.any():
            if slot is None:
                slot = np.full(prov.full_count, -1, dtype=np.int64)
                slot[prov.flat_index(n)[alive]] = np.flatnonzero(alive)
            r = (bi[:, None] * bs + np.arange(bs)[None, :])  # (m, bs)
            c = (bj[:, None] * bs + np.arange(bs)[None, :])
            pos = ((plane[:, None, None] * h + r[:, :, None]) * w + c[:, None, :]).ravel()
            drop[slot[pos]] = True
    merged = (parts[0] if len(parts) == 1 else Gaussians.concatenate(parts)) if parts else Gaussians.empty(gaussians.sh_degree)
    if parts and merged.sh.shape[1] != gaussians.sh.shape[1]:
        merged = merged.with_(sh=np.pad(merged.sh, ((0, 0), (0, gaussians.sh.shape[1] - merged.sh.shape[1]), (0, 0))))
    return SmoothMerge(drop, merged, np.concatenate(index) if index else np.zeros(0, np.int64),
                       np.concatenate(side) if side else np.zeros(0, np.int64), dict(sorted(counts.items())))
