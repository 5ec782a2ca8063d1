"""Leave out Gaussians a scene does not need (numpy, vectorised).

A two-view reconstruction has one Gaussian per Yin and per Yang pixel of
both views (786,432 at 512x1024). :func:`compact` removes, in this order,
each step switchable in :class:`CompactionOptions`:

1. ``min_opacity`` / ``min_confidence``: Gaussians too transparent (or too
   unconfident) to show. The renderer already skips alpha < 1/255 per pixel,
   so ``min_opacity = 1/255`` only saves their projection and storage.
2. ``resolve_overlap``: the ~6% of each view's sphere covered by both Yin and
   Yang is kept once. ``"split"`` keeps, per direction, the grid whose domain
   margin is larger (the same rule as the renderer's Yin/Yang merge weight,
   :func:`rasterizer.yin_yang.blend_weight_yin` >= 0.5); ``"yin"`` keeps all
   of Yin and Yang only outside the Yin domain.
3. ``merge_duplicates``: a Gaussian whose centre, seen from the *other*
   reference, lands on a pixel whose Gaussian lies at the same range (relative
   tolerance) with a similar footprint is a second sample of the same surface
   point; the one farther from its own camera (the coarser sample) is
   dropped, never both (a dropped Gaussian's partner is always kept).
4. ``merge_smooth``: a 2x2 block of one grid's pixels (with
   ``smooth_levels`` >= 2 also 4x4 of merged 2x2 blocks, ...) whose
   Gaussians are all still there, nearly the same colour and opacity, and
   lie on one plane seen at most 45 degrees off its normal is replaced by
   one moment-matched Gaussian with the block's optical depth
   (:func:`smooth_merge_blocks`). Flat, evenly coloured walls then need a
   quarter of the Gaussians and about half the render contributions.
5. ``max_count`` / ``max_bytes``: keep the Gaussians with the largest
   opacity x footprint solid angle seen from their own reference.

Steps 1-3 and 5 only drop Gaussians; step 4 makes new ones. The output
comes in layout order (a merged block at its top-left pixel). An
environment shell after the pixel-aligned Gaussians (``Provenance.shell``,
:mod:`rasterizer.shell`) is kept as it is, except for steps 1 (opacity) and
5 (the cap counts it), and comes last.

The layout (which view, grid, row, column each Gaussian came from) is a
:class:`Provenance`; the encoder's order is [view][grid][row][col].
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, fields, replace
from functools import lru_cache

import numpy as np

from . import geometry as geo
from .depth_gaussians import SURFEL_SCALE_FACTOR
from .gaussians import SH_C0, Gaussians
from .ply import ply_bytes
from .shell import shell_layout
from .yin_yang import blend_weight_yin

OVERLAP_MODES = ("split", "yin", "off")
#: Largest block side of the smooth-region merge is 2**MAX_SMOOTH_LEVELS pixels.
MAX_SMOOTH_LEVELS = 4


class CompactionError(ValueError):
    """Bad options, or Gaussians that do not match their provenance."""


@dataclass(frozen=True)
class CompactionOptions:
    """Which compaction steps run, and their thresholds (every step can be turned off).

    min_opacity: drop opacity below this (0 = off). min_confidence: drop
    confidence below this (0 = off; needs per-Gaussian confidence).
    resolve_overlap: "split" | "yin" | "off". merge_duplicates: on/off, with
    duplicate_range_tol (relative range difference that is "the same surface")
    and duplicate_footprint_ratio (largest footprint ratio that is "similar").
    merge_smooth: on/off, with smooth_levels (1: 2x2 blocks, 2: also 4x4, ...
    up to 2**4), smooth_colour_tol (largest max - min of each DC colour
    channel in a block), smooth_opacity_tol (max - min opacity),
    smooth_plane_tol (rms distance from the block's plane / range) and
    smooth_max_incidence_deg (largest angle between the plane's normal and
    the ray; also what rejects depth steps). max_count, max_bytes: optional cap (None = off); max_bytes counts the PLY.
    """

    min_opacity: float = 1.0 / 255.0
    min_confidence: float = 0.0
    # Off by default since encoder 0.5.0 (Gaussians of 0.5 pixel pitches): on the dev splits the overlap
    # step cost up to 0.52 dB (zind pano_5) and the duplicate step 0.66 dB (m3d) at the targets, while
    # the smooth merge alone stays within 0.02 dB (docs/bench/compaction.md).
    resolve_overlap: str = "off"
    merge_duplicates: bool = False
    duplicate_range_tol: float = 0.05  # 0.1 cost 0.56 dB on m3d with encoder 0.2.0; 0.05 stayed within 0.2 dB then
    duplicate_footprint_ratio: float = 4.0
    merge_smooth: bool = True
    # 2x2 blocks only. 2 (also 4x4) left 3-16% fewer Gaussians on the dev scenes, but rendered 1-5 dB
    # further from the uncompacted scene (within 0.03 dB of 1 against the target images).
    smooth_levels: int = 1
    # colour 0.06 and incidence 55 deg (were 0.04 / 45, tuned on encoder 0.3.0): with encoder 0.5.0,
    # Gaussians fewer on m3d / zind 2+6 / zind 4+5 37.7 / 30.7 / 45.7% -> 49.2 / 40.5 / 54.2%, target PSNR
    # change worst -0.013 -> -0.069 dB, PSNR against the uncompacted render >= 43 dB; incidence 60 deg
    # made 52 / 46 / 57% but zind pano_6 fell to 34 dB against the uncompacted render.
    smooth_colour_tol: float = 0.06
    smooth_opacity_tol: float = 0.1
    smooth_plane_tol: float = 0.002
    smooth_max_incidence_deg: float = 55.0
    max_count: int | None = None
    max_bytes: int | None = None

    def __post_init__(self) -> None:
        if self.resolve_overlap not in OVERLAP_MODES:
            raise CompactionError(f"resolve_overlap must be one of {OVERLAP_MODES}, got {self.resolve_overlap!r}")
        for name in ("min_opacity", "min_confidence", "duplicate_range_tol", "smooth_colour_tol",
                     "smooth_opacity_tol", "smooth_plane_tol"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise CompactionError(f"{name} must be a finite number >= 0, got {v!r}")
        if not (np.isfinite(self.duplicate_footprint_ratio) and self.duplicate_footprint_ratio >= 1):
            raise CompactionError(f"duplicate_footprint_ratio must be >= 1, got {self.duplicate_footprint_ratio!r}")
        if not (isinstance(self.smooth_levels, (int, np.integer)) and not isinstance(self.smooth_levels, bool)
                and 1 <= self.smooth_levels <= MAX_SMOOTH_LEVELS):
            raise CompactionError(f"smooth_levels must be an integer in 1..{MAX_SMOOTH_LEVELS}, "
                                  f"got {self.smooth_levels!r}")
        if not (np.isfinite(self.smooth_max_incidence_deg) and 0 <= self.smooth_max_incidence_deg <= 90):
            raise CompactionError(f"smooth_max_incidence_deg must be in [0, 90], got {self.smooth_max_incidence_deg!r}")
        for name in ("max_count", "max_bytes"):
            v = getattr(self, name)
            if v is not None and (int(v) != v or v < 0):
                raise CompactionError(f"{name} must be a non-negative integer or null, got {v!r}")

    @classmethod
    def off(cls) -> "CompactionOptions":
        """Every step disabled (compact() then returns its input unchanged)."""
        return cls(min_opacity=0.0, min_confidence=0.0, resolve_overlap="off", merge_duplicates=False,
                   merge_smooth=False)

    @classmethod
    def from_dict(cls, d: dict | None) -> "CompactionOptions":
        """Options from a JSON object (API ``options.compaction``); unknown keys raise."""
        d = dict(d or {})
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise CompactionError(f"unknown compaction option(s) {unknown}; known: {sorted(names)}")
        if "resolve_overlap" in d and d["resolve_overlap"] in (False, None):
            d["resolve_overlap"] = "off"
        elif d.get("resolve_overlap") is True:
            d["resolve_overlap"] = "split"
        return cls(**d)

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class Provenance:
    """Where each Gaussian came from: grid layout [view][grid][row][col] plus poses.

    grids: grid kinds per view, e.g. ("yin", "yang") or ("erp",); height,
    width: size of one grid; c2w: (V, 4, 4) reference poses; index: (N,)
    flat position of each Gaussian in the full layout, or None when the
    Gaussians are the full layout in order; shell: how many Gaussians after
    those are the environment shell (:mod:`rasterizer.shell`), which
    compaction passes through unchanged.
    """

    grids: tuple[str, ...]
    height: int
    width: int
    c2w: np.ndarray
    index: np.ndarray | None = None
    shell: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "c2w", np.asarray(self.c2w, dtype=np.float64).reshape(-1, 4, 4))
        if self.index is not None:
            object.__setattr__(self, "index", np.asarray(self.index, dtype=np.int64))

    @classmethod
    def from_reconstruction(cls, reconstruction, c2w_a, c2w_b) -> "Provenance":
        """Layout of an :class:`service.encoder.Reconstruction` (range_maps (2, G, H, W))."""
        v, g, h, w = np.shape(reconstruction.range_maps)
        grids = ("erp",) if g == 1 else ("yin", "yang")
        shell = int(getattr(reconstruction, "shell", 0))
        prov = cls(grids, h, w, np.stack([np.asarray(c2w_a), np.asarray(c2w_b)]), shell=shell)
        if len(reconstruction.gaussians) != prov.full_count + shell:
            raise CompactionError(
                f"reconstruction has {len(reconstruction.gaussians)} Gaussians, layout {prov.full_count} "
                f"+ shell {shell}: run the encoder without min_opacity and compact with "
                "CompactionOptions.min_opacity instead")
        return prov

    @property
    def views(self) -> int:
        return int(self.c2w.shape[0])

    @property
    def full_count(self) -> int:
        return self.views * len(self.grids) * self.height * self.width

    def flat_index(self, n: int) -> np.ndarray:
        """(n,) flat layout positions of ``n`` Gaussians (checks the count)."""
        if self.index is None:
            if n != self.full_count:
                raise CompactionError(f"{n} Gaussians but the layout has {self.full_count}")
            return np.arange(n, dtype=np.int64)
        if self.index.shape != (n,):
            raise CompactionError(f"provenance index has shape {self.index.shape}, expected ({n},)")
        return self.index

    def decode(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(view, grid, row, col) int arrays of ``n`` Gaussians."""
        flat = self.flat_index(n)
        per_grid = self.height * self.width
        vg, pix = np.divmod(flat, per_grid)
        view, grid = np.divmod(vg, len(self.grids))
        row, col = np.divmod(pix, self.width)
        return view, grid, row, col

    def subset(self, keep: np.ndarray, n: int) -> "Provenance":
        """Provenance of ``gaussians.subset(keep)`` (of the pixel-aligned ones: no shell)."""
        return Provenance(self.grids, self.height, self.width, self.c2w, self.flat_index(n)[keep])


# ---------------------------------------------------------------------------
# Per-step masks
# ---------------------------------------------------------------------------

def overlap_keep_mask(grids: tuple[str, ...], height: int, width: int, mode: str = "split") -> np.ndarray:
    """(G, H, W) bool: grid pixels kept so each direction of a view is covered once (read-only, cached).

    "split": a pixel is kept where its own grid has the larger domain margin
    (Yin wins ties), "yin": Yin whole, Yang only outside the Yin domain,
    "off": everything. ERP layouts have no overlap.
    """
    if mode not in OVERLAP_MODES:
        raise CompactionError(f"resolve_overlap must be one of {OVERLAP_MODES}, got {mode!r}")
    return _overlap_keep_mask(tuple(grids), int(height), int(width), mode)


@lru_cache(maxsize=16)
def _overlap_keep_mask(grids: tuple[str, ...], height: int, width: int, mode: str) -> np.ndarray:
    keep = np.ones((len(grids), height, width), dtype=bool)
    if mode == "off" or tuple(grids) != ("yin", "yang"):
        keep.setflags(write=False)
        return keep
    d_yin = geo.grid_directions("yin", height, width)
    d_yang = geo.grid_directions("yang", height, width)
    if mode == "split":
        keep[0] = blend_weight_yin(d_yin) >= 0.5
        keep[1] = blend_weight_yin(d_yang) < 0.5
    elif mode == "yin":
        keep[1] = ~geo.in_grid_domain("yin", d_yang)
    else:
        raise CompactionError(f"resolve_overlap must be one of {OVERLAP_MODES}, got {mode!r}")
    keep.setflags(write=False)
    return keep


def owner_grid(directions: np.ndarray, mode: str = "split") -> np.ndarray:
    """Index (0 Yin, 1 Yang) of the grid that keeps each camera-frame direction under ``mode``.

    The continuous counterpart of :func:`overlap_keep_mask` (for tests and lookups).
    """
    if mode == "yin":
        return np.where(geo.in_grid_domain("yin", directions), 0, 1)
    return np.where(blend_weight_yin(directions) >= 0.5, 0, 1)


def footprint(gaussians: Gaussians) -> np.ndarray:
    """(N,) tangential size: geometric mean of the two largest scales (world units)."""
    s = gaussians.scales
    a, b, c = s[:, 0], s[:, 1], s[:, 2]
    hi = np.maximum(np.maximum(a, b), c)
    mid = np.maximum(np.minimum(a, b), np.minimum(np.maximum(a, b), c))  # the median (a selection, exact)
    return np.sqrt(mid.astype(np.float64) * hi)


def _ranges_from_own_camera(gaussians: Gaussians, view: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    cam = c2w[:, :3, 3]
    m = gaussians.means
    d = [m[:, k] - np.take(cam[:, k], view) for k in range(3)]  # float64
    return np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])  # np.linalg.norm's order


