"""Scene-folder reading and the image metrics."""

import numpy as np
import pytest

from bench.metrics import NADIR_CAP_DEG, psnr, psnr_above_nadir, ssim, ws_psnr
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


def test_psnr_above_nadir_leaves_out_the_bottom_cap():
    """Only rows within the cap of the nadir are left out; an error there does not count."""
    h, w = 36, 72  # 5 deg rows
    target = np.full((h, w, 3), 0.5)
    pred = target.copy()
    cap_rows = int(round(h * NADIR_CAP_DEG / 180))  # 3 rows at 15 deg
    pred[h - cap_rows:] = 0.0  # a rig-like dark disc at the nadir
    assert psnr(pred, target) < 20.0
    assert psnr_above_nadir(pred, target) == float("inf")
    pred[h - cap_rows - 1] += 0.1  # the first row above the cap counts
    mse = 0.01 / (h - cap_rows)
    assert np.isclose(psnr_above_nadir(pred, target), -10 * np.log10(mse))
    assert np.isclose(psnr_above_nadir(pred, target, cap_deg=0.0), psnr(pred, target))
    with pytest.raises(ValueError, match="cap_deg"):
        psnr_above_nadir(pred, target, cap_deg=90.0)
