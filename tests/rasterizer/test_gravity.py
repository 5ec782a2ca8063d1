"""Gravity geometry: pitch/roll readings, the levelling turn, the vertical vanishing point of line normals."""

import numpy as np
import pytest

from rasterizer.gravity import down_from_pitch_roll, level_rotation, line_support, tilt_deg, vertical_from_lines


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def test_pitch_roll_signs_and_size():
    assert np.allclose(down_from_pitch_roll(0, 0), [0, 1, 0])
    up = down_from_pitch_roll(5, 0)  # centre above the horizon: gravity behind the centre
    assert up[2] < 0 and abs(up[0]) < 1e-12 and abs(tilt_deg(up) - 5) < 1e-9
    rolled = down_from_pitch_roll(0, 4)
    assert rolled[0] > 0 and abs(rolled[2]) < 1e-12 and abs(tilt_deg(rolled) - 4) < 1e-9


@pytest.mark.parametrize("down", [[0.05, 1, -0.03], [0, 1, 0], [-0.2, 1, 0.1], [0, -1, 0]])
def test_level_rotation_maps_down_to_y_without_yaw(down):
    d = _unit(np.array(down, float))
    L = level_rotation(d)
    assert np.allclose(L @ d, [0, 1, 0]) and np.allclose(L @ L.T, np.eye(3)) and np.isclose(np.linalg.det(L), 1)
    axis = np.cross(d, [0, 1, 0])
    if np.linalg.norm(axis) > 1e-9:  # the turn is about the axis perpendicular to both: no yaw
        assert np.allclose(L @ axis, axis)


def _line_normals(down, n_vertical=40, n_other=60, noise_deg=0.05, seed=0):
    """Great-circle normals of vertical lines (all perpendicular to ``down``) plus others in any direction."""
    rng = np.random.default_rng(seed)
    down = _unit(np.asarray(down, float))
    h = _unit(np.cross(down, rng.normal(size=(n_vertical, 3))))  # perpendicular to down
    h = _unit(h + rng.normal(0, np.radians(noise_deg), h.shape))
    other = _unit(rng.normal(size=(n_other, 3)))
    return np.concatenate([h, other]), rng.uniform(0.05, 0.3, n_vertical + n_other)


@pytest.mark.parametrize("pitch, roll", [(0, 0), (4, -3), (-6, 2), (10, 8)])
def test_vertical_from_lines_recovers_the_tilt(pitch, roll):
    down = down_from_pitch_roll(pitch, roll)
    normals, w = _line_normals(down)
    est, info = vertical_from_lines(normals, w)
    assert np.degrees(np.arccos(np.clip(est @ down, -1, 1))) < 0.1
    assert info["inliers"] >= 35 and info["spread_deg"] > 90


def test_vertical_from_lines_needs_lines():
    with pytest.raises(ValueError):
        vertical_from_lines(_unit(np.random.default_rng(0).normal(size=(5, 3))), np.ones(5))


def test_line_support_counts_agreeing_segments():
    down = down_from_pitch_roll(3, 1)
    normals, w = _line_normals(down, n_other=0)
    count, share = line_support(normals, w, down, agree_deg=0.5)
    assert count == 40 and share == pytest.approx(1.0)
    count, share = line_support(normals, w, down_from_pitch_roll(-3, 1), agree_deg=0.5)
    assert share < 0.3
