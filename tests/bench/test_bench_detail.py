"""The detail bench's metrics (bench.metrics: sharpness and GMSD of conventions section 6) and its view scores."""

import numpy as np
import pytest
from scipy.ndimage import uniform_filter

from bench import metrics
from bench.detail import view_metrics


def _image(seed=0, size=(32, 64)):
    return np.random.default_rng(seed).random((*size, 3))


def test_identical_images_score_one_and_zero():
    a = _image()
    assert metrics.sharpness(a, a) == 1.0
    assert metrics.gmsd(a, a) == 0.0
    assert metrics.sharpness(a, a, 0.0) == 1.0 and metrics.gmsd(a, a, 0.0) == 0.0


def test_blur_lowers_sharpness_and_raises_gmsd():
    a = _image()
    soft = uniform_filter(a, (3, 3, 1), mode="wrap")
    softer = uniform_filter(a, (5, 5, 1), mode="wrap")
    assert 0 < metrics.sharpness(softer, a) < metrics.sharpness(soft, a) < 0.5
    assert metrics.gmsd(softer, a) > metrics.gmsd(soft, a) > 0.05
    flat = np.full_like(a, 0.5)
    assert metrics.sharpness(flat, a) < 1e-9


def test_box_is_a_5x5_mean_wrapping_in_longitude_clamped_in_latitude():
    y = metrics.luma(_image(3))
    expected = uniform_filter(y, 5, mode=("nearest", "wrap"))
    assert np.allclose(metrics.box5_erp(y), expected, atol=1e-12)
    # the same image turned in longitude has the same high-frequency energy: the seam is no edge of the box
    a = np.zeros((16, 32, 3))
    a[:, :16] = 1.0
    assert abs(metrics.detail(np.roll(a, 8, axis=1)) - metrics.detail(a)) < 1e-12


def test_rows_above_the_cap_are_the_rows_north_of_its_latitude():
    rows = metrics.above_nadir_rows(512, metrics.NADIR_CAP_DEG)  # -75 deg latitude
    assert rows[:469].all() and not rows[469:].any()
    assert metrics.above_nadir_rows(8, 0.0).all()
    a, b = _image(1), _image(2)
    keep = metrics.above_nadir_rows(32, 45.0)  # rows above -45 deg: 24 of 32
    assert keep.sum() == 24
    c = b.copy()
    c[26:] = 0.0  # rows the metrics neither keep nor read (box5 reaches 2 rows, GMSD's pooled Prewitt 2)
    assert metrics.detail(c, keep) == metrics.detail(b, keep)
    assert metrics.sharpness(c, a, 45.0) == metrics.sharpness(b, a, 45.0)
    assert metrics.gmsd(c, a, 45.0) == metrics.gmsd(b, a, 45.0)
    assert metrics.sharpness(c, a, 0.0) != metrics.sharpness(b, a, 0.0)
    assert metrics.gmsd(c, a, 0.0) != metrics.gmsd(b, a, 0.0)


def test_view_metrics_score_every_row_of_synthetic_scenes_and_real_captures_above_the_cap():
    target = _image(4, (64, 128))
    nadir = target.copy()
    nadir[-2:] = 0.0  # the last 2 of 64 rows lie below -75 deg (the rig of a real capture)
    real = view_metrics(nadir, target, metrics.NADIR_CAP_DEG)
    assert real == {"psnr": float("inf"), "sharpness": 1.0, "gmsd": 0.0}
    synthetic = view_metrics(nadir, target, 0.0)
    assert synthetic["psnr"] == pytest.approx(round(metrics.psnr(nadir, target), 3))
    assert synthetic["psnr"] < 30 and synthetic["sharpness"] != 1.0 and synthetic["gmsd"] > 0.0


def test_detail_is_a_bench_command(capsys):
    from bench.__main__ import main

    with pytest.raises(SystemExit) as info:
        main(["detail", "--help"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    assert "--render-width" in out and "--scene" in out
