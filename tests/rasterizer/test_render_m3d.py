"""Renderer on real data (m3d_bedroom): self re-render, ERP vs Yin-Yang, oracle sanity."""

import numpy as np
import pytest

from bench.metrics import psnr
from rasterizer import geometry as geo
from rasterizer.depth_gaussians import gaussians_from_depth
from rasterizer.gaussians import Gaussians, quat_to_rotmat
from rasterizer.render import render
from rasterizer.scene_folder import load_scene
from rasterizer.yin_yang import erp_to_yin_yang, resize_erp


@pytest.fixture(scope="module")
def scene(m3d_dir):
    return load_scene(m3d_dir)


def test_depth_gaussians_rerender_their_own_view_above_40db(scene):
    """Full resolution: the 0.3 px^2 low-pass blurs each pixel with its nearer neighbours,
    so the PSNR is bounded (~41 dB here) and only tiny Gaussians reach it."""
    f = scene.frames["00"]
    img, depth = f.image(), f.depth()
    g = gaussians_from_depth(img, depth, f.c2w, "erp", scale_factor=0.02)
    ok = depth > 0
    assert len(g) == int(ok.sum())
    out = render(g, f.c2w, projection="erp", width=img.shape[1], method="direct")
    value = psnr(out.colour[ok], img[ok])
    print(f"self re-render (ERP 512x1024, GT depth, pixels with depth): {value:.2f} dB")
    assert value >= 40
    # the expected range is the depth map itself
    assert np.median(np.abs(out.range[ok] - depth[ok]) / depth[ok]) < 5e-3


def test_depth_gaussians_sit_on_their_rays(scene):
    f = scene.frames["02"]
    for grid in ("erp", "yang"):
        img = resize_erp(f.image(), 32, 64)
        depth = f.depth()[8::16, 8::16]
        if grid == "yang":
            img, depth = erp_to_yin_yang(img)[1], erp_to_yin_yang(f.depth(), nearest=True, height=16)[1]
        g = gaussians_from_depth(img, depth, f.c2w, grid)
        rays = geo.grid_directions(grid, *depth.shape)[depth > 0] @ f.c2w[:3, :3].T
        rel = g.means - f.c2w[:3, 3]
        assert np.allclose(np.linalg.norm(rel, axis=1), depth[depth > 0], rtol=1e-5)
        assert np.allclose(rel / np.linalg.norm(rel, axis=1, keepdims=True), rays, atol=1e-5)
        # flattened along the ray: the thin local axis (third column of R) is the ray
        axis = quat_to_rotmat(g.quats)[:, :, 2]
        assert np.allclose(np.abs(np.sum(axis * rays, axis=1)), 1, atol=1e-5)
        assert np.all(g.scales[:, 2] < g.scales[:, :2].min(axis=1))


def _two_reference_gaussians(scene, height):
    parts = []
    for name in ("00", "02"):
        f = scene.frames[name]
        img = resize_erp(f.image(), height, 2 * height)
        depth = f.depth()
        # nearest-style downsampling of depth (no invented ranges across edges)
        step = depth.shape[0] // height
        depth = depth[step // 2::step, step // 2::step]
        yi, ya = erp_to_yin_yang(img)
        di, da = erp_to_yin_yang(depth, nearest=True)
        parts += [gaussians_from_depth(yi, di, f.c2w, "yin"), gaussians_from_depth(ya, da, f.c2w, "yang")]
    return Gaussians.concatenate(parts)


def test_direct_erp_and_yinyang_agree_on_a_real_scene(scene):
    g = _two_reference_gaussians(scene, 128)
    c2w = scene.frames["01"].c2w
    direct = render(g, c2w, projection="erp", width=256, method="direct")
    yy = render(g, c2w, projection="erp", width=256, method="yinyang")
    value = psnr(direct.colour, yy.colour)
    print(f"direct ERP vs Yin-Yang ERP (128x256, {len(g)} Gaussians): {value:.2f} dB")
    assert value > 30
    assert np.mean(np.abs(direct.alpha - yy.alpha)) < 0.02


def test_oracle_beats_the_nearest_reference_at_the_target(scene):
    g = _two_reference_gaussians(scene, 128)
    tgt = scene.frames["01"]
    gt = resize_erp(tgt.image(), 128, 256)
    out = render(g, tgt.c2w, projection="erp", width=256)
    oracle = psnr(out.colour, gt)
    baseline = max(psnr(resize_erp(scene.frames[n].image(), 128, 256), gt) for n in ("00", "02"))
    print(f"oracle at 128x256: {oracle:.2f} dB (reference image as-is: {baseline:.2f} dB)")
    assert oracle > baseline + 6
