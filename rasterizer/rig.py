"""The capture rig: what a real 360 capture shows at its own nadir is the tripod, not the scene.

Every panorama of a tripod capture (the dev data's zind_room09: a dark disc with three legs below about
-77 deg latitude) shows the rig at the camera's nadir. It is attached to the camera, so pixel-aligned
Gaussians of those pixels paint a copy of the rig onto the floor under each reference, which every other
viewpoint shows as a dark blob (README, "The capture rig"; docs/experiments.md).

:func:`patch_rig` gives the Gaussians of reference v's pixels within ``cap_deg`` of v's nadir (camera
+y, whatever the gravity) the colour that the other reference u saw at the same point, where u sees it
(it is not behind u's estimated surface by more than ``tol`` of its range and u's pixel is not in u's
own cap). Their positions stay the encoder's: moving them onto a floor plane fitted around the cap was
measured and opened holes (docs/experiments.md). Where u does not see the point the rig colour stays: a
hole would be worse.
"""

from __future__ import annotations

import numpy as np

from . import geometry as geo
from .gaussians import Gaussians
from .view_colour import VIEW_COLOUR_TOL, seen_pixels

#: Off by default: scenes without a rig (synthetic renders, nadir-patched captures) lose detail under
#: each camera that only the other, oblique view replaces (README, "The capture rig").
DEFAULT_RIG_CAP_DEG = 0.0
#: Largest accepted cap: a quarter of the sphere's latitude range.
MAX_RIG_CAP_DEG = 45.0


def check_rig_cap(value) -> float:
    """``value`` as a cap in degrees within [0, MAX_RIG_CAP_DEG]; raises ValueError naming the range."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) \
            or not 0.0 <= value <= MAX_RIG_CAP_DEG:
        raise ValueError(f"rig_cap_deg: expected degrees from the nadir in [0, {MAX_RIG_CAP_DEG:g}] "
                         f"(0 = off), got {value!r}")
    return float(value)


def rig_mask(grids: tuple[str, ...], height: int, width: int, cap_deg: float) -> np.ndarray:
    """(G, H, W) bool: grid pixels whose camera-frame ray lies within ``cap_deg`` of the nadir (+y)."""
    down = np.stack([geo.grid_directions(g, height, width)[..., 1] for g in grids])
    return down > np.cos(np.radians(check_rig_cap(cap_deg)))


def patch_rig(layout: Gaussians, range_maps: np.ndarray, c2w: np.ndarray, grids: tuple[str, ...],
              cap_deg: float, *, tol: float = VIEW_COLOUR_TOL) -> tuple[Gaussians, np.ndarray]:
    """``layout`` with its rig pixels re-coloured from the other view (module docstring), and the mask.

    layout: N = 2 G H W pixel-aligned Gaussians of two views in [view][grid][row][col] order, colour in
    the SH DC band; range_maps (2, G, H, W) range from each view's camera (scene units); c2w (2, 4, 4)
    the poses the means are in. Returns (Gaussians, rig (2, G, H, W) bool: the pixels that show the rig,
    which later steps must not read as a view of the scene).
    """
    v_count, g_count, h, w = np.shape(range_maps)
    n = g_count * h * w
    if v_count != 2 or len(layout) != 2 * n:
        raise ValueError(f"need two views' pixel-aligned layout; got {len(layout)} Gaussians for {np.shape(range_maps)}")
    cap = rig_mask(tuple(grids), h, w, cap_deg).reshape(n)
    rig = np.stack([cap, cap])
    if not cap.any():
        return layout, rig.reshape(2, g_count, h, w)
    sh = layout.sh.copy()
    rng = np.asarray(range_maps, dtype=np.float64).reshape(2, n)
    poses = np.asarray(c2w, dtype=np.float64)
    idx = np.flatnonzero(cap)
    for v in range(2):
        u = 1 - v
        pix, seen = seen_pixels(layout.means[v * n + idx], poses[u], rng[u], grids, h, w, tol)
        seen &= ~cap[pix]
        sh[v * n + idx[seen], 0, :] = layout.sh[u * n + pix[seen], 0, :]  # the other view's pixel colour
    return layout.with_(sh=sh), rig.reshape(2, g_count, h, w)