def _view_of(prov: Provenance, n: int) -> np.ndarray:
    """(n,) reference view of each Gaussian (``prov.decode(n)[0]``, one division)."""
    return prov.flat_index(n) // (len(prov.grids) * prov.height * prov.width)


def duplicate_drop_mask(gaussians: Gaussians, prov: Provenance, alive: np.ndarray, *,
                        range_tol: float = 0.1, footprint_ratio: float = 4.0) -> np.ndarray:
    """(N,) bool: alive Gaussians that duplicate a better-sampled alive Gaussian of the other view.

    Every alive Gaussian x of view v is taken into each other view u; at the
    nearest pixel of each of u's grids, the alive Gaussian y there (if any)
    is a match when ``| |y - C_u| - |x - C_u| | <= range_tol |x - C_u|`` (the
    same surface, and x is not hidden from u) and their footprints differ by
    at most ``footprint_ratio``. x is a candidate when it is nearer to C_u
    than to its own camera C_v (u samples that point more finely; the lower
    view wins ties). The rule depends on position only, so x and y at the
    same point agree on which goes; near the bisecting plane, where they may
    not, a candidate is dropped only if its partner is not a candidate, so
    every dropped Gaussian leaves a kept one in its place.

    (Keeping the smaller *footprint* instead is not consistent: Yin and Yang
    pixels differ in shape, so x -> y and y -> x' both "finer" blocks most
    merges; measured 29% vs 41% removed on m3d_bedroom, same PSNR.)
    """
    n = len(gaussians)
    view = _view_of(prov, n)
    h, w, g_count = prov.height, prov.width, len(prov.grids)
    flat = prov.flat_index(n)
    lookup = np.full(prov.full_count, -1, dtype=np.int64)
    lookup[flat[alive]] = np.flatnonzero(alive)
    fp = footprint(gaussians)
    means = gaussians.means.astype(np.float64)
    own = _ranges_from_own_camera(gaussians, view, prov.c2w)
    best = np.full(n, -1, dtype=np.int64)
    best_err = np.full(n, np.inf)
    for v in range(prov.views):
        xs_v = np.flatnonzero(alive & (view == v))
        if xs_v.size == 0:
            continue
        for u in range(prov.views):
            if u == v:
                continue
            d = np.take(means, xs_v, axis=0) - prov.c2w[u, :3, 3]  # np.take: faster than fancy indexing
            r_all = np.sqrt(np.einsum("ij,ij->i", d, d))
            own_v = np.take(own, xs_v)
            nearer_u = ((r_all < own_v) | ((r_all == own_v) & (u < v))) & (r_all > 0)
            sel = np.flatnonzero(nearer_u)
            xs, r_x = np.take(xs_v, sel), np.take(r_all, sel)
            p_u = np.take(d, sel, axis=0) @ np.ascontiguousarray(prov.c2w[u, :3, :3])
            fx = np.take(fp, xs)
            for g, kind in enumerate(prov.grids):
                ci, ri, inside = _nearest_pixel(kind, p_u, h, w)
                slot = ((u * g_count + g) * h + ri) * w + ci
                ys = np.where(inside, np.take(lookup, slot), -1)
                ysafe = np.maximum(ys, 0)
                err = np.abs(np.take(own, ysafe) - r_x) / r_x  # y belongs to view u: its own range is its range from u
                fy = np.take(fp, ysafe)
                ok = (ys >= 0) & (err <= range_tol) & (err < np.take(best_err, xs))
                ok &= np.maximum(fx, fy) <= footprint_ratio * np.minimum(fx, fy)
                best[xs[ok]] = ys[ok]
                best_err[xs[ok]] = err[ok]
    cand = best >= 0
    drop = cand.copy()
    drop[cand] = ~cand[best[cand]]
    return drop


