"""View-dependent colour: degree-1 spherical harmonics fitted so that each reference sees its own image.

The two references' pixel-aligned Gaussians share one scene. Seen from reference A, a Gaussian of
reference B that sits in front of A's surface (a depth error of B) or on it (a different sampling of
the same surface) paints B's colour over A's pixels: with one colour per Gaussian a render at A's own
pose does not show A's image (measurements: docs/design.md).

Each Gaussian x of view v keeps its own pixel colour c_v in the direction d_v from v's camera. Where
the other view u sees x (x is not behind u's estimated surface by more than ``tol`` of its range), u
saw colour c_u along the direction d_u to x: the colour of u's grid pixel that x projects to. A linear
colour c(d) = a + G d (3x3 G: the degree-1 SH band) is fitted with c(d_v) = c_v exactly and c(d_u) =
c_u in the ridge sense, G = (c_u - c_v) (d_u - d_v)^T / (|d_u - d_v|^2 + ridge). The ridge keeps G
bounded, |G| <= |c_u - c_v| / (2 sqrt(ridge)), so views far from both references see at most that
swing; where u does not see x, G = 0 (the Gaussian's single colour).
"""

from __future__ import annotations

import numpy as np

from .gaussians import Gaussians, rgb_to_sh_dc, sh_dc_to_rgb
from .sh import SH_C1
from .threads import map_threads
from .yin_yang import grid_pixel

#: Colour models a reconstruction offers: 0 = one colour per Gaussian, 1 = this module's fit.
SH_DEGREES = (0, 1)
DEFAULT_SH_DEGREE = 1
#: Ridge of the fit (units of |d_u - d_v|^2, i.e. squared chord length of the two viewing directions).
VIEW_COLOUR_RIDGE = 0.2
#: x counts as seen by the other view when its range from that view is at most (1 + tol) times the
#: other view's estimated range in that direction.
VIEW_COLOUR_TOL = 0.1


def check_sh_degree(value) -> int:
    """``value`` as one of :data:`SH_DEGREES`; raises ValueError naming the accepted ones."""
    if isinstance(value, bool) or value not in SH_DEGREES:
        raise ValueError(f"sh_degree: expected one of {list(SH_DEGREES)} (1: view-dependent colour, "
                         f"0: one colour per Gaussian), got {value!r}")
    return int(value)


