"""bench.coverage helpers and the plain / V/A compositing of the benches."""

import numpy as np
import pytest

from bench.coverage import alpha_stats, perspective_crop, yaw_pose
from bench.quality import alpha_normalised, composited


def test_composited_plain_and_va():
    rng = np.random.default_rng(0)
    colour = rng.random((4, 8, 3)).astype(np.float32)
    alpha = np.array([0.0, 0.001, 0.5, 1.0] * 8, np.float32).reshape(4, 8)
    # Yin-Yang renders return V/A colour: plain is it times alpha (the merged premultiplied colour)
    np.testing.assert_allclose(composited(colour, alpha, "yinyang", "plain"), colour * alpha[..., None])
    np.testing.assert_array_equal(composited(colour, alpha, "yinyang", "va"), colour)
    # direct renders return plain colour: V/A divides where alpha >= 1/255 and is 0 elsewhere
    np.testing.assert_array_equal(composited(colour, alpha, "direct", "plain"), colour)
    va = composited(colour, alpha, "direct", "va")
    np.testing.assert_array_equal(va, alpha_normalised(colour, alpha))
    assert np.all(va[alpha < 1 / 255] == 0)
    with pytest.raises(ValueError, match="compositing"):
        composited(colour, alpha, "direct", "over")


def test_yaw_turns_the_view_right():
    pose = yaw_pose(np.eye(4), 90.0)
    np.testing.assert_allclose(pose[:3, 2], [1.0, 0.0, 0.0], atol=1e-12)  # +z (forward) -> +x (right)
    np.testing.assert_allclose(pose[:3, 1], [0.0, 1.0, 0.0], atol=1e-12)  # the vertical stays
    np.testing.assert_allclose(yaw_pose(pose, -90.0), np.eye(4), atol=1e-12)


def test_perspective_crop_follows_the_yaw():
    """A crop at yaw 90 of an ERP is the crop at yaw 0 of the ERP rolled by a quarter turn."""
    h, w = 32, 64
    rng = np.random.default_rng(1)
    erp = rng.random((h, w, 3)).astype(np.float32)
    a = perspective_crop(erp, 90.0, 24, 16, 60.0)
    b = perspective_crop(np.roll(erp, -w // 4, axis=1), 0.0, 24, 16, 60.0)
    np.testing.assert_allclose(a, b, atol=1e-5)
    flat = perspective_crop(np.full((h, w, 3), 0.25, np.float32), 180.0, 24, 16, 60.0)
    np.testing.assert_allclose(flat, 0.25, atol=1e-6)


def test_alpha_stats_counts_covered_pixels():
    alpha = np.array([[0.2, 0.99], [0.995, 1.0]], np.float32)
    s = alpha_stats(alpha)
    assert s["covered"] == pytest.approx(0.75) and s["mean_alpha"] == pytest.approx(alpha.mean())
    assert alpha_stats(alpha, alpha > 0.5)["covered"] == 1.0
