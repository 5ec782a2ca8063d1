"""Helpers shared by the tests (not a test module): small synthetic scenes.

``two_view_box``: two references inside a box room, the full [view][yin, yang][row][col] layout;
``toy_scene``: Gaussians on a sphere around the origin (a closed room) with known colours / opacities;
``random_scene`` / ``reference_composite``: random Gaussians and the slow per-pixel compositor the renderer is checked against.
"""

from __future__ import annotations

import numpy as np

from rasterizer import geometry as geo
from rasterizer.compaction import Provenance
from rasterizer.depth_gaussians import gaussians_from_depth
from rasterizer.gaussians import Gaussians, quat_to_rotmat, rgb_to_sh_dc
from rasterizer.splat import ALPHA_MIN

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


# -- renderer tests: random scenes and the slow reference compositor --------------------

def make_gaussians(means, scales, quats=None, opacities=None, rgb=None):
    means = np.atleast_2d(np.asarray(means, dtype=np.float64))
    n = len(means)
    scales = np.broadcast_to(np.asarray(scales, dtype=np.float64), (n, 3))
    quats = np.tile([1.0, 0, 0, 0], (n, 1)) if quats is None else np.atleast_2d(quats)
    opacities = np.full(n, 0.5) if opacities is None else np.broadcast_to(opacities, (n,))
    rgb = np.full((n, 3), 0.8) if rgb is None else np.broadcast_to(rgb, (n, 3))
    return Gaussians(means, scales, quats, opacities, rgb_to_sh_dc(rgb)[:, None, :])


def random_scene(rng, n, radius=(1.0, 4.0), size=(0.02, 0.2)):
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    means = d * rng.uniform(*radius, size=(n, 1))
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return make_gaussians(means, rng.uniform(*size, size=(n, 3)), q, rng.uniform(0.05, 1.0, n),
                          rng.uniform(0, 1, (n, 3)))


def pose(rng):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    c2w = np.eye(4)
    c2w[:3, :3] = quat_to_rotmat(q[None])[0]
    c2w[:3, 3] = rng.normal(size=3) * 0.3
    return c2w


def reference_composite(fp_mean, fp_conic, ranges, opacities, colours, w, h, period=None, depths=None,
                        q_max=np.inf):
    """Slow per-pixel loop: evaluate every Gaussian, sort by range (by ``depths`` if given), apply the 3DGS rules;
    footprints end at Mahalanobis radius^2 ``q_max`` too (a scalar, or one per Gaussian)."""
    q_max = np.broadcast_to(np.asarray(q_max, dtype=np.float64), (len(opacities),))
    colour = np.zeros((h, w, 3))
    alpha = np.zeros((h, w))
    rng_img = np.zeros((h, w))
    order = np.argsort(ranges if depths is None else depths, kind="stable")
    for r in range(h):
        for c in range(w):
            t = 1.0
            for i in order:
                dx = c - fp_mean[i, 0]
                if period is not None:
                    dx = (dx + period / 2) % period - period / 2
                dy = r - fp_mean[i, 1]
                qv = fp_conic[i, 0] * dx * dx + 2 * fp_conic[i, 1] * dx * dy + fp_conic[i, 2] * dy * dy
                g = np.exp(-0.5 * qv)
                if g < ALPHA_MIN or qv > q_max[i]:
                    continue  # outside the opacity-free footprint
                a = min(0.99, opacities[i] * g)
                if a < ALPHA_MIN:
                    continue
                if t * (1 - a) < 1e-4:
                    break
                colour[r, c] += t * a * colours[i]
                alpha[r, c] += t * a
                rng_img[r, c] += t * a * ranges[i]
                t *= 1 - a
    return colour, alpha, np.where(alpha > 0, rng_img / np.maximum(alpha, 1e-30), 0)


def forward_scene(rng, n: int = 40, opacity=(0.0, 1.0)):
    """``n`` random Gaussians 1-3 m in front of an identity camera (+z, within a frustum-like spread)."""
    d = rng.normal(size=(n, 3)) * [0.6, 0.3, 1]
    d[:, 2] = np.abs(d[:, 2]) + 0.3
    means = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(1.0, 3.0, (n, 1))
    q = rng.normal(size=(n, 4))
    return make_gaussians(means, rng.uniform(0.02, 0.15, (n, 3)), q / np.linalg.norm(q, axis=1, keepdims=True),
                          rng.uniform(*opacity, n), rng.uniform(0, 1, (n, 3)))
