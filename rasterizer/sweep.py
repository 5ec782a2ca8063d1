"""Pose-dependent inputs of the encoder's ONNX graph, computed in numpy.

The sphere sweep needs, for every target pixel and depth candidate, where
that 3D point lands in the *other* camera's grids. This depends only on the
two poses, the grid sizes and the candidates, so it is computed here (float32,
vectorised) instead of inside the graph: no matrix inverse, no ``atan2`` at
singular points and no data-dependent shapes in ONNX (design doc
ecosystem-reference E).

Layout of the arrays fed to the graph (G = 2 grids ``("yin", "yang")`` or 1
grid ``("erp",)``; D planes; feature grid h x w):

==============  ======================  ==========================================
name            shape                   meaning
==============  ======================  ==========================================
``warp_grids``  (2, G, D, h, w, 2)      [direction][target grid]: ``grid_sample``
                                        coordinates (x, y), ``align_corners=False``,
                                        in the *stacked source* (below);
                                        direction 0 = target A / source B,
                                        1 = target B / source A. ERP sources are
                                        addressed in the source padded by
                                        :data:`ERP_PAD` columns on each side
                                        (circular wrap in longitude).
``rel_rt``      (2, 3, 4)               [R | t] target camera -> source camera.
``inv_depths``  (D,)                    candidate inverse ranges (1/m),
                                        ascending: 1/far ... 1/near, uniform
                                        in inverse range
                                        (:func:`inverse_depth_candidates`).
``c2w``         (2, 4, 4)               camera-to-world of A and B (OpenCV).
``cam_quats``   (2, 4)                  (w, x, y, z) of the c2w rotations.
==============  ======================  ==========================================

The stacked source of Yin/Yang models is one (2h + 2, w) image: the source view's Yin grid, its last
row repeated, Yang's first row repeated, then Yang (:func:`stacked_rows`). Each candidate point is
sampled once, in Yin where its direction lies in Yin's domain, else in Yang (the two cover the
sphere); the repeated rows keep every bilinear tap inside the grid it was meant for. This is the
paper's mask blend (eq. 4) with Yang's mask zeroed where Yin's is 1: half the samples of reading
both grids and averaging their 6% overlap.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

from .gaussians import rotmat_to_quat
from .geometry import YIN_LAT_MAX, YIN_LON_MAX, grid_directions, rigid_inverse
from .lru import LRUCache

#: Names of the encoder graph's inputs and outputs, in order: the contract between
#: :mod:`export` (which writes the graph) and :mod:`service.encoder` (which feeds it).
INPUT_NAMES = ("erp_a", "erp_b", "warp_grids", "rel_rt", "inv_depths", "c2w", "cam_quats")
OUTPUT_NAMES = ("means", "scales", "quats", "opacities", "sh_dc", "range_maps", "confidence", "matches")
#: Dimensions of ``warp_grids`` (table above); a model built for another layout cannot take these inputs.
WARP_GRIDS_RANK = 6

#: Columns of circular padding added on each side of an ERP before sampling.
ERP_PAD = 2

#: Below this baseline (metres, or scene units) depth cannot be triangulated.
MIN_BASELINE = 1e-4
#: Largest camera coordinate and sweep range (scene units): float32 positions, scales and
#: their squares stay finite and resolvable.
MAX_SCENE_EXTENT = 1e6
#: float32 positions of the scene must resolve this fraction of the baseline.
POSITION_RESOLUTION = 1e-3
#: near/far bounds in units of the baseline (the sweep's inverse depths stay finite in float32).
MIN_NEAR_PER_BASELINE = 1e-5
MAX_FAR_PER_BASELINE = 1e7


class SweepRangeError(ValueError):
    """Cameras or a sweep range the encoder cannot resolve (too far, too small, too wide)."""


def distinct_numbers(value: float, limit: float) -> tuple[str, str]:
    """``value`` and ``limit`` printed with the fewest significant digits (3 or more) that tell them apart,
    so that a message about a value just beyond its limit does not print the same number twice."""
    for digits in range(3, 18):
        shown = f"{value:.{digits}g}", f"{limit:.{digits}g}"
        if shown[0] != shown[1]:
            return shown
    return repr(float(value)), repr(float(limit))


def check_scene_scale(c2w_a: np.ndarray, c2w_b: np.ndarray, near: float | None = None,
                      far: float | None = None) -> None:
    """Raise :class:`SweepRangeError` when float32 Gaussians could not represent the scene.

    Checks the camera coordinates and baseline against :data:`MAX_SCENE_EXTENT`, that float32
    positions near the cameras resolve :data:`POSITION_RESOLUTION` of the baseline, and an
    explicit near/far against :data:`MIN_NEAR_PER_BASELINE` / :data:`MAX_FAR_PER_BASELINE`.
    """
    centres = np.stack([np.asarray(c2w_a, dtype=np.float64)[:3, 3], np.asarray(c2w_b, dtype=np.float64)[:3, 3]])
    b = baseline(c2w_a, c2w_b)
    reach = float(np.abs(centres).max())
    if not (np.isfinite(reach) and reach <= MAX_SCENE_EXTENT and b <= MAX_SCENE_EXTENT):
        limit = distinct_numbers(reach if not reach <= MAX_SCENE_EXTENT else b, MAX_SCENE_EXTENT)[1]
        raise SweepRangeError(f"camera positions and the baseline must lie within {limit} of the origin "
                              f"(got {distinct_numbers(reach, MAX_SCENE_EXTENT)[0]}, "
                              f"baseline {distinct_numbers(b, MAX_SCENE_EXTENT)[0]})")
    step = float(np.spacing(np.float32(reach + FAR_PER_BASELINE * b)))
    if step > POSITION_RESOLUTION * b:
        raise SweepRangeError(f"the cameras are {reach:.3g} from the origin but only {b:.3g} apart: float32 "
                              f"positions there are {step:.3g} apart, coarser than {POSITION_RESOLUTION:g} of the "
                              "baseline; move the origin near the cameras")
    if near is not None and not near >= MIN_NEAR_PER_BASELINE * b:
        raise SweepRangeError(f"near={near:.3g} is below {MIN_NEAR_PER_BASELINE:g} x the baseline ({b:.3g})")
    if far is not None and not far <= min(MAX_FAR_PER_BASELINE * b, MAX_SCENE_EXTENT):
        shown_far, limit = distinct_numbers(far, min(MAX_FAR_PER_BASELINE * b, MAX_SCENE_EXTENT))
        raise SweepRangeError(f"far={shown_far} is beyond {limit}: at most {MAX_FAR_PER_BASELINE:g} x the baseline "
                              f"({b:.3g}) and {MAX_SCENE_EXTENT:g}")


def grids_for_mode(erp_encoder: bool) -> tuple[str, ...]:
    """Grid kinds the encoder works on: ``("erp",)`` or ``("yin", "yang")``."""
    return ("erp",) if erp_encoder else ("yin", "yang")


def baseline(c2w_a: np.ndarray, c2w_b: np.ndarray) -> float:
    """Distance between the two camera centres."""
    return float(np.linalg.norm(np.asarray(c2w_a)[:3, 3] - np.asarray(c2w_b)[:3, 3]))


#: Default sweep range in units of the baseline b: near = NEAR_PER_BASELINE * b,
#: far = FAR_PER_BASELINE * b (see :func:`default_near_far`).
NEAR_PER_BASELINE = 0.3
FAR_PER_BASELINE = 20.0


def default_near_far(c2w_a: np.ndarray, c2w_b: np.ndarray, *, near_ratio: float = NEAR_PER_BASELINE,
                     far_ratio: float = FAR_PER_BASELINE) -> tuple[float, float]:
    """Sweep range proportional to the baseline b: (near_ratio b, far_ratio b).

    Pure proportionality makes the encoder equivariant to a global scale of the scene (poses and
    geometry scaled together give the same planes in units of b, hence the same warp grids and the same
    images). The candidates are uniform in inverse range from 0.3 b (:func:`inverse_depth_candidates`):
    their density at the near end keeps thin near objects (lamps, chair and table legs) on planes; a nearer
    near plane or a spacing uniform in the parallax angle spreads the 64 planes more evenly over the far
    room but leaves those objects between planes, and selections on them lose half their IoU
    (docs/design.md).
    """
    if not (0 < near_ratio < far_ratio) or not np.isfinite(far_ratio):
        raise ValueError(f"need 0 < near_ratio < far_ratio < inf, got {near_ratio}, {far_ratio}")
    b = baseline(c2w_a, c2w_b)
    return float(near_ratio * b), float(far_ratio * b)


def inverse_depth_candidates(near: float, far: float, num_planes: int) -> np.ndarray:
    """D inverse ranges between 1/far and 1/near, ascending, float32, uniform in inverse range.

    The uniform spacing is what the encoder's graph expects (``export.readout``): a plane step is one
    constant in inverse range. Its density at the near end is what thin near objects need (docs/design.md,
    "Where the sweep's planes fall").
    """
    if not (0 < near < far) or not np.isfinite(far):
        raise ValueError(f"need 0 < near < far < inf, got near={near}, far={far}")
    if num_planes < 2:
        raise ValueError(f"need at least 2 planes, got {num_planes}")
    return np.linspace(1.0 / far, 1.0 / near, num_planes).astype(np.float32)


def relative_pose(c2w_target: np.ndarray, c2w_source: np.ndarray) -> np.ndarray:
    """4x4 transform from target-camera coordinates to source-camera coordinates."""
    return rigid_inverse(c2w_source) @ np.asarray(c2w_target, dtype=np.float64)


def normalised_coords(kind: str, col: np.ndarray, row: np.ndarray, height: int, width: int) -> np.ndarray:
    """``grid_sample`` (x, y), align_corners=False, of pixel coords (centre of c at c).

    For ERP the x coordinate addresses the source padded by :data:`ERP_PAD`
    columns each side, and longitudes are wrapped into that padded range.
    """
    if kind == "erp":
        col = np.mod(col + 0.5, width) - 0.5  # wrap into [-0.5, W - 0.5)
        x = (2.0 * (col + ERP_PAD) + 1.0) / (width + 2 * ERP_PAD) - 1.0
    else:
        x = (2.0 * col + 1.0) / width - 1.0
    y = (2.0 * row + 1.0) / height - 1.0
    return np.stack([x, y], axis=-1).astype(np.float32)


def _project_normalised(kind: str, x: np.ndarray, y: np.ndarray, z: np.ndarray, out: np.ndarray,
                        height: int, width: int) -> None:
    """``normalised_coords(kind, *project_to_grid(kind, p))`` of camera-frame points ``p = (x, y, z)``.

    Written into ``out`` (..., 2); float32, one arctan2 pair per point and
    in-place arithmetic in the same order as :func:`rasterizer.geometry.project_to_grid`
    and :func:`normalised_coords`, so the result is bit-identical to them.
    """
    if kind == "yang":
        x, y, z = y, x, -z
    lat = np.arctan2(-y, np.hypot(x, z))
    lon = np.arctan2(x, z)
    if kind == "erp":
        lon += np.pi
        lon /= 2 * np.pi
        lon *= width
        lon -= 0.5  # col
        lon += 0.5
        np.mod(lon, width, out=lon)
        lon -= 0.5
        lon += ERP_PAD
        lon *= 2.0
        lon += 1.0
        lon /= width + 2 * ERP_PAD
        lat_max, lat_span = np.pi / 2, np.pi
    else:
        lon += YIN_LON_MAX
        lon /= 2 * YIN_LON_MAX
        lon *= width
        lon -= 0.5  # col
        lon *= 2.0
        lon += 1.0
        lon /= width
        lat_max, lat_span = YIN_LAT_MAX, 2 * YIN_LAT_MAX
    lon -= 1.0
    out[..., 0] = lon
    np.subtract(lat_max, lat, out=lat)
    lat /= lat_span
    lat *= height
    lat -= 0.5  # row
    lat *= 2.0
    lat += 1.0
    lat /= height
    lat -= 1.0
    out[..., 1] = lat


def in_yin_domain(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """True where the direction of camera-frame points (x, y, z) lies in the Yin grid's domain
    (|lat| <= YIN_LAT_MAX and |lon| <= YIN_LON_MAX = 3 pi / 4), without arc functions."""
    norm = np.sqrt(x * x + y * y + z * z)
    return (np.abs(y) <= np.float32(np.sin(YIN_LAT_MAX)) * norm) & (z >= -np.abs(x))


def stacked_rows(gy: np.ndarray, in_yin: np.ndarray, height: int) -> np.ndarray:
    """``grid_sample`` y of a grid of ``height`` rows -> y in the stacked (2 height + 2)-row source (module
    docstring): the same rows for Yin, shifted down by height + 2 rows for Yang."""
    shift = np.where(in_yin, np.float32(0.0), np.float32(2 * height + 4))  # two rows per pixel pitch
    return ((gy + np.float32(1.0)) * np.float32(height) + shift) / np.float32(2 * height + 2) - np.float32(1.0)


def _warp_grids_uncached(rels: np.ndarray, inv: np.ndarray, grids: tuple[str, ...], height: int, width: int,
                         workers: int) -> np.ndarray:
    ranges = (np.float32(1.0) / inv).astype(np.float32)[:, None, None]
    d_count, g_count = len(inv), len(grids)
    out = np.empty((2, g_count, d_count, height, width, 2), dtype=np.float32)

    def one(direction: int, gt: int) -> None:
        rot, t = rels[direction, :3, :3], rels[direction, :3, 3]
        u = grid_directions(grids[gt], height, width).astype(np.float32) @ rot.T  # (h, w, 3)
        # X_k = R d r_k + t, one (D, h, w) array per component
        x, y, z = (u[None, :, :, i] * ranges + t[i] for i in range(3))
        dst = out[direction, gt]
        if grids == ("erp",):
            _project_normalised("erp", x, y, z, dst, height, width)
            return
        # each point in the grid that owns it: Yang points in the Yang frame (y, x, -z), where its layout is Yin's
        yin = in_yin_domain(x, y, z)
        _project_normalised("yin", np.where(yin, x, y), np.where(yin, y, x), np.where(yin, z, -z), dst, height, width)
        dst[..., 1] = stacked_rows(dst[..., 1], yin, height)

    jobs = [(d, g) for d in range(2) for g in range(g_count)]
    if workers <= 1:
        for job in jobs:
            one(*job)
    else:
        # numpy ufuncs release the GIL: two threads use both cores of the target box
        with ThreadPoolExecutor(max_workers=workers) as pool:
            list(pool.map(lambda dg: one(*dg), jobs))
    return out


#: Small LRU of warp grids keyed by (relative poses, candidates, grids, size): a service
#: re-rendering the same pair (or a benchmark repeating it) skips the numpy work.
#: Entries are read-only; quality-preset grids are ~50 MB each.
#: The bound is read at every call (0 turns the cache off) and every insert: a change at run time applies at once.
WARP_CACHE_SIZE = 2
_warp_cache: LRUCache[tuple, np.ndarray] = LRUCache(lambda: WARP_CACHE_SIZE)


def clear_warp_cache() -> None:
    """Forget every kept warp grid."""
    _warp_cache.clear()


def warp_grids(
    c2w_a: np.ndarray,
    c2w_b: np.ndarray,
    inv_depths: np.ndarray,
    grids: tuple[str, ...],
    height: int,
    width: int,
    workers: int = 2,
    cache: bool = True,
) -> np.ndarray:
    """Sampling coordinates of every (target pixel, candidate) in the stacked source grids.

    Returns (2, G, D, h, w, 2) float32 (see the module table). A candidate
    point X = R (r_k d) + t in source-camera coordinates, r_k = 1/inv_depths[k].
    The result depends only on the two relative poses (float32), the
    candidates, the grids and the size; with ``cache`` it is kept in a small
    LRU (:data:`WARP_CACHE_SIZE`) and returned read-only.
    """
    inv = np.ascontiguousarray(inv_depths, dtype=np.float32)
    rels = np.stack([relative_pose(c2w_a, c2w_b), relative_pose(c2w_b, c2w_a)]).astype(np.float32)
    grids = tuple(grids)
    if not cache or WARP_CACHE_SIZE <= 0:
        return _warp_grids_uncached(rels, inv, grids, int(height), int(width), workers)
    key = (rels.tobytes(), inv.tobytes(), grids, int(height), int(width))
    hit = _warp_cache.get(key)
    if hit is not None:
        return hit
    out = _warp_grids_uncached(rels, inv, grids, int(height), int(width), workers)
    out.flags.writeable = False
    _warp_cache.put(key, out)
    return out


def sweep_inputs(
    c2w_a: np.ndarray,
    c2w_b: np.ndarray,
    *,
    near: float,
    far: float,
    num_planes: int,
    feature_size: tuple[int, int],
    erp_encoder: bool = False,
) -> dict[str, np.ndarray]:
    """All pose-dependent graph inputs (module table), keyed by input name."""
    c2w_a = np.asarray(c2w_a, dtype=np.float64)
    c2w_b = np.asarray(c2w_b, dtype=np.float64)
    if baseline(c2w_a, c2w_b) < MIN_BASELINE:
        raise ValueError("the two camera centres coincide: depth cannot be triangulated")
    inv = inverse_depth_candidates(near, far, num_planes)
    h, w = feature_size
    grids = grids_for_mode(erp_encoder)
    rel = np.stack([relative_pose(c2w_a, c2w_b)[:3], relative_pose(c2w_b, c2w_a)[:3]]).astype(np.float32)
    c2w = np.stack([c2w_a, c2w_b]).astype(np.float32)
    quats = rotmat_to_quat(np.stack([c2w_a[:3, :3], c2w_b[:3, :3]])).astype(np.float32)
    return {
        "warp_grids": warp_grids(c2w_a, c2w_b, inv, grids, h, w),
        "rel_rt": rel,
        "inv_depths": inv,
        "c2w": c2w,
        "cam_quats": quats,
    }
