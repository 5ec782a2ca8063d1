"""Pre-render culling: hidden and out-of-view Gaussians go, the image stays the same."""

import numpy as np

from bench.metrics import psnr
from bench.render_cull import cull_for_camera
from rasterizer import geometry as geo
from rasterizer.depth_gaussians import gaussians_from_depth
from rasterizer.gaussians import Gaussians
from rasterizer.render import render


def _sphere_shell(radius, colour, h=32, opacity=0.95):
    """Pixel-aligned Gaussians of a sphere of ``radius`` around the origin (both grids)."""
    parts = []
    for k in ("yin", "yang"):
        rng = np.full((h, 3 * h), radius)
        parts.append(gaussians_from_depth(np.full((h, 3 * h, 3), colour, np.float32), rng, np.eye(4), k,
                                          scale_factor=0.75, thickness=0.1, opacity=opacity))
    return Gaussians.concatenate(parts)


def test_occluded_shell_is_culled_and_image_unchanged():
    inner = Gaussians.concatenate([_sphere_shell(1.0, 0.8)] * 3)  # three layers: tau ~ 10 > tau_cut 7
    outer = _sphere_shell(3.0, 0.1)
    g = Gaussians.concatenate([inner, outer])
    idx = cull_for_camera(g, np.eye(4), "erp", width=128)
    kept = np.zeros(len(g), bool)
    kept[idx] = True
    assert kept[: len(inner)].all()  # nothing in front is culled
    assert kept[len(inner):].mean() < 0.2  # the hidden shell goes (some pole cells are too small to tell)
    full = render(g, np.eye(4), projection="erp", width=128)
    culled = render(g.subset(idx), np.eye(4), projection="erp", width=128)
    assert psnr(culled.colour, full.colour) > 40.0


def test_transparent_occluder_culls_nothing():
    g = Gaussians.concatenate([_sphere_shell(1.0, 0.8, opacity=0.05), _sphere_shell(3.0, 0.1)])
    idx = cull_for_camera(g, np.eye(4), "erp", width=128)
    assert idx.size == len(g)
    assert cull_for_camera(g, np.eye(4), "erp", width=128, occlusion=False).size == len(g)


def test_perspective_frustum_cull():
    g = _sphere_shell(2.0, 0.5)
    pose = np.eye(4)
    idx = cull_for_camera(g, pose, "perspective", width=64, fov_deg=90.0, occlusion=False)
    d = geo.world_to_camera(g.means, pose)
    assert np.all(d[idx, 2] > 0)  # nothing behind the camera survives
    assert 0.1 < idx.size / len(g) < 0.4  # a 90-degree cone (plus margin) of the sphere
    full = render(g, pose, projection="perspective", width=64)
    culled = render(g.subset(idx), pose, projection="perspective", width=64)
    np.testing.assert_allclose(culled.colour, full.colour, atol=1e-5)
