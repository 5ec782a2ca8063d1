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
4. ``max_count`` / ``max_bytes``: keep the Gaussians with the largest
   opacity x footprint solid angle seen from their own reference.

The layout (which view, grid, row, column each Gaussian came from) is a
:class:`Provenance`; the encoder's order is [view][grid][row][col].
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, fields

import numpy as np

from . import geometry as geo
from .gaussians import Gaussians
from .ply import ply_bytes
from .yin_yang import blend_weight_yin

OVERLAP_MODES = ("split", "yin", "off")


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
    max_count, max_bytes: optional cap (None = off); max_bytes counts the PLY.
    """

    min_opacity: float = 1.0 / 255.0
    min_confidence: float = 0.0
    resolve_overlap: str = "split"
    merge_duplicates: bool = True
    duplicate_range_tol: float = 0.05  # 0.1 cost 0.56 dB on m3d with the quality encoder; 0.05 stays within 0.2 dB
    duplicate_footprint_ratio: float = 4.0
    max_count: int | None = None
    max_bytes: int | None = None

    def __post_init__(self) -> None:
        if self.resolve_overlap not in OVERLAP_MODES:
            raise CompactionError(f"resolve_overlap must be one of {OVERLAP_MODES}, got {self.resolve_overlap!r}")
        for name in ("min_opacity", "min_confidence", "duplicate_range_tol"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise CompactionError(f"{name} must be a finite number >= 0, got {v!r}")
        if not (np.isfinite(self.duplicate_footprint_ratio) and self.duplicate_footprint_ratio >= 1):
            raise CompactionError(f"duplicate_footprint_ratio must be >= 1, got {self.duplicate_footprint_ratio!r}")
        for name in ("max_count", "max_bytes"):
            v = getattr(self, name)
            if v is not None and (int(v) != v or v < 0):
                raise CompactionError(f"{name} must be a non-negative integer or null, got {v!r}")

    @classmethod
    def off(cls) -> "CompactionOptions":
        """Every step disabled (compact() then returns its input unchanged)."""
        return cls(min_opacity=0.0, min_confidence=0.0, resolve_overlap="off", merge_duplicates=False)

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
    Gaussians are the full layout in order.
    """

    grids: tuple[str, ...]
    height: int
    width: int
    c2w: np.ndarray
    index: np.ndarray | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "c2w", np.asarray(self.c2w, dtype=np.float64).reshape(-1, 4, 4))
        if self.index is not None:
            object.__setattr__(self, "index", np.asarray(self.index, dtype=np.int64))

    @classmethod
    def from_reconstruction(cls, reconstruction, c2w_a, c2w_b) -> "Provenance":
        """Layout of an :class:`service.encoder.Reconstruction` (range_maps (2, G, H, W))."""
        v, g, h, w = np.shape(reconstruction.range_maps)
        grids = ("erp",) if g == 1 else ("yin", "yang")
        prov = cls(grids, h, w, np.stack([np.asarray(c2w_a), np.asarray(c2w_b)]))
        if len(reconstruction.gaussians) != prov.full_count:
            raise CompactionError(
                f"reconstruction has {len(reconstruction.gaussians)} Gaussians, layout {prov.full_count}: "
                "run the encoder without min_opacity and compact with CompactionOptions.min_opacity instead")
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
        """Provenance of ``gaussians.subset(keep)``."""
        return Provenance(self.grids, self.height, self.width, self.c2w, self.flat_index(n)[keep])


# ---------------------------------------------------------------------------
# Per-step masks
# ---------------------------------------------------------------------------

def overlap_keep_mask(grids: tuple[str, ...], height: int, width: int, mode: str = "split") -> np.ndarray:
    """(G, H, W) bool: grid pixels kept so each direction of a view is covered once.

    "split": a pixel is kept where its own grid has the larger domain margin
    (Yin wins ties), "yin": Yin whole, Yang only outside the Yin domain,
    "off": everything. ERP layouts have no overlap.
    """
    keep = np.ones((len(grids), height, width), dtype=bool)
    if mode == "off" or tuple(grids) != ("yin", "yang"):
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
    s = np.sort(gaussians.scales.astype(np.float64), axis=1)
    return np.sqrt(s[:, 1] * s[:, 2])


