"""The capture rig: what a real 360 capture shows at its own nadir is the tripod, not the scene.

Every panorama of a tripod capture (the dev data's zind_room09: a dark disc with three legs below about
-77 deg latitude) shows the rig at the camera's nadir. It is attached to the camera, so pixel-aligned
Gaussians of those pixels paint a copy of the rig onto the floor under each reference, which every other
viewpoint shows as a dark blob (docs/design.md, "The capture rig").

:func:`patch_rig` gives the Gaussians of reference v's pixels within ``cap_deg`` of v's nadir (camera
+y, whatever the gravity) the colour that the other reference u saw at the same point, where u sees it
(it is not behind u's estimated surface by more than ``tol`` of its range and u's pixel is not in u's
own cap). Their positions stay the encoder's: moving them onto a floor plane fitted around the cap was
measured and opened holes (docs/design.md). Where u does not see the point the rig colour stays: a
hole would be worse.

The rig is also what a capture *from the novel pose* would show at its nadir. :func:`rig_layer` estimates
it as a camera-attached ERP layer: within ``RIG_LAYER_CAP_DEG`` of the nadir, each reference's pixels in
its own camera frame, kept where the two references agree (a rig moves with the camera; the floor under
two cameras metres apart does not). :func:`overlay_rig` composites it over a render in the render's own
camera frame. It is not part of the 3D scene (no 3DGS viewer can show camera-attached content), so
renders take it only on request (``rig=true``; README, "The capture rig").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import uniform_filter

from . import geometry as geo
from .camera import sample_erp
from .gaussians import Gaussians
from .view_colour import VIEW_COLOUR_TOL, seen_pixels

#: The cap a scene gets when the caller sets none and :func:`rig_summary` detects a rig: the ZInD rig's
#: disc and most of its legs. Without a detected rig the cap is 0: scenes without one (synthetic
#: renders, nadir-patched captures) would lose detail under each camera that only the other, oblique
#: view replaces (README, "The capture rig").
AUTO_RIG_CAP_DEG = 20.0
#: Largest accepted cap: a quarter of the sphere's latitude range.
MAX_RIG_CAP_DEG = 45.0

#: A rig is detected when, within this many degrees of the nadir, the two references' images in their own
#: camera frames differ by at most RIG_DETECT_MAX_DIFF (cos-latitude-weighted mean absolute difference,
#: colours in [0, 1]). Measured at 512 px width: zind_room09's six pano pairs (a tripod) 0.011-0.019;
#: m3d_bedroom's three pairs (no rig) 0.087-0.114 (docs/design.md).
RIG_DETECT_CAP_DEG = 5.0
RIG_DETECT_MAX_DIFF = 0.05
#: The layer covers this many degrees around the nadir: zind_room09's tripod disc reaches 12.5 deg from
#: it; its thin legs, up to 24 deg, sit where the floor differs too, and a wider cap cost the scene
#: (caps 13-30 deg: docs/design.md).
RIG_LAYER_CAP_DEG = 15.0
#: Per-pixel agreement -> layer opacity: a box mean (RIG_LAYER_BOX pixels square) of the two views'
#: absolute difference at or below the first value is opaque rig, at or above the second is scene.
RIG_LAYER_AGREE = (0.03, 0.08)
RIG_LAYER_BOX = 5


def check_rig_cap(value) -> float | None:
    """``value`` as a cap in degrees within [0, MAX_RIG_CAP_DEG], None (automatic: ``AUTO_RIG_CAP_DEG``
    where a rig is detected, else 0) as None; raises ValueError naming the range."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) \
            or not 0.0 <= value <= MAX_RIG_CAP_DEG:
        raise ValueError(f"rig_cap_deg: expected degrees from the nadir in [0, {MAX_RIG_CAP_DEG:g}] "
                         f"(0 = off; absent or null = {AUTO_RIG_CAP_DEG:g} where both references show a rig, "
                         f"else 0), got {value!r}")
    return float(value)


def rig_mask(grids: tuple[str, ...], height: int, width: int, cap_deg: float) -> np.ndarray:
    """(G, H, W) bool: grid pixels whose camera-frame ray lies within ``cap_deg`` of the nadir (+y)."""
    cap = check_rig_cap(cap_deg)
    if cap is None:
        raise ValueError("rig_mask needs a cap in degrees, not the automatic None")
    down = np.stack([geo.grid_directions(g, height, width)[..., 1] for g in grids])
    return down > np.cos(np.radians(cap))


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


@dataclass(frozen=True)
class RigLayer:
    """The capture rig as seen from the camera: an ERP layer in the camera frame.

    colour (H, W, 3) float32 in [0, 1] and alpha (H, W) float32 in [0, 1] (0 outside the cap);
    agreement: the detection statistic (see ``RIG_DETECT_MAX_DIFF``).
    """

    colour: np.ndarray
    alpha: np.ndarray
    agreement: float