def _nearest_pixel(kind: str, p: np.ndarray, h: int, w: int):
    """(col, row) of the pixel nearest to camera-frame points ``p``, and whether it is inside the grid.

    The same as :func:`rasterizer.geometry.project_to_grid` + rounding +
    :func:`~rasterizer.geometry.in_grid_domain`, with one arctan2 pair per point.
    """
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    if kind == "yang":  # grid frame M p = (y, x, -z)
        x, y, z = y, x, -z
    lat = np.arctan2(-y, np.hypot(x, z))
    lon = np.arctan2(x, z)
    if kind == "erp":
        col = (lon + np.pi) / (2 * np.pi) * w - 0.5
        row = (np.pi / 2 - lat) / np.pi * h - 0.5
        inside = np.ones(x.shape, dtype=bool)
    else:
        col = (lon + geo.YIN_LON_MAX) / (2 * geo.YIN_LON_MAX) * w - 0.5
        row = (geo.YIN_LAT_MAX - lat) / (2 * geo.YIN_LAT_MAX) * h - 0.5
        inside = (np.abs(lat) <= geo.YIN_LAT_MAX) & (np.abs(lon) <= geo.YIN_LON_MAX)
    ci, ri = np.rint(col).astype(np.int64), np.rint(row).astype(np.int64)
    inside &= (ci >= 0) & (ci < w) & (ri >= 0) & (ri < h)
    return np.clip(ci, 0, w - 1), np.clip(ri, 0, h - 1), inside


