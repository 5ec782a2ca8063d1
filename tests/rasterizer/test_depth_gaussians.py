"""Surfels of rasterizer.depth_gaussians (the numpy twin of the encoder's head)."""

import numpy as np

from rasterizer.depth_gaussians import SURFEL_MAX_STRETCH, gaussians_from_depth, pixel_steps, surfel_shapes
from rasterizer.gaussians import Gaussians, covariance_from_scale_rotation
from rasterizer.render import render


def _plane_range(grid, h, w, normal, dist):
    """Range along each pixel ray to the plane n.x = dist (inf where the ray misses it)."""
    ray, _, _ = pixel_steps(grid, h, w)
    cos = ray @ np.asarray(normal, float)
    with np.errstate(divide="ignore"):
        return np.where(cos > 1e-3, dist / np.maximum(cos, 1e-3), np.inf)


def test_surfels_lie_in_a_tilted_plane():
    h, w = 32, 96
    n = np.array([0.3, -0.2, 0.93])
    n /= np.linalg.norm(n)
    depth = _plane_range("yin", h, w, n, 2.0)
    g = gaussians_from_depth(np.full((h, w, 3), 0.5, np.float32), depth, np.eye(4), "yin", surfels=True)
    cov = covariance_from_scale_rotation(g.scales, g.quats)
    ray = np.asarray(g.means) / np.linalg.norm(g.means, axis=1, keepdims=True)
    steep = ray @ n > 0.5  # within SURFEL_MAX_STRETCH facing steps (grazing ones fall back to facing)
    assert steep.sum() > 1000
    evals, evecs = np.linalg.eigh(cov[steep])
    normal = evecs[:, :, 0]  # smallest axis
    assert np.quantile(np.abs(normal @ n), 0.05) > 0.999
    assert np.all(evals[:, 0] < 0.02 * evals[:, 1])  # flat


def test_no_surfel_stretches_across_a_depth_step():
    h, w = 16, 48
    depth = np.full((h, w), 2.0)
    depth[:, w // 2:] = 5.0  # step
    depth[5, 10] = 0.8  # one-pixel spike: both neighbours jump
    ray, east, south = pixel_steps("yin", h, w)
    axes, scales = surfel_shapes(depth[..., None] * ray, depth[..., None] * east, depth[..., None] * south,
                                 scale_factor=0.6)
    facing = np.linalg.norm(depth[..., None] * east, axis=-1)
    assert np.all(scales[..., 0] <= 0.6 * SURFEL_MAX_STRETCH * facing * 1.5 + 1e-12)
    # beside the step and at the spike the surfel keeps the pixel footprint (facing step)
    for r, c in ((7, w // 2 - 1), (7, w // 2), (5, 10)):
        assert scales[r, c, 0] < 1.1 * 0.6 * np.hypot(facing[r, c], np.linalg.norm(depth[r, c] * south[r, c]))
    assert np.all(np.isfinite(axes)) and np.all(np.isfinite(scales))


def test_invalid_depth_is_skipped_without_nan():
    h, w = 8, 24
    depth = np.full((h, w), 3.0)
    depth[2, 3], depth[4, 4], depth[6, 6] = 0.0, np.nan, np.inf
    g = gaussians_from_depth(np.zeros((h, w, 3), np.float32), depth, np.eye(4), "yang", surfels=True)
    assert len(g) == h * w - 3
    g.check_finite()


def test_opaque_surfels_cover_the_scene():
    """Plain compositing of opaque surfels of two panoramas inside a 4 m box: alpha >= 0.99 on >= 98% of
    the ERP at a reference pose and midway; camera-facing discs of the same size do not get there."""
    h, w = 48, 144
    centres = ([-0.25, 0.0, 0.0], [0.25, 0.0, 0.0])

    def scene(**kw):
        parts = []
        for c in centres:
            c2w = np.eye(4)
            c2w[:3, 3] = c
            for grid in ("yin", "yang"):
                ray, _, _ = pixel_steps(grid, h, w)
                # range to the walls of the cube |x| = 2 seen from c
                t = np.min(np.where(ray != 0, (np.sign(ray) * 2.0 - np.asarray(c)) / np.where(ray != 0, ray, 1),
                                    np.inf), axis=-1)
                parts.append(gaussians_from_depth(np.full((h, w, 3), 0.5, np.float32), t, c2w, grid, **kw))
        return Gaussians.concatenate(parts)

    surfels, discs = scene(surfels=True, opacity=0.99), scene(scale_factor=0.3, opacity=0.99)
    for x in (-0.25, 0.0):
        pose = np.eye(4)
        pose[0, 3] = x
        assert (render(surfels, pose, projection="erp", width=192, method="direct").alpha >= 0.99).mean() >= 0.98
        assert (render(discs, pose, projection="erp", width=192, method="direct").alpha >= 0.99).mean() < 0.9