def _dot3(a, b) -> np.ndarray:
    """(M,) a . b of vectors given as three (M,) columns each (a (3, M) array or a list), summed in index
    order as numpy's reduction over the last axis of (M, 3) rows does (column passes: that reduction
    over many rows of three is several times slower)."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _unit_columns(cols, floor: float) -> list[np.ndarray]:
    """geometry.unit_vectors of rows given as three (M,) columns, as three float32 columns (the same values:
    the norm is the same sum of squares)."""
    norm = np.maximum(np.sqrt(_dot3(cols, cols)), floor)
    return [(c / norm).astype(np.float32) for c in cols]


def _camera_columns(points: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    """(3, M) float64 camera-frame coordinates of world ``points`` (M, 3): geo.world_to_camera's (x - t) R,
    the three products of each coordinate summed in order, on contiguous columns."""
    pose = np.asarray(c2w, dtype=np.float64)
    pts = np.asarray(points)
    d = [pts[:, j].astype(np.float64) - pose[j, 3] for j in range(3)]
    out = np.empty((3, pts.shape[0]))
    for k in range(3):
        out[k] = d[0] * pose[0, k] + d[1] * pose[1, k] + d[2] * pose[2, k]
    return out


def seen_pixels(points: np.ndarray, c2w: np.ndarray, range_map: np.ndarray, grids: tuple[str, ...], height: int,
                width: int, tol: float = VIEW_COLOUR_TOL) -> tuple[np.ndarray, np.ndarray]:
    """Where another view sees world ``points`` (M, 3): (pix (M,) flat index into its (G, H, W) grid
    layout, seen (M,) bool). ``range_map`` (G H W,) is that view's estimated range per pixel; a point
    counts as seen when its range from that camera (``c2w``) is > 0 and at most (1 + tol) times it."""
    p = _camera_columns(points, c2w)
    r = np.sqrt(_dot3(p, p))  # np.linalg.norm's sum of squares, without a reduction over rows of 3
    pix = grid_pixel(p.T, grids, height, width)
    return pix, np.isfinite(r) & (r > 0) & (r <= range_map[pix] * (1.0 + tol))


def fit_view_colour(layout: Gaussians, range_maps: np.ndarray, c2w: np.ndarray, grids: tuple[str, ...], *,
                    ridge: float = VIEW_COLOUR_RIDGE, tol: float = VIEW_COLOUR_TOL,
                    hidden: np.ndarray | None = None) -> Gaussians:
    """``layout`` with degree-1 SH colours (module docstring).

    layout: N = 2 G H W pixel-aligned Gaussians of two views in [view][grid][row][col] order, colour
    in the SH DC band; range_maps (2, G, H, W) range from each view's camera (scene units); c2w (2, 4, 4)
    the poses the layout's means are in; grids: the G grid kinds; hidden: optional (2, G, H, W) bool,
    pixels that do not show the scene (the capture rig, :mod:`rasterizer.rig`), which see nothing.
    Returns the same Gaussians with ``sh`` (N, 4, 3).
    """
    v_count, g_count, h, w = np.shape(range_maps)
    n = g_count * h * w
    if v_count != 2 or len(layout) != 2 * n:
        raise ValueError(f"need two views' pixel-aligned layout; got {len(layout)} Gaussians for {np.shape(range_maps)}")
    if not ridge > 0:
        raise ValueError(f"ridge must be > 0, got {ridge}")
    # per-Gaussian maths on contiguous (n,) columns, one per coordinate or colour channel
    rgb = np.ascontiguousarray(sh_dc_to_rgb(layout.sh[:, 0, :]).T).reshape(3, 2, n)
    rng = np.asarray(range_maps, dtype=np.float64).reshape(2, n)
    shows = np.ones((2, n), dtype=bool) if hidden is None else ~np.asarray(hidden, dtype=bool).reshape(2, n)
    means = layout.means.reshape(2, n, 3)
    poses = np.asarray(c2w, dtype=np.float64)
    sh = np.empty((2, n, 4, 3), dtype=np.float32)

    def one(job):
        v, c = job  # a chunk of view v's Gaussians against the other view u
        u = 1 - v
        _fit_chunk(sh[v, c], means[v, c], rgb[:, v, c], rgb[:, u], poses[v], poses[u], rng[u], shows[u], grids,
                   h, w, ridge, tol)

    # each Gaussian's maths is its own: the chunks, two at a time, give the values of one pass
    map_threads(one, [(v, slice(c0, min(n, c0 + CHUNK))) for v in range(2) for c0 in range(0, n, CHUNK)])
    return layout.with_(sh=sh.reshape(2 * n, 4, 3))


#: Gaussians per chunk of :func:`fit_view_colour`: its float64 temporaries then stay in the CPU cache.
CHUNK = 16384


def _fit_chunk(sh: np.ndarray, means: np.ndarray, rgb_v: np.ndarray, rgb_u: np.ndarray, pose_v: np.ndarray,
               pose_u: np.ndarray, rng_u: np.ndarray, shows_u: np.ndarray, grids: tuple[str, ...], h: int, w: int,
               ridge: float, tol: float) -> None:
    """:func:`fit_view_colour` of M Gaussians of view v against the other view u: writes their (M, 4, 3)
    ``sh``. means (M, 3); rgb_v (3, M) their colours; rgb_u (3, G H W), rng_u (G H W,) and shows_u (G H W,)
    u's pixel colours, ranges and pixels that show the scene; pose_v, pose_u (4, 4) float64."""
    pix, seen = seen_pixels(means, pose_u, rng_u, grids, h, w, tol)
    seen &= shows_u[pix]
    d_v = _unit_columns([means[:, j].astype(np.float64) - pose_v[j, 3] for j in range(3)], 1e-30)
    d_u = _unit_columns([means[:, j].astype(np.float64) - pose_u[j, 3] for j in range(3)], 1e-30)
    dd = [d_u[j] - d_v[j] for j in range(3)]
    den = _dot3(dd, dd) + np.float32(ridge)
    wt = [dd[j] / den for j in range(3)]  # G = dc w^T
    dc = [np.where(seen, rgb_u[j][pix] - rgb_v[j], np.float32(0.0)) for j in range(3)]
    g_dv = _dot3(wt, d_v)
    for j in range(3):
        sh[:, 0, j] = rgb_to_sh_dc(rgb_v[j] - dc[j] * g_dv)  # a = c_v - G d_v
    # 3DGS degree-1 basis: -C1 y, C1 z, -C1 x (rasterizer.sh.sh_basis)
    for k, (axis, sign) in enumerate(((1, -1.0), (2, 1.0), (0, -1.0)), start=1):
        scaled = np.float32(sign / SH_C1) * wt[axis]
        for j in range(3):
            sh[:, k, j] = dc[j] * scaled
