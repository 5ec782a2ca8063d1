"""Scene-folder reading and the image metrics."""

import numpy as np

from bench.metrics import psnr, ssim, ws_psnr
from rasterizer.scene_folder import load_scene


def test_load_dev_scene(m3d_dir):
    scene = load_scene(m3d_dir)
    assert set(scene.frames) == {"00", "01", "02"}
    assert scene.splits[0].references == ("00", "02")
    f = scene.frames["00"]
    img, depth = f.image(), f.depth()
    assert img.shape == (512, 1024, 3) and img.dtype == np.float32
    assert depth.shape == (512, 1024) and np.isfinite(depth).all()
    # frame 00 sits 0.5 m forward (-z world) of 01
    assert np.allclose(f.c2w[:3, 3] - scene.frames["01"].c2w[:3, 3], [0, 0, -0.5])


def test_metrics_closed_forms():
    rng = np.random.default_rng(0)
    a = rng.random((32, 64, 3))
    assert psnr(a, a) == float("inf")
    b = np.clip(a + 0.1, 0, 1)
    mse = np.mean((b - a) ** 2)
    assert np.isclose(psnr(b, a), -10 * np.log10(mse))
    # a uniform error gives WS-PSNR == PSNR
    c = np.full_like(a, 0.5)
    assert np.isclose(ws_psnr(c + 0.05, c), psnr(c + 0.05, c))
    assert np.isclose(ssim(a, a), 1.0) and ssim(b, a) < 1.0
    # values outside [0, 1] are clipped before PSNR
    assert psnr(a + 5.0, np.ones_like(a)) == float("inf")
