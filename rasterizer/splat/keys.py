"""Per-pixel front-to-back contribution lists: :func:`footprints` and :func:`sorted_keys`.

:func:`footprints` enumerates, for every pixel, the Gaussians that can touch
it, in front-to-back order of Euclidean range (camera z for a pinhole), with
the *opacity-free* Gaussian weight ``g = exp(-0.5 d^T conic d)`` (d = pixel
centre - projected centre, pixels). The compositor then uses
``alpha = min(0.99, opacity * g)``. Only contributions with ``g >= 1/255`` are
kept (those are the ones that could reach alpha >= 1/255 at opacity 1), so a
caller that changes opacities later (the +opt refinement) can reuse the
footprints with fixed geometry. A caller that knows the opacities will not
grow may pass ``opacity_bound`` to cut each footprint at
``g >= 1/(255 * bound)`` instead (smaller, faster; render does).

Culled before enumeration (besides :mod:`.projection`'s culls): footprints
entirely outside the image or a Yin/Yang grid's domain. ERP columns wrap
across the seam; a footprint wider than a full turn is capped at one turn (no
duplicate columns); polar ERP footprints follow :mod:`.polar`.

Implementation (vectorised, no loop over Gaussians or pixels): footprints
are bucketed into size classes, each class is a dense (n, KY, KX) block;
each surviving contribution is packed into one uint64 key
``pixel | depth rank | quantised q`` (:mod:`.blocks`) and a single sort orders
all of them by pixel, then by range. The blocks are laid out (KY, KX, n) with
the Gaussians ordered by (box origin, depth rank), so each box offset emits an
already sorted run of keys and that sort is a stable (timsort) merge of a
few hundred runs, 2-4x cheaper than sorting random keys. The dense key
blocks run in cache-sized chunks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..camera import Camera
from .blocks import KeyLayout, class_keys
from .polar import polar_split, sphere_boxes, sphere_ellipses, sphere_keys
from .projection import (
    Q_MAX,
    Columns,
    SharedPose,
    footprint_boxes,
    opacity_cuts,
    project_columns,
    shared_pose,
    sigma_cuts,
)

#: Default memory guard of :func:`footprints`: refuse renders estimated above this many (Gaussian, pixel)
#: contributions (about 20 bytes each). The environment shell's (rasterizer.shell) large backdrop discs need
#: room: a zind scene's full 1024x512 ERP lists estimate ~86M.
MAX_CONTRIBUTIONS = 120_000_000
_SIZE_CLASSES = np.unique(np.concatenate([
    np.arange(1, 13), np.ceil(12 * 1.25 ** np.arange(1, 60)),
]).astype(np.int64))
#: Dense elements per block before a class is split into chunks (cache-sized: more, shorter
#: sorted runs cost the final merge sort little, streaming big blocks through memory costs more).
_CHUNK_ELEMENTS = 1 << 17
#: ``job_keys`` drops the keys of masked-out pixels only when a sample of every MASK_PROBE_STEP-th
#: key finds more than MASK_MIN_DROP of them there: the filter (a gather and a compress per key)
#: costs about a tenth of what a kept key costs in the sort and the compositing after it.
MASK_PROBE_STEP = 16
MASK_MIN_DROP = 0.125
#: A size-class group whose dense block would hold fewer elements than this moves to a coarser
#: class (a few at most): every block costs about 40 numpy calls (~50 us) whatever its size, the
#: time of some thousands of dense elements, and most blocks of the large classes hold a handful
#: of Gaussians.
SMALL_BLOCK = 1 << 12

class RenderLimitError(ValueError):
    """The footprints would need more memory than the caller allowed."""


@dataclass(frozen=True)
class Footprints:
    """Per-(pixel, Gaussian) contributions of one camera, front-to-back per pixel.

    ``pixel`` (M,) int32 flat index ``row * width + col``, ascending; within
    one pixel the entries are in increasing range of their Gaussian.
    ``gaussian`` (M,) int32 index into the Gaussians given to
    :func:`footprints`; ``weight`` (M,) float32 opacity-free Gaussian weight
    g in [1/255, 1]; ``ranges`` (N,) float32 range of every input Gaussian
    (0 for culled ones); ``height``, ``width``: the image size.
    """

    pixel: np.ndarray
    gaussian: np.ndarray
    weight: np.ndarray
    ranges: np.ndarray
    height: int
    width: int

    def __len__(self) -> int:
        return int(self.pixel.shape[0])

def _size_class(k: np.ndarray) -> np.ndarray:
    """Smallest size class >= k (k >= 1)."""
    pos = np.searchsorted(_SIZE_CLASSES, k)
    big = pos >= len(_SIZE_CLASSES)
    out = _SIZE_CLASSES[np.minimum(pos, len(_SIZE_CLASSES) - 1)]
    return np.where(big, k, out)


def footprints(gaussians, camera: Camera, *, opacity_bound: np.ndarray | None = None,
               factors: np.ndarray | None = None, max_contributions: int = MAX_CONTRIBUTIONS,
               camera_points: tuple[np.ndarray, np.ndarray] | None = None) -> Footprints:
    """Per-pixel, front-to-back lists of the Gaussians that can reach each pixel.

    Parameters
    ----------
    gaussians : Gaussians (N)
    camera : Camera
    opacity_bound : (N,) optional upper bound on each Gaussian's opacity; the
        footprint is then cut where ``bound * g < 1/255`` and Gaussians with
        bound < 1/255 are culled. Default: 1 (the opacity-free footprint,
        valid for any opacities in [0, 1]).
    factors : optional :func:`gaussian_factors` of ``gaussians`` (reuse it
        across cameras of one render).
    camera_points : optional (camera-frame centres, ranges) shared by cameras
        with the same pose (see :func:`project`).
    max_contributions : refuse (:class:`RenderLimitError`) when the estimated
        number of contributions exceeds this (last-resort memory guard, about
        20 bytes each; ordinary views up to 2048 wide stay far below it).

    Returns
    -------
    Footprints, sorted by pixel then range (see the class docstring).
    """
    n_all = len(gaussians)
    pose = shared_pose(gaussians, camera, factors, camera_points)
    key, layout, cols, _ = sorted_keys(pose, camera, opacity_cuts(opacity_bound, n_all), max_contributions)
    return _unpack_keys(key, layout, cols, pose, camera)


def _unpack_keys(key, layout, cols: Columns, pose: SharedPose, camera: Camera) -> Footprints:
    """:class:`Footprints` of sorted keys (see :func:`sorted_keys`)."""
    n_all = pose.ranges.size
    ranges_all = np.zeros(n_all, dtype=np.float32)
    ranges_all[cols.index] = cols.ranges
    h, w = camera.height, camera.width
    if key is None:
        return Footprints(np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros(0, np.float32), ranges_all, h, w)
    pixel = layout.pixels(key).astype(np.int32)
    gauss = pose.order.astype(np.int32)[layout.ranks(key)]
    weight = layout.weights(key)
    return Footprints(pixel, gauss, weight, ranges_all, h, w)


@dataclass(frozen=True)
class KeyJob:
    """What the keys of one camera are built from: projected columns, cuts, ranks, boxes, key layout.

    ``cols`` the kept Gaussians' :class:`~.projection.Columns` (n); ``qcut`` (n,) float64
    Mahalanobis cut; ``rank`` (n,) int64 depth rank among all the pose's Gaussians, or among
    these n only (``n_all``: how many are ranked); ``live``
    indices into ``cols`` of the non-empty pixel-space footprints and ``box`` (x0, kx, y0, ky)
    (n,) int64 their pixel boxes; ``polar`` indices into ``cols`` of the polar ERP footprints,
    ``sphere`` their tangent-plane ellipses and ``sphere_box`` their boxes (None without any).
    """

    cols: Columns
    qcut: np.ndarray
    rank: np.ndarray
    live: np.ndarray
    box: tuple
    polar: np.ndarray
    sphere: object
    sphere_box: tuple | None
    layout: KeyLayout
    camera: Camera
    n_all: int


def key_job(pose: SharedPose, camera: Camera, qcut_all: np.ndarray | None,
            columns: Columns | None = None, own_ranks: bool = False, cut_sigma: float | None = None) -> KeyJob | None:
    """The :class:`KeyJob` of ``camera`` (None when no Gaussian projects into it).

    ``columns``: the camera's :func:`~.projection.project_columns` when the caller has them.
    ``cut_sigma``: footprints also end at :func:`~.projection.sigma_cuts` of it (None: ``qcut_all`` alone).
    ``own_ranks``: rank the camera's Gaussians among themselves (the same order; one camera's
    render need not sort all the pose's Gaussians) instead of among all of them.
    Raises :class:`RenderLimitError` when the image and the Gaussian count do not fit the 64-bit key.
    """
    h, w = camera.height, camera.width
    cols = project_columns(pose, camera) if columns is None else columns
    n = cols.index.size
    if n == 0:
        return None
    qcut = np.full(n, Q_MAX) if qcut_all is None else qcut_all[cols.index]
    if cut_sigma is not None:
        qcut = np.minimum(qcut, sigma_cuts(cols.cov_a, cols.cov_b, cols.cov_c, cut_sigma))
    if own_ranks:
        n_all, rank = n, pose.ranks_among(cols.index)
    else:
        n_all, rank = pose.ranges.size, pose.rank[cols.index]

    flat_idx, polar_idx = polar_split(cols.my, cols.cov_c, camera)
    x0, kx, y0, ky = footprint_boxes(cols.mx, cols.my, cols.cov_a, cols.cov_c, camera, np.maximum(qcut, 0.0))
    ok = (kx > 0) & (ky > 0) & (qcut > 0)
    live = flat_idx[ok[flat_idx]] if polar_idx.size else np.flatnonzero(ok)

    # key layout, high to low bits: [pixel | depth rank | (unused) | q], q in the low 32 bits
    pix_bits = max(1, int(np.ceil(np.log2(h * w))))
    rank_bits = max(1, int(np.ceil(np.log2(n_all + 1))))
    q_bits = min(24, 64 - pix_bits - rank_bits)
    if q_bits < 12:
        raise RenderLimitError(f"image {w}x{h} with {n_all} Gaussians exceeds the 64-bit sort key")
    layout = KeyLayout(pix_bits, rank_bits, q_bits, 64 - pix_bits - rank_bits)

    sph, sph_box = None, None
    if polar_idx.size:
        sph = sphere_ellipses(cols, polar_idx, camera, pose.factors[:, cols.index[polar_idx]])
        sph_box = sphere_boxes(sph, camera)
    return KeyJob(cols, qcut, rank, live, (x0, kx, y0, ky), polar_idx, sph, sph_box, layout, camera, n_all)


def job_keys(job: KeyJob, live: np.ndarray, polar: np.ndarray, pixel_mask: np.ndarray | None = None):
    """(keys, job_ranks) of a subset of ``job``'s footprints, keys sorted (None when there are none).

    ``live``: a subset of ``job.live`` (indices into ``job.cols``); ``polar``: positions in
    ``job.polar``. ``pixel_mask`` (H*W,) bool, optional: the keys of pixels it does not mark are
    dropped before the sort when they are many (:data:`MASK_MIN_DROP`), else kept (the caller gives
    them no weight). job_ranks: see :func:`sorted_keys` (None when polar keys are included).
    """
    camera, layout, cols, qcut, rank = job.camera, job.layout, job.cols, job.qcut, job.rank
    h, w = camera.height, camera.width
    keys = []
    job_ranks = None
    if live.size:
        x0, kx, y0, ky = job.box
        flat, job_ranks = _flat_keys(live, cols, qcut, rank, x0, kx, y0, ky, h, w, camera.column_period,
                                     camera.period_start, job.n_all, layout)
        keys.append(flat)
    if polar.size:
        sph, polar_idx = job.sphere, job.polar
        sx0, skx, sy0, sky = (b[polar] for b in job.sphere_box)
        kcx, kcy = _size_class(np.maximum(skx, 1)), _size_class(np.maximum(sky, 1))
        cls = kcx * (1 << 20) + kcy
        grp_order = np.argsort(cls, kind="stable")
        cuts = np.flatnonzero(np.diff(cls[grp_order])) + 1
        for grp in np.split(grp_order, cuts):
            kxc, kyc = int(kcx[grp[0]]), int(kcy[grp[0]])
            step = max(1, _CHUNK_ELEMENTS // (kxc * kyc))
            for start in range(0, grp.size, step):
                sub = grp[start:start + step]
                part = polar[sub]
                box = (sx0[sub], skx[sub], sy0[sub], sky[sub])
                keys.append(sphere_keys(part, polar_idx[part], kxc, kyc, sph, qcut, rank, box, h, w, layout))
    if len(keys) > 1:
        job_ranks = None
    keys = [k for k in keys if k.size]
    if not keys:
        return None, None
    key = np.concatenate(keys) if len(keys) > 1 else keys[0]
    del keys
    if pixel_mask is not None and _mask_drops_many(key, pixel_mask, layout):
        key = key[pixel_mask[layout.pixels(key)]]
        if key.size == 0:
            return None, None
    key.sort(kind="stable")  # timsort: merges the pre-sorted runs (keys are unique: order is the same)
    return key, job_ranks


def _mask_drops_many(key: np.ndarray, pixel_mask: np.ndarray, layout: KeyLayout) -> bool:
    """Whether more than MASK_MIN_DROP of the keys (estimated on every MASK_PROBE_STEP-th) fall outside ``pixel_mask``."""
    probe = np.ascontiguousarray(key[::MASK_PROBE_STEP])
    kept = np.count_nonzero(pixel_mask[layout.pixels(probe)])
    return kept < (1.0 - MASK_MIN_DROP) * probe.size


def sorted_keys(pose: SharedPose, camera: Camera, qcut_all: np.ndarray | None, max_contributions: int):
    """(keys, layout, columns, job_ranks): the sorted uint64 keys ``pixel | rank | q`` of one camera.

    keys is None when nothing is visible. Ranks are the pose's (all N Gaussians).
    job_ranks: the ranks of the Gaussians in the order their keys were built
    (by size class, then box origin), a spatially coherent order for tables
    indexed per contribution; None when some keys came from elsewhere (polar
    ERP footprints). Refuses (:class:`RenderLimitError`) more than about
    ``max_contributions`` keys.
    """
    job = key_job(pose, camera, qcut_all)
    if job is None:
        return None, None, project_columns(pose, camera), None
    _, kx, _, ky = job.box
    est = _estimated_hits(job.cols, job.qcut, job.live, kx, ky, job.sphere_box, max_contributions)
    if est > max_contributions:
        raise RenderLimitError(
            f"footprints need about {est} contributions (> max_contributions={max_contributions}); "
            "reduce the image size or the number/size of Gaussians")
    key, job_ranks = job_keys(job, job.live, np.arange(job.polar.size))
    return key, job.layout, job.cols, job_ranks


def _flat_keys(live, cols: Columns, qcut, rank, x0, kx, y0, ky, h, w, period, s0, n_all, layout):
    """(keys, ranks): keys of the pixel-space footprints ``live`` (indices into ``cols``), block
    after block, and the ranks of those Gaussians in that order.

    The Gaussians are grouped by size class (wrapping ones apart) and, within a
    group, ordered by (box origin row y0, column x0, depth rank): for one fixed
    box offset (oy, ox) the pixel of every in-image element is
    (y0 + oy) * w + x0 + ox, which then increases along the Gaussians (two
    in-image columns differ by less than w), so every offset of a size-class
    block yields an already sorted run of keys and the final sort is a merge
    of a few hundred runs (a stable sort, i.e. timsort, merges them ~2-3x
    faster than sorting at random). Gaussians whose columns wrap around the
    period break that order: they form their own groups. One integer sort
    of packed (group, origin, rank) keys orders them all.
    """
    lkx, lky, lx0, ly0 = kx[live], ky[live], x0[live], y0[live]
    nc = len(_SIZE_CLASSES)
    px = np.searchsorted(_SIZE_CLASSES, np.maximum(lkx, 1))
    py = np.searchsorted(_SIZE_CLASSES, np.maximum(lky, 1))
    in_table = px.max() < nc and py.max() < nc
    if period is not None:
        wraps = (lx0 < s0) | (lx0 + lkx - 1 >= s0 + period)
    else:
        wraps = None
    if in_table:
        px, py = _merge_small_groups(px, py, wraps, nc)
    origin = ly0 * (w + 2 * (period or 0) + 2) + lx0
    origin -= origin.min()
    obits = max(1, int(origin.max()).bit_length())
    rbits = max(1, int(n_all).bit_length())
    cbits = int(nc).bit_length()
    lrank = rank[live]
    if in_table and 2 * cbits + 1 + obits + rbits <= 63:
        grp = px * (1 << cbits) + py
        if wraps is not None:
            grp |= wraps.astype(np.int64) << (2 * cbits)
        okey = (grp << (obits + rbits)) | (origin << rbits) | lrank
        perm = np.argsort(okey)
        del okey, grp
    else:  # sizes beyond the table or too many bits: a lexsort does the same
        kcx, kcy = _size_class(np.maximum(lkx, 1)), _size_class(np.maximum(lky, 1))
        wr = np.zeros(live.size, np.int64) if wraps is None else wraps.astype(np.int64)
        perm = np.lexsort((lrank, origin, kcy, kcx, wr))
    del origin
    sel = live[perm]
    jx0, jkx, jy0, jky = lx0[perm], lkx[perm], ly0[perm], lky[perm]
    mx, my = cols.mx[sel], cols.my[sel]
    ca = cols.con_a[sel].astype(np.float32)
    cb = (2.0 * cols.con_b[sel]).astype(np.float32)
    cc = cols.con_c[sel].astype(np.float32)
    qc = qcut[sel].astype(np.float32)
    rkey = lrank[perm].astype(np.uint64) << np.uint64(layout.rank_shift)
    if in_table:
        kcx_all, kcy_all = _SIZE_CLASSES[px[perm]], _SIZE_CLASSES[py[perm]]
    else:
        kcx_all, kcy_all = _size_class(np.maximum(jkx, 1)), _size_class(np.maximum(jky, 1))
    change = (kcx_all[1:] != kcx_all[:-1]) | (kcy_all[1:] != kcy_all[:-1])
    jw = None
    if wraps is not None:
        jw = wraps[perm]
        change |= jw[1:] != jw[:-1]
    cuts = np.concatenate([[0], np.flatnonzero(change) + 1, [sel.size]])
    # every hit lands in one buffer (no per-block arrays, no concatenation); its size bounds the hits
    buf = np.empty(int(np.sum(kcx_all * kcy_all)), dtype=np.uint64)
    pos = 0
    for g0, g1 in zip(cuts[:-1], cuts[1:]):
        kxc, kyc = int(kcx_all[g0]), int(kcy_all[g0])
        step = max(1, _CHUNK_ELEMENTS // (kxc * kyc))
        for a in range(g0, g1, step):
            s = slice(a, min(g1, a + step))
            pos = class_keys(kxc, kyc, jx0[s], jkx[s], jy0[s], jky[s], mx[s], my[s], ca[s], cb[s], cc[s],
                              qc[s], rkey[s], h, w, period, s0, layout, wrap=jw is not None and bool(jw[g0]),
                              out=buf, pos=pos)
    return buf[:pos], lrank[perm]


def _merge_small_groups(px, py, wraps, nc: int):
    """Size-class indices (px, py) with the Gaussians of small groups (:data:`SMALL_BLOCK`) in coarser classes.

    Twice: the indices of a small group's Gaussians are rounded up to odd (then to 3 mod 4), at most
    ``nc - 1``, so neighbouring classes share a block. A coarser class only pads the block with
    misses: the keys are the same.
    """
    for bits in (1, 3):
        grp = px * nc + py
        if wraps is not None:
            grp += wraps * (nc * nc)
        dense = np.bincount(grp, weights=_SIZE_CLASSES[px] * _SIZE_CLASSES[py])[grp]
        small = dense < SMALL_BLOCK
        if not small.any():
            break
        px = np.where(small, np.minimum(px | bits, nc - 1), px)
        py = np.where(small, np.minimum(py | bits, nc - 1), py)
    return px, py


def _estimated_hits(cols: Columns, qcut: np.ndarray, live, kx, ky, sph_box, limit: int) -> int:
    """Upper estimate of the contributions (= memory) the footprints will produce.

    Pixel-space footprints: the ellipse area ``pi qcut sqrt(det)`` plus its
    bounding-box perimeter (pixels cut by the border), at most the clipped
    box; polar (sphere) footprints: their whole box. Counting dense, size-class
    rounded boxes instead over-counted thin or diagonal ellipses 2-4x and
    refused ordinary 2048-wide views near a wall. The estimate is at most the
    plain box count, so that count is returned when it is within ``limit``.
    """
    box = np.maximum(kx[live], 0).astype(np.float64) * np.maximum(ky[live], 0)
    total = 0
    if sph_box is not None:
        _, skx, _, sky = sph_box
        total += int(np.sum(np.maximum(skx, 0).astype(np.float64) * np.maximum(sky, 0)))
    box_total = float(np.sum(box))
    if int(box_total) + total <= limit:
        return int(box_total) + total
    a, b, c = cols.cov_a[live], cols.cov_b[live], cols.cov_c[live]
    q = np.maximum(qcut[live], 0.0)
    ell = np.pi * q * np.sqrt(np.maximum(a * c - b * b, 0.0)) + 2 * np.sqrt(q) * (np.sqrt(a) + np.sqrt(c)) + 1
    return int(np.sum(np.minimum(box, ell))) + total
