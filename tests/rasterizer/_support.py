"""Helpers shared by the tests (not a test module): small synthetic scenes.

``two_view_box``: two references inside a box room, the full [view][yin, yang][row][col] layout;
``toy_scene``: Gaussians on a sphere around the origin (a closed room) with known colours / opacities.
"""

from __future__ import annotations

import numpy as np

from rasterizer import geometry as geo
from rasterizer.compaction import Provenance
from rasterizer.depth_gaussians import gaussians_from_depth
from rasterizer.gaussians import Gaussians, rgb_to_sh_dc

H, W = 12, 36  # one Yin/Yang grid of two_view_box


def pose_at(t):
    """A camera at ``t`` looking along +z (identity rotation)."""
    c2w = np.eye(4)
    c2w[:3, 3] = t
    return c2w


def box_range(kind, c2w, half=2.0, size=(H, W)):
    """Range along each grid ray (grid ``size``) from camera ``c2w`` to the inside of the box [-half, half]^3."""
    d = geo.grid_directions(kind, *size) @ c2w[:3, :3].T
    o = c2w[:3, 3]
    with np.errstate(divide="ignore"):
        t = np.where(d > 0, (half - o) / d, np.where(d < 0, (-half - o) / d, np.inf))
    return t.min(axis=-1)


def box_colour(kind, c2w):
    """Smooth colours of the box walls seen along each grid ray of one camera."""
    d = geo.grid_directions(kind, H, W) @ c2w[:3, :3].T
    p = c2w[:3, 3] + d * box_range(kind, c2w)[..., None]
    return (0.5 + 0.4 * np.sin(3 * p)).astype(np.float32)


def two_view_box(opacity=0.9):
    """Two references inside a box room: full [view][yin, yang][row][col] layout."""
    poses = [pose_at([0.0, 0.0, -0.3]), pose_at([0.0, 0.0, 0.3])]
    parts = [gaussians_from_depth(box_colour(k, c), box_range(k, c), c, k, scale_factor=0.75, thickness=0.1,
                                  opacity=opacity)
             for c in poses for k in ("yin", "yang")]
    return Gaussians.concatenate(parts), Provenance(("yin", "yang"), H, W, np.stack(poses))


def toy_scene(seed: int = 0, n: int = 600):
    """Gaussians on a sphere of radius ~3 around the origin (a closed room), true colours/opacities."""
    rng = np.random.default_rng(seed)
    d = rng.standard_normal((n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    means = d * rng.uniform(2.5, 3.5, (n, 1))
    scales = np.full((n, 3), 0.35) * rng.uniform(0.7, 1.3, (n, 1))
    quats = rng.standard_normal((n, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    rgb = rng.uniform(0.05, 0.95, (n, 3))
    opac = rng.uniform(0.5, 0.95, n)
    return Gaussians(means, scales, quats, opac, rgb_to_sh_dc(rgb)[:, None, :])