def _float_rgb(image: np.ndarray) -> np.ndarray:
    a = np.asarray(image)
    return a.astype(np.float32) / 255.0 if a.dtype == np.uint8 else a.astype(np.float32)


def _pair(erp_a: np.ndarray, erp_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a, b = _float_rgb(erp_a), _float_rgb(erp_b)
    if a.shape != b.shape or a.ndim != 3 or a.shape[2] != 3 or a.shape[1] != 2 * a.shape[0]:
        raise ValueError(f"need two ERP RGB images of one size (H, 2H, 3); got {a.shape} and {b.shape}")
    return a, b


def _nadir_distance_deg(height: int) -> np.ndarray:
    """(H, 1) degrees from the nadir of ERP row centres."""
    return (np.arange(height, dtype=np.float64)[::-1, None] + 0.5) / height * 180.0


def _agreement(a: np.ndarray, b: np.ndarray) -> float:
    nadir = _nadir_distance_deg(a.shape[0])[:, 0]
    rows = nadir <= max(RIG_DETECT_CAP_DEG, nadir[-1])  # at least the last row
    weight = np.sin(np.radians(nadir[rows]))[:, None]  # cos(latitude)
    diff = np.abs(a[rows] - b[rows]).mean(-1)
    return float((diff * weight).sum() / (weight.sum() * a.shape[1]))


def rig_agreement(erp_a: np.ndarray, erp_b: np.ndarray) -> float:
    """Cos-latitude-weighted mean |a - b| within ``RIG_DETECT_CAP_DEG`` of the nadir, camera frames.

    erp_a, erp_b: (H, 2H, 3) uint8 or float in [0, 1], the two references as captured.
    """
    return _agreement(*_pair(erp_a, erp_b))


def rig_summary(erp_a: np.ndarray, erp_b: np.ndarray) -> dict:
    """{"detected", "agreement", "max_agreement"}: whether the two references show one rig at their nadir."""
    agreement = rig_agreement(erp_a, erp_b)
    return {"detected": bool(agreement <= RIG_DETECT_MAX_DIFF), "agreement": round(agreement, 4),
            "max_agreement": RIG_DETECT_MAX_DIFF}


def resolve_rig_cap(cap_deg: float | None, detected: bool) -> float:
    """The cap a scene gets: the caller's, or automatic (``AUTO_RIG_CAP_DEG`` with a detected rig, else 0)."""
    cap = check_rig_cap(cap_deg)
    return (AUTO_RIG_CAP_DEG if detected else 0.0) if cap is None else cap


class NoRigError(ValueError):
    """The two references show no common rig at their nadir; the message gives the statistic."""


def require_rig_layer(erp_a: np.ndarray, erp_b: np.ndarray) -> RigLayer:
    """The rig both references show at their nadir (module docstring); :class:`NoRigError` when none.

    erp_a, erp_b: (H, 2H, 3) uint8 or float in [0, 1]. Returns a layer of the same size: colour the two
    views' mean, alpha from their local agreement (``RIG_LAYER_AGREE``) within ``RIG_LAYER_CAP_DEG``.
    """
    a, b = _pair(erp_a, erp_b)
    agreement = _agreement(a, b)
    if not agreement <= RIG_DETECT_MAX_DIFF:
        raise NoRigError(f"the two references show no common capture rig at their nadir (mean difference "
                         f"{agreement:.3f} > {RIG_DETECT_MAX_DIFF} within {RIG_DETECT_CAP_DEG:g} deg of it)")
    diff = uniform_filter(np.abs(a - b).mean(-1), RIG_LAYER_BOX, mode=("nearest", "wrap"))
    lo, hi = RIG_LAYER_AGREE
    alpha = np.clip((hi - diff) / (hi - lo), 0.0, 1.0) * (_nadir_distance_deg(a.shape[0]) <= RIG_LAYER_CAP_DEG)
    return RigLayer(0.5 * (a + b), alpha.astype(np.float32), agreement)


def rig_layer(erp_a: np.ndarray, erp_b: np.ndarray) -> RigLayer | None:
    """:func:`require_rig_layer`, or None when the references show no common rig."""
    try:
        return require_rig_layer(erp_a, erp_b)
    except NoRigError:
        return None


def overlay_rig(colour: np.ndarray, directions: np.ndarray, layer: RigLayer) -> np.ndarray:
    """``colour`` (H, W, 3) with the rig layer composited over it ("over", straight alpha).

    directions: (H, W, 3) camera-frame rays of the render's pixels (the rig moves with the camera, so the
    render's pose does not enter). Returns float32 (H, W, 3).
    """
    d = np.asarray(directions, dtype=np.float64)
    col, row = geo.project_to_grid("erp", d, *layer.alpha.shape)
    rgba = sample_erp(np.concatenate([layer.colour, layer.alpha[..., None]], -1), col, row)
    a = rgba[..., 3:]
    return (np.asarray(colour, dtype=np.float32) * (1.0 - a) + rgba[..., :3] * a).astype(np.float32)