def cap_keep_mask(gaussians: Gaussians, prov: Provenance, alive: np.ndarray, count: int) -> np.ndarray:
    """(N,) bool: the ``count`` alive Gaussians with the largest opacity x footprint solid angle.

    Solid angle = footprint^2 / range^2 from the Gaussian's own reference
    (world area alone would drop the nearest, largest-on-screen ones first).
    """
    idx = np.flatnonzero(alive)
    if count >= idx.size:
        return alive.copy()
    view = _view_of(prov, len(gaussians))
    rng = np.maximum(_ranges_from_own_camera(gaussians, view, prov.c2w), 1e-9)
    score = gaussians.opacities.astype(np.float64) * (footprint(gaussians) / rng) ** 2
    keep = np.zeros(len(gaussians), dtype=bool)
    if count > 0:
        top = idx[np.argpartition(-score[idx], count - 1)[:count]]
        keep[top] = True
    return keep


def ply_count_for_bytes(max_bytes: int, sh_coeffs: int) -> int:
    """Largest Gaussian count whose PLY (header included) fits in ``max_bytes``."""
    header = len(ply_bytes(Gaussians.empty(int(round(np.sqrt(sh_coeffs))) - 1)))
    per = 4 * (17 + 3 * (sh_coeffs - 1))
    # the header's vertex count has more digits for larger counts; allow 12
    return max(0, (int(max_bytes) - header - 12) // per)


# ---------------------------------------------------------------------------
# Smooth-region merge
# ---------------------------------------------------------------------------

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


def opacity_depth(alpha: np.ndarray) -> np.ndarray:
    """Li2(alpha): a Gaussian's optical depth -ln(1 - alpha g) integrated over its footprint, per unit area.

    ``int -ln(1 - a exp(-q/2)) dA = 2 pi sigma_1 sigma_2 Li2(a)``; summed over
    overlapping Gaussians it is the mean optical depth of a surface patch.
    """
    return np.interp(np.clip(alpha, 0.0, MERGED_OPACITY_MAX), _LI2_X, _LI2_Y)


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


_SYM = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


# Reductions over a length-3 last axis, column by column (numpy's axis reductions are slow on short rows).
def _sum3(a: np.ndarray) -> np.ndarray:
    return a[..., 0] + a[..., 1] + a[..., 2]


def _max3(a: np.ndarray) -> np.ndarray:
    return np.maximum(np.maximum(a[..., 0], a[..., 1]), a[..., 2])


def _min3(a: np.ndarray) -> np.ndarray:
    return np.minimum(np.minimum(a[..., 0], a[..., 1]), a[..., 2])


def _outer6(d: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(n, 6) w d d^T of vectors d (n, 3)."""
    return np.stack([w * d[:, i] * d[:, j] for i, j in _SYM], axis=1)


def _sym_full(s6: np.ndarray) -> np.ndarray:
    """(n, 3, 3) symmetric matrices from their 6 components."""
    out = np.empty((s6.shape[0], 3, 3))
    for k, (i, j) in enumerate(_SYM):
        out[:, i, j] = s6[:, k]
        out[:, j, i] = s6[:, k]
    return out


def _sym3_eigvals(s6: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Eigenvalues (ascending) of symmetric 3x3 matrices given as 6 components, and the spread p.

    Closed form (trigonometric roots of the characteristic polynomial),
    many times faster than ``np.linalg.eigh`` on small stacked matrices.
    """
    return _eigvals_c(*(s6[:, k] for k in range(6)))


def _smallest_eigenpair(s6: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Smallest eigenvalue, its unit eigenvector and ok-flag of symmetric PSD 3x3 matrices (6 components).

    The eigenvector is the longest cross product of two rows of A - lambda I.
    ok is False where the smallest eigenvalue is (numerically) repeated, so
    the eigenvector, a plane normal here, is not defined.
    """
    lam, mid, _, p = _sym3_eigvals(s6)
    xx, yy, zz, xy, xz, yz = (s6[:, k] for k in range(6))
    r0 = np.stack([xx - lam, xy, xz], axis=1)
    r1 = np.stack([xy, yy - lam, yz], axis=1)
    r2 = np.stack([xz, yz, zz - lam], axis=1)
    cands = np.stack([np.cross(r0, r1), np.cross(r0, r2), np.cross(r1, r2)], axis=1)
    norms = _sum3(cands * cands)
    best = np.argmax(norms, axis=1)
    rows = np.arange(len(best))
    vec, nb = cands[rows, best], np.sqrt(norms[rows, best])
    ok = (p > 0) & (mid - lam > 1e-9 * p) & (nb > 0)
    return np.maximum(lam, 0.0), vec / np.where(nb > 0, nb, 1.0)[:, None], ok


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
    m2 = sum(p.m2 + _outer6(p.mu - mu, p.w) for p in parts)
    return _Units(w, mu, m2, sum(p.cov for p in parts), sum(p.sh for p in parts), sum(p.depth for p in parts),
                  np.minimum.reduce([p.cmin for p in parts]), np.maximum.reduce([p.cmax for p in parts]),
                  np.minimum.reduce([p.amin for p in parts]), np.maximum.reduce([p.amax for p in parts]))


def _rows4(a: np.ndarray) -> np.ndarray:
    """a[0] + a[1] + a[2] + a[3] in that order (the same rounding as summing four member arrays one by one)."""
    return a[0] + a[1] + a[2] + a[3]


def _eigvals_c(xx, yy, zz, xy, xz, yz):
    """:func:`_sym3_eigvals` on the six components as separate arrays."""
    q = (xx + yy + zz) / 3.0
    p2 = (xx - q) ** 2 + (yy - q) ** 2 + (zz - q) ** 2 + 2.0 * (xy * xy + xz * xz + yz * yz)
    p = np.sqrt(p2 / 6.0)
    inv = np.where(p > 0, 1.0 / np.where(p > 0, p, 1.0), 0.0)
    bxx, byy, bzz = (xx - q) * inv, (yy - q) * inv, (zz - q) * inv
    bxy, bxz, byz = xy * inv, xz * inv, yz * inv
    det = bxx * (byy * bzz - byz * byz) - bxy * (bxy * bzz - byz * bxz) + bxz * (bxy * byz - byy * bxz)
    phi = np.arccos(np.clip(det / 2.0, -1.0, 1.0)) / 3.0
    lo = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    hi = q + 2.0 * p * np.cos(phi)
    return lo, 3.0 * q - lo - hi, hi, p


def _plane_ok_c(wsafe, mux, muy, muz, m2, plane_tol: float, cos_incidence: float) -> np.ndarray:
    """Blocks whose (weighted) centres lie on a plane seen at most at the incidence limit.

    Residual = rms distance from the best plane (smallest eigenvalue of the
    scatter m2 / wsafe), relative to the range of the block's centre (mux,
    muy, muz); incidence = angle between that plane's normal and the ray to
    the centre. The incidence limit also rejects depth steps: a block whose
    pixels jump in range fits a plane almost parallel to the rays.

    m2: six (m,) component arrays of the scatter. The cheap tests (spread, repeated eigenvalue, residual)
    run first; the normal (cross products of rows of A - lambda I, the longest one) only for the blocks
    that pass them.
    """
    xx, yy, zz, xy, xz, yz = (c / wsafe for c in m2)
    lam, mid, _, p = _eigvals_c(xx, yy, zz, xy, xz, yz)
    rng = np.sqrt(mux * mux + muy * muy + muz * muz)
    ok = (p > 0) & (mid - lam > 1e-9 * p) & (rng > 0) & (np.maximum(lam, 0.0) <= (plane_tol * rng) ** 2)
    i = np.flatnonzero(ok)
    lam, xx, yy, zz, xy, xz, yz = (a[i] for a in (lam, xx, yy, zz, xy, xz, yz))
    r0 = (xx - lam, xy, xz)
    r1 = (xy, yy - lam, yz)
    r2 = (xz, yz, zz - lam)

    def cross(a, b):
        return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])

    cands = (cross(r0, r1), cross(r0, r2), cross(r1, r2))
    norms = [c[0] * c[0] + c[1] * c[1] + c[2] * c[2] for c in cands]
    # argmax, first of equal maxima
    best1 = norms[1] > norms[0]
    nmax = np.where(best1, norms[1], norms[0])
    best2 = norms[2] > nmax
    nb2 = np.where(best2, norms[2], nmax)
    vec = [np.where(best2, cands[2][k], np.where(best1, cands[1][k], cands[0][k])) for k in range(3)]
    nb = np.sqrt(nb2)
    nbs = np.where(nb > 0, nb, 1.0)
    mux, muy, muz, rng = mux[i], muy[i], muz[i], rng[i]
    dot = (vec[0] / nbs) * mux + (vec[1] / nbs) * muy + (vec[2] / nbs) * muz
    cos_inc = np.abs(dot) / rng
    ok[i] = (nb > 0) & (cos_inc >= cos_incidence)
    return ok


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
                  plane_tol: float, cos_incidence: float, pitch: float):
    """2x2 blocks that merge: (block ids into the (P, H/2, W/2) block grid, their units, (m, 4) member indices).

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
    blk = np.flatnonzero(ok)
    top = _block_tops(n_grids, h, w)[blk]  # layout position of each candidate's top-left pixel
    plane = top // (h * w)
    mem = np.stack([top, top + 1, top + w, top + w + 1])  # (4, m) layout positions
    if slot is not None:
        mem = slot[mem]
    cams = np.repeat(prov.c2w[:, :3, 3], len(prov.grids), axis=0)
    parts = [_level1_chunk(gaussians, mem[:, i:i + _CHUNK], cams[plane[i:i + _CHUNK]], plane_tol, cos_incidence, pitch)
             for i in range(0, blk.size, _CHUNK)]
    sel = np.concatenate([p[0] for p in parts]) if parts else np.zeros(0, bool)
    b = blk[sel]
    k = gaussians.sh.shape[1]
    cat = (lambda j, shape: np.concatenate([p[j] for p in parts]) if parts else np.zeros(shape))
    units = _Units(cat(1, (0,)), cat(2, (0, 3)), cat(3, (0, 6)), cat(4, (0, 6)), cat(5, (0, k, 3)), cat(6, (0,)),
                   cmin[:, b].T.astype(np.float64), cmax[:, b].T.astype(np.float64),
                   amin.reshape(-1)[b].astype(np.float64), amax.reshape(-1)[b].astype(np.float64))
    return b, units, mem[:, sel].T


#: Candidate blocks per chunk of :func:`_level1_chunk` (its float64 temporaries then stay in the CPU cache).
_CHUNK = 16384


def _level1_chunk(gaussians: Gaussians, mem: np.ndarray, cam: np.ndarray, plane_tol: float, cos_incidence: float,
                  pitch: float):
    """Plane test and moment sums of candidate 2x2 blocks with member indices ``mem`` (4, m).

    Returns (ok mask (m,), and for the blocks that merge: w, mu (., 3), m2 (., 6), weighted covariance
    sum (., 6), weighted SH sum (., K, 3), optical depth sum), the same float64 arithmetic as
    :func:`_outer6` / :func:`_plane_ok_c` / :func:`quat_to_rotmat` / :func:`_render_area` per member.
    """
    sc = np.take(gaussians.scales, mem, axis=0)  # (4, m, 3) float32 (np.take: faster than fancy indexing)
    s0, s1, s2 = (sc[..., k].astype(np.float64) for k in range(3))
    area = s0 * s1 * s2 / np.maximum(np.minimum(np.minimum(s0, s1), s2), 1e-300)  # two largest
    opa = np.take(gaussians.opacities, mem).astype(np.float64)
    wk = opa * area
    mp = np.take(gaussians.means, mem, axis=0)
    px, py, pz = (mp[..., k] - cam[:, k] for k in range(3))  # float64, camera-relative
    wt = _rows4(wk)
    wsafe = np.where(wt > 0, wt, 1.0)
    mux, muy, muz = (_rows4(wk * pc) / wsafe for pc in (px, py, pz))
    dx, dy, dz = px - mux, py - muy, pz - muz
    tx, ty = wk * dx, wk * dy
    m2 = [_rows4(tx * dx), _rows4(ty * dy), _rows4((wk * dz) * dz), _rows4(tx * dy), _rows4(tx * dz), _rows4(ty * dz)]
    good = (wt > 0) & _plane_ok_c(wsafe, mux, muy, muz, m2, plane_tol, cos_incidence)
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
    for c, (i, j) in enumerate(_SYM):
        cov[:, c] = _rows4(wk * (rs[i][0] * r[j][0] + rs[i][1] * r[j][1] + rs[i][2] * r[j][2]))
    shs = _rows4(wk[..., None, None] * np.take(gaussians.sh, m, axis=0).astype(np.float64))
    rng = np.sqrt(px ** 2 + py ** 2 + pz ** 2)
    s_max = np.maximum(np.maximum(s0, s1), s2)
    s_min = np.minimum(np.minimum(s0, s1), s2)
    s_mid = s0 + s1 + s2 - s_max - s_min
    low = COVERAGE_LOW_PASS * (rng * pitch) ** 2
    depth = _rows4(np.sqrt((s_mid**2 + low) * (s_max**2 + low)) * opacity_depth(opa))
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
    s_max, s_min = _max3(scales), _min3(scales)
    s_mid = _sum3(scales) - s_max - s_min
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
        lam0, n, _ = _smallest_eigenpair(spread)
        inplane_spread = 0.5 * (spread[:, 0] + spread[:, 1] + spread[:, 2] - lam0)
        nn = np.stack([n[:, i] * n[:, j] for i, j in _SYM], axis=1)
        cur = 0.5 * (cov[:, 0] + cov[:, 1] + cov[:, 2] - (nn * cov * np.array([1, 1, 1, 2, 2, 2])).sum(1))
        target = MIN_OVERLAP**2 * 12.0 * side**2 / (side**2 - 1) * inplane_spread
        delta = np.maximum(target - cur, 0.0)
        eye = np.array([1.0, 1, 1, 0, 0, 0])
        cov = cov + delta[:, None] * (eye - nn)
    return cov


def _needed_depth(u: _Units, pitch: float, side: int = 1) -> np.ndarray:
    """Li2(opacity) a merged unit needs to keep its optical depth (> Li2(0.99): it cannot)."""
    lo, mid, hi, _ = _sym3_eigvals(_merged_cov6(u, side))
    sig = np.sqrt(np.maximum(np.stack([lo, mid, hi], axis=1), 0.0))
    rng = np.sqrt(_sum3(u.mu * u.mu))
    return u.depth / np.maximum(_render_area(sig, rng * pitch), 1e-300)


def _scale_rotation6(cov6: np.ndarray, min_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`rasterizer.gaussians.scale_rotation_from_covariance` of covariances given as 6 components.

    The same eigen-decomposition (``np.linalg.eigh``, so the same eigenvector
    signs and quaternions); the reflection test uses the triple product of
    the orthonormal eigenvectors instead of an LU determinant (same sign).
    """
    evals, r = np.linalg.eigh(_sym_full(cov6))
    det = (r[:, 0, 0] * (r[:, 1, 1] * r[:, 2, 2] - r[:, 1, 2] * r[:, 2, 1])
           - r[:, 0, 1] * (r[:, 1, 0] * r[:, 2, 2] - r[:, 1, 2] * r[:, 2, 0])
           + r[:, 0, 2] * (r[:, 1, 0] * r[:, 2, 1] - r[:, 1, 1] * r[:, 2, 0]))
    r[:, :, 2] *= np.where(det < 0, -1.0, 1.0)[:, None]
    return np.sqrt(np.maximum(evals, min_scale**2)), _rotmat_to_quat(r)


def _rotmat_to_quat(r: np.ndarray) -> np.ndarray:
    """:func:`rasterizer.gaussians.rotmat_to_quat` (the same arithmetic), component by component."""
    m00, m11, m22 = r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]
    trace = m00 + m11 + m22
    d21, d02, d10 = r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] - r[:, 0, 1]
    s01, s02, s12 = r[:, 0, 1] + r[:, 1, 0], r[:, 0, 2] + r[:, 2, 0], r[:, 1, 2] + r[:, 2, 1]
    cand = ((1 + trace, d21, d02, d10),
            (d21, 1 + m00 - m11 - m22, s01, s02),
            (d02, s01, 1 - m00 + m11 - m22, s12),
            (d10, s02, s12, 1 - m00 - m11 + m22))
    # argmax over (trace, m00, m11, m22), the first of equal maxima
    which = np.zeros(trace.shape, dtype=np.intp)
    cur = trace
    for k, d in ((1, m00), (2, m11), (3, m22)):
        gt = d > cur
        which[gt] = k
        cur = np.where(gt, d, cur)
    q = [np.choose(which, [c[k] for c in cand]) for k in range(4)]
    norm = np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    sign = np.where(q[0] / norm < 0, -1.0, 1.0)
    out = np.empty(trace.shape + (4,))
    for k in range(4):
        out[:, k] = q[k] / norm * sign
    return out


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
    rng = np.sqrt(_sum3(mu * mu))
    scales, quats = _scale_rotation6(_merged_cov6(u, side), min_scale=1e-12)
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
                        max_incidence_deg: float = CompactionOptions.smooth_max_incidence_deg) -> SmoothMerge:
    """Replace 2x2 (then 4x4, ... up to 2**levels) blocks of one grid's pixels by one Gaussian each.

    A block merges when all its pixels are alive, every DC colour channel
    varies by at most ``colour_tol`` and opacity by at most ``opacity_tol``
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
            chosen, units, children = _level1_merge(gaussians, prov, alive, colour_tol, opacity_tol, plane_tol,
                                                    cos_inc, pitch)
        else:
            ids = np.full(ids_shape[0] * ids_shape[1] * ids_shape[2], -1, dtype=np.int64)
            ids[per_level[-1][0]] = np.arange(per_level[-1][0].size)
            blocks = _blocks(ids.reshape(ids_shape)).reshape(-1, 4)
            cand = np.flatnonzero(np.all(blocks >= 0, axis=1))
            u = _combine(per_level[-1][1], blocks[cand])
            ok = ((_max3(u.cmax - u.cmin) <= np.float32(colour_tol / SH_C0))
                  & (u.amax - u.amin <= np.float32(opacity_tol)) & (u.w > 0))
            ok &= _plane_ok_c(np.where(u.w > 0, u.w, 1.0), u.mu[:, 0], u.mu[:, 1], u.mu[:, 2],
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
    merged = Gaussians.concatenate(parts) if parts else Gaussians.empty(gaussians.sh_degree)
    if parts and merged.sh.shape[1] != gaussians.sh.shape[1]:
        merged = merged.with_(sh=np.pad(merged.sh, ((0, 0), (0, gaussians.sh.shape[1] - merged.sh.shape[1]), (0, 0))))
    return SmoothMerge(drop, merged, np.concatenate(index) if index else np.zeros(0, np.int64),
                       np.concatenate(side) if side else np.zeros(0, np.int64), dict(sorted(counts.items())))


# ---------------------------------------------------------------------------
# Driver
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class CompactionResult:
    """What :func:`compact_result` returns.

    gaussians: the output (kept inputs and merged blocks, in layout order);
    provenance: its layout positions (a merged block's is its top-left
    pixel); block: (M,) side of the pixel block each output Gaussian stands
    for (1 = an input kept as it is); index: input indices of the inputs kept
    as they are (ascending); stats: see :func:`compact`.
    """

    gaussians: Gaussians
    provenance: Provenance
    block: np.ndarray
    index: np.ndarray
    stats: dict


def _interleave(gaussians: Gaussians, index: np.ndarray, pos: np.ndarray, merged: SmoothMerge):
    """Kept inputs ``gaussians[index]`` (layout positions ``pos``) and the merged blocks, in layout order.

    The same as concatenating both and a stable argsort by position; when both position lists are
    already ascending (the usual case) each output row is written once, at its merged place.
    """
    m_pos = merged.index
    if not (np.all(pos[1:] > pos[:-1]) and np.all(m_pos[1:] > m_pos[:-1])):
        out_g = Gaussians.concatenate([gaussians.subset(index), merged.gaussians])
        out_pos = np.concatenate([pos, m_pos])
        out_block = np.concatenate([np.ones(index.size, dtype=np.int64), merged.block])
        order = np.argsort(out_pos, kind="stable")
        return out_g.subset(order), out_pos[order], out_block[order]
    total = index.size + m_pos.size
    m_slot = np.searchsorted(pos, m_pos, side="right") + np.arange(m_pos.size)  # inputs first on equal positions
    is_m = np.zeros(total, dtype=bool)
    is_m[m_slot] = True
    in_slot = np.flatnonzero(~is_m)
    mg = merged.gaussians
    cols = []
    for f in fields(Gaussians):
        src, add = getattr(gaussians, f.name), getattr(mg, f.name)
        if f.name == "sh" and add.shape[1] != src.shape[1]:
            k = max(add.shape[1], src.shape[1])
            src = np.pad(src, ((0, 0), (0, k - src.shape[1]), (0, 0)))
            add = np.pad(add, ((0, 0), (0, k - add.shape[1]), (0, 0)))
        out = np.empty((total,) + src.shape[1:], dtype=np.float32)
        out[in_slot] = np.take(src, index, axis=0)
        out[m_slot] = add
        cols.append(out)
    out_pos = np.empty(total, dtype=np.int64)
    out_pos[in_slot] = pos
    out_pos[m_slot] = m_pos
    out_block = np.ones(total, dtype=np.int64)
    out_block[m_slot] = merged.block
    return Gaussians(*cols), out_pos, out_block


def compact_result(gaussians: Gaussians, provenance: Provenance, options: CompactionOptions | None = None, *,
                   confidence: np.ndarray | None = None) -> CompactionResult:
    """Run the enabled steps in order (see the module docstring)."""
    opts = options or CompactionOptions()
    if provenance.shell:
        return _compact_with_shell(gaussians, provenance, opts, confidence)
    n = len(gaussians)
    flat = provenance.flat_index(n)  # validates the count
    alive = np.ones(n, dtype=bool)
    removed: dict[str, int] = {}
    seconds: dict[str, float] = {}

    def step(name: str, keep: np.ndarray | None, t0: float) -> None:
        before = int(alive.sum())
        if keep is not None:
            alive[:] &= keep
        removed[name] = before - int(alive.sum())
        seconds[name] = round(time.perf_counter() - t0, 4)

    t0 = time.perf_counter()
    keep = gaussians.opacities >= np.float32(opts.min_opacity) if opts.min_opacity > 0 else None
    if opts.min_confidence > 0:
        if confidence is None:
            raise CompactionError("min_confidence needs per-Gaussian confidence")
        conf = np.asarray(confidence, dtype=np.float32).reshape(-1)
        if conf.size == provenance.full_count and conf.size != n:
            conf = conf[flat]
        if conf.shape != (n,):
            raise CompactionError(f"confidence has {conf.size} values for {n} Gaussians")
        sure = conf >= np.float32(opts.min_confidence)
        keep = sure if keep is None else keep & sure
    step("min_opacity", keep, t0)

    t0 = time.perf_counter()
    if opts.resolve_overlap != "off" and tuple(provenance.grids) == ("yin", "yang"):
        grids, h, w = tuple(provenance.grids), provenance.height, provenance.width
        local = flat % (len(grids) * h * w)
        keep = overlap_keep_mask(grids, h, w, opts.resolve_overlap).reshape(-1)[local]
        step("resolve_overlap", keep, t0)
    else:
        step("resolve_overlap", None, t0)

    t0 = time.perf_counter()
    if opts.merge_duplicates and provenance.views > 1:
        drop = duplicate_drop_mask(gaussians, provenance, alive, range_tol=opts.duplicate_range_tol,
                                   footprint_ratio=opts.duplicate_footprint_ratio)
        step("merge_duplicates", ~drop, t0)
    else:
        step("merge_duplicates", None, t0)

    t0 = time.perf_counter()
    smooth_stats = {"merged": 0, "added": 0, "blocks": {}}
    merged = None
    if opts.merge_smooth:
        sm = smooth_merge_blocks(gaussians, provenance, alive, levels=opts.smooth_levels,
                                 colour_tol=opts.smooth_colour_tol, opacity_tol=opts.smooth_opacity_tol,
                                 plane_tol=opts.smooth_plane_tol, max_incidence_deg=opts.smooth_max_incidence_deg)
        alive &= ~sm.drop
        merged = sm
        smooth_stats = {"merged": int(sm.drop.sum()), "added": len(sm.gaussians),
                        "blocks": {str(k): v for k, v in sm.blocks.items()}}
    removed["merge_smooth"] = smooth_stats["merged"] - smooth_stats["added"]
    seconds["merge_smooth"] = round(time.perf_counter() - t0, 4)

    t0 = time.perf_counter()
    index = np.flatnonzero(alive)
    out_pos = flat[index]
    if merged is not None and len(merged.gaussians):
        out_g, out_pos, out_block = _interleave(gaussians, index, out_pos, merged)
    else:
        out_g = gaussians.subset(index)
        out_block = np.ones(index.size, dtype=np.int64)
    out_prov = Provenance(provenance.grids, provenance.height, provenance.width, provenance.c2w, out_pos)
    seconds["assemble"] = round(time.perf_counter() - t0, 4)

    t0 = time.perf_counter()
    limit = _count_limit(opts, gaussians.sh.shape[1])
    removed["cap"] = 0
    if limit is not None and limit < len(out_g):
        kept = np.flatnonzero(cap_keep_mask(out_g, out_prov, np.ones(len(out_g), bool), limit))
        removed["cap"] = len(out_g) - kept.size
        kept_inputs = out_block[kept] == 1
        index = index[np.isin(flat[index], out_pos[kept][kept_inputs])]
        out_g, out_pos, out_block = out_g.subset(kept), out_pos[kept], out_block[kept]
        out_prov = Provenance(provenance.grids, provenance.height, provenance.width, provenance.c2w, out_pos)
    seconds["cap"] = round(time.perf_counter() - t0, 4)

    stats = {"input": n, "output": len(out_g), "removed": removed, "merge_smooth": smooth_stats,
             "seconds": seconds, "options": opts.to_dict()}
    return CompactionResult(out_g, out_prov, out_block, index, stats)


def _count_limit(opts: CompactionOptions, sh_coeffs: int) -> int | None:
    """The Gaussian count ``max_count`` / ``max_bytes`` allow (None: no cap)."""
    limit = None if opts.max_count is None else int(opts.max_count)
    if opts.max_bytes is not None:
        by_bytes = ply_count_for_bytes(int(opts.max_bytes), sh_coeffs)
        limit = by_bytes if limit is None else min(limit, by_bytes)
    return limit


def _compact_with_shell(gaussians: Gaussians, provenance: Provenance, opts: CompactionOptions,
                        confidence: np.ndarray | None) -> CompactionResult:
    """Compact the pixel-aligned Gaussians; the shell after them is appended unchanged (its blocks'
    top-left pixels as provenance, :func:`rasterizer.shell.shell_layout`)."""
    n, count = len(gaussians), provenance.shell
    if n < count:
        raise CompactionError(f"{n} Gaussians but a shell of {count}")
    index, block = shell_layout(provenance.views, len(provenance.grids), provenance.height, provenance.width)
    if index.size != count:
        raise CompactionError(f"shell of {count} Gaussians, layout {index.size}")
    shell = gaussians.subset(np.arange(n - count, n))
    keep = shell.opacities >= np.float32(opts.min_opacity) if opts.min_opacity > 0 else np.ones(count, bool)
    limit = _count_limit(opts, gaussians.sh.shape[1])
    front_opts = opts
    capped = 0
    if limit is not None:  # the cap counts the shell too; a cap below the shell's size thins it evenly
        kept = np.flatnonzero(keep)
        if kept.size > limit:
            thin = np.zeros(count, bool)
            thin[kept[np.linspace(0, kept.size - 1, limit).astype(np.int64)]] = True
            capped, keep = kept.size - int(thin.sum()), thin
        front_opts = replace(opts, max_count=limit - int(keep.sum()), max_bytes=None)
    res = compact_result(gaussians.subset(np.arange(n - count)), replace(provenance, shell=0), front_opts,
                         confidence=confidence)
    out_g = Gaussians.concatenate([res.gaussians, shell.subset(keep)])
    pos = np.concatenate([res.provenance.flat_index(len(res.gaussians)), index[keep]])
    removed = dict(res.stats["removed"])
    removed["min_opacity"] += int(count - capped - keep.sum())
    removed["cap"] += capped
    stats = {**res.stats, "input": n, "output": len(out_g), "removed": removed, "shell": int(keep.sum()),
             "options": opts.to_dict()}
    return CompactionResult(out_g, Provenance(provenance.grids, provenance.height, provenance.width, provenance.c2w, pos),
                            np.concatenate([res.block, block[keep]]), res.index, stats)


def compact_index(gaussians: Gaussians, provenance: Provenance, options: CompactionOptions | None = None, *,
                  confidence: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """Indices (ascending) of the inputs kept as they are, and the stats dict (see :func:`compact`).

    Without ``merge_smooth`` these are exactly the output; with it the merged
    blocks come in addition (:func:`compact_result` has both).
    """
    res = compact_result(gaussians, provenance, options, confidence=confidence)
    return res.index, res.stats


def compact(gaussians: Gaussians, provenance: Provenance, options: CompactionOptions | None = None, *,
            confidence: np.ndarray | None = None) -> tuple[Gaussians, dict]:
    """The Gaussians a scene needs, and how many each step removed.

    Returns (Gaussians in layout order, stats) with stats = ``{"input": N,
    "output": M, "removed": {"min_opacity", "resolve_overlap",
    "merge_duplicates", "merge_smooth", "cap"}: counts (merge_smooth: inputs
    merged minus merged Gaussians added, so the counts sum to N - M),
    "merge_smooth": {"merged", "added", "blocks": {side: count}}, "seconds":
    per step (and "assemble", building the output), "options": ...}``. Without ``merge_smooth`` the output is a
    subset of the input in its original order.
    """
    res = compact_result(gaussians, provenance, options, confidence=confidence)
    return res.gaussians, res.stats