def _ranges_from_own_camera(gaussians: Gaussians, view: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    return np.linalg.norm(gaussians.means.astype(np.float64) - c2w[view, :3, 3], axis=1)


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
    view = prov.decode(n)[0]
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
        xs = np.flatnonzero(alive & (view == v))
        if xs.size == 0:
            continue
        for u in range(prov.views):
            if u == v:
                continue
            p_u = geo.world_to_camera(means[xs], prov.c2w[u])
            r_x = np.linalg.norm(p_u, axis=1)
            nearer_u = (r_x < own[xs]) | ((r_x == own[xs]) & (u < v))
            for g, kind in enumerate(prov.grids):
                c, r = geo.project_to_grid(kind, p_u, h, w)
                ci, ri = np.rint(c).astype(np.int64), np.rint(r).astype(np.int64)
                inside = nearer_u & (ci >= 0) & (ci < w) & (ri >= 0) & (ri < h) & (r_x > 0)
                if kind != "erp":
                    inside &= geo.in_grid_domain(kind, p_u)
                slot = ((u * g_count + g) * h + np.clip(ri, 0, h - 1)) * w + np.clip(ci, 0, w - 1)
                ys = np.where(inside, lookup[slot], -1)
                ysafe = np.maximum(ys, 0)
                r_y = np.linalg.norm(means[ysafe] - prov.c2w[u, :3, 3], axis=1)
                err = np.abs(r_y - r_x) / np.maximum(r_x, 1e-12)
                fx, fy = fp[xs], fp[ysafe]
                ok = (ys >= 0) & (err <= range_tol) & (err < best_err[xs])
                ok &= np.maximum(fx, fy) <= footprint_ratio * np.minimum(fx, fy)
                best[xs[ok]] = ys[ok]
                best_err[xs[ok]] = err[ok]
    cand = best >= 0
    drop = cand.copy()
    drop[cand] = ~cand[best[cand]]
    return drop


def cap_keep_mask(gaussians: Gaussians, prov: Provenance, alive: np.ndarray, count: int) -> np.ndarray:
    """(N,) bool: the ``count`` alive Gaussians with the largest opacity x footprint solid angle.

    Solid angle = footprint^2 / range^2 from the Gaussian's own reference
    (world area alone would drop the nearest, largest-on-screen ones first).
    """
    idx = np.flatnonzero(alive)
    if count >= idx.size:
        return alive.copy()
    view = prov.decode(len(gaussians))[0]
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
# Driver
# ---------------------------------------------------------------------------

def compact_index(gaussians: Gaussians, provenance: Provenance, options: CompactionOptions | None = None, *,
                  confidence: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """Indices (ascending) of the Gaussians kept, and the stats dict (see :func:`compact`)."""
    opts = options or CompactionOptions()
    n = len(gaussians)
    provenance.flat_index(n)  # validates the count
    alive = np.ones(n, dtype=bool)
    removed: dict[str, int] = {}
    seconds: dict[str, float] = {}

    def step(name: str, keep: np.ndarray, t0: float) -> None:
        before = int(alive.sum())
        alive[:] &= keep
        removed[name] = before - int(alive.sum())
        seconds[name] = round(time.perf_counter() - t0, 4)

    t0 = time.perf_counter()
    keep = gaussians.opacities >= np.float32(opts.min_opacity) if opts.min_opacity > 0 else np.ones(n, bool)
    if opts.min_confidence > 0:
        if confidence is None:
            raise CompactionError("min_confidence needs per-Gaussian confidence")
        conf = np.asarray(confidence, dtype=np.float32).reshape(-1)
        if conf.size == provenance.full_count and conf.size != n:
            conf = conf[provenance.flat_index(n)]
        if conf.shape != (n,):
            raise CompactionError(f"confidence has {conf.size} values for {n} Gaussians")
        keep &= conf >= np.float32(opts.min_confidence)
    step("min_opacity", keep, t0)

    t0 = time.perf_counter()
    if opts.resolve_overlap != "off":
        _, grid, row, col = provenance.decode(n)
        mask = overlap_keep_mask(provenance.grids, provenance.height, provenance.width, opts.resolve_overlap)
        step("resolve_overlap", mask[grid, row, col], t0)
    else:
        step("resolve_overlap", np.ones(n, bool), t0)

    t0 = time.perf_counter()
    if opts.merge_duplicates and provenance.views > 1:
        drop = duplicate_drop_mask(gaussians, provenance, alive, range_tol=opts.duplicate_range_tol,
                                   footprint_ratio=opts.duplicate_footprint_ratio)
        step("merge_duplicates", ~drop, t0)
    else:
        step("merge_duplicates", np.ones(n, bool), t0)

    t0 = time.perf_counter()
    limit = None
    if opts.max_count is not None:
        limit = int(opts.max_count)
    if opts.max_bytes is not None:
        by_bytes = ply_count_for_bytes(int(opts.max_bytes), gaussians.sh.shape[1])
        limit = by_bytes if limit is None else min(limit, by_bytes)
    if limit is not None:
        step("cap", cap_keep_mask(gaussians, provenance, alive, limit), t0)
    else:
        step("cap", np.ones(n, bool), t0)

    index = np.flatnonzero(alive)
    stats = {"input": n, "output": int(index.size), "removed": removed, "seconds": seconds,
             "options": opts.to_dict()}
    return index, stats


def compact(gaussians: Gaussians, provenance: Provenance, options: CompactionOptions | None = None, *,
            confidence: np.ndarray | None = None) -> tuple[Gaussians, dict]:
    """The Gaussians a scene needs, and how many each step removed.

    Returns (kept Gaussians in their original order, stats) with stats =
    ``{"input": N, "output": M, "removed": {"min_opacity", "resolve_overlap",
    "merge_duplicates", "cap"}: counts, "seconds": per step, "options": ...}``.
    ``provenance.subset(index, N)`` describes the result (see :func:`compact_index`).
    """
    index, stats = compact_index(gaussians, provenance, options, confidence=confidence)
    return gaussians.subset(index), stats
