"""Upright relative pose from bearings: minimal solver + RANSAC, refinement, floor scale."""

import numpy as np
import pytest

from rasterizer.relative_pose import (
    epipolar_error,
    floor_scale,
    refine_general,
    refine_upright,
    rotation_exp,
    rotation_only_fraction,
    tilt_between,
    triangulate,
    upright_ransac,
    yaw_rotation,
)


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _matches(yaw_deg, t, n=200, outliers=0.25, noise_deg=0.0, seed=0, points=None):
    """Bearings of random room points seen from A = I and B = [yaw_rotation(yaw) | t]; some replaced by outliers."""
    rng = np.random.default_rng(seed)
    X = points if points is not None else rng.uniform([-4, -1.2, -4], [4, 1.5, 4], (n, 3))
    R = yaw_rotation(np.radians(yaw_deg))
    fa = _unit(X)
    fb = _unit((X - t) @ R)
    if noise_deg:
        fa = _unit(fa + rng.normal(0, np.radians(noise_deg), fa.shape))
        fb = _unit(fb + rng.normal(0, np.radians(noise_deg), fb.shape))
    k = int(outliers * len(X))
    fb[:k] = _unit(rng.normal(size=(k, 3)))
    return fa, fb


def _angle(u, v):
    return np.degrees(np.arccos(np.clip(_unit(u) @ _unit(v), -1, 1)))


@pytest.mark.parametrize("yaw_deg, t", [
    (37.0, [1.5, 0.05, -0.8]),
    (179.6, [0.0, 0.0, -1.0]),   # B turned to face A's seam, moving towards it: epipoles on the seam
    (-179.6, [0.3, 0.0, 1.0]),   # yaw across the +-180 wrap
    (0.0, [0.0, 0.0, 0.5]),      # pure forward motion, identical orientation (m3d-like)
])
def test_ransac_recovers_pose_with_outliers(yaw_deg, t):
    t = np.asarray(t, float)
    fa, fb = _matches(yaw_deg, t, noise_deg=0.1)
    res = upright_ransac(fa, fb)
    yaw, tt = refine_upright(fa[res.best.inliers], fb[res.best.inliers], res.best.yaw, res.best.t)
    assert abs(np.degrees(np.angle(np.exp(1j * (yaw - np.radians(yaw_deg)))))) < 0.2
    assert _angle(tt, t) < 1.0  # sign from cheirality: not the flipped direction
    assert res.best.num_inliers >= 0.6 * len(fa)


def test_points_at_the_poles_are_handled():
    rng = np.random.default_rng(3)
    X = rng.uniform([-3, -1.2, -3], [3, 1.5, 3], (150, 3))
    X[:20, 0] = X[:20, 2] = 1e-9  # straight up and down from A
    fa, fb = _matches(20.0, np.array([1.0, 0.0, 0.3]), points=X, outliers=0.1)
    assert np.isfinite(epipolar_error(fa, fb, yaw_rotation(0.3), np.array([1.0, 0, 0]))).all()
    res = upright_ransac(fa, fb)
    assert _angle(res.best.t, [1.0, 0.0, 0.3]) < 1.5


def test_epipolar_error_is_zero_for_true_pose_and_triangulation_is_exact():
    t = np.array([0.8, -0.1, 0.4])
    fa, fb = _matches(-65.0, t, outliers=0.0)
    R = yaw_rotation(np.radians(-65.0))
    assert np.degrees(epipolar_error(fa, fb, R, t)).max() < 1e-6
    la, lb = triangulate(fa, fb, R, t)
    assert np.allclose(la[:, None] * fa, lb[:, None] * (fb @ R.T) + t, atol=1e-6)
    assert np.degrees(epipolar_error(fa, fb, R, -t)).max() < 1e-6  # the sign of t is not epipolar...
    la, lb = triangulate(fa, fb, R, -t)
    assert (la < 0).mean() > 0.9  # ...cheirality decides it


def test_rotation_only_fraction_tells_parallax_apart():
    fa, fb = _matches(30.0, np.array([1.0, 0, 0]), outliers=0.0)
    assert rotation_only_fraction(fa, fb) < 0.2
    fa2, fb2 = _matches(30.0, np.zeros(3), outliers=0.0)
    assert rotation_only_fraction(fa2, fb2) > 0.95


def test_rotation_only_fraction_is_the_share_of_matches_some_yaw_turns_onto_each_other():
    """Against its definition: every bearing of B turned by every yaw of the 0.5-deg search."""
    rng = np.random.default_rng(3)
    fa, fb = _matches(-70.0, np.zeros(3), outliers=0.3)
    fb = fb + rng.normal(scale=0.004, size=fb.shape)  # some within the 0.5 deg, some not
    fb /= np.linalg.norm(fb, axis=1, keepdims=True)
    turned = np.einsum("yij,nj->yni", yaw_rotation(np.radians(np.arange(0.0, 360.0, 0.5))), fb)
    expected = np.max(np.mean(np.sum(turned * fa, -1) > np.cos(np.radians(0.5)), axis=1))
    assert rotation_only_fraction(fa, fb) == expected and 0.2 < expected < 0.9
    assert rotation_only_fraction(fa[:0], fb[:0]) == 0.0


def test_ransac_reports_a_rival_mode():
    fa, fb = _matches(10.0, np.array([1.0, 0, 0.2]), outliers=0.0)
    res = upright_ransac(fa, fb)
    assert res.rival is None or res.rival.num_inliers < 0.5 * res.best.num_inliers
    # two scenes superposed, each consistent with its own pose: RANSAC sees two modes
    fa2, fb2 = _matches(190.0, np.array([-1.0, 0, -0.2]), outliers=0.0, seed=5)
    res2 = upright_ransac(np.concatenate([fa, fa2]), np.concatenate([fb, fb2]))
    assert res2.rival is not None and res2.rival.num_inliers > 0.7 * res2.best.num_inliers


def test_floor_scale_finds_the_floor_below_furniture():
    rng = np.random.default_rng(0)
    h = 1.4  # metres; the points are in units of 1/scale
    floor = np.c_[rng.uniform(-4, 4, 80), np.full(80, h), rng.uniform(-4, 4, 80)]
    table = np.c_[rng.uniform(-1, 1, 30), np.full(30, h - 0.75), rng.uniform(0.5, 1.5, 30)]
    walls = np.c_[rng.uniform(-4, 4, 60), rng.uniform(-1, h, 60), np.full(60, 4.0)]
    pts = np.concatenate([floor, table, walls]) / 2.5  # the estimate's unit is 2.5 m
    scale, info = floor_scale(pts, h)
    assert abs(scale / 2.5 - 1) < 0.02 and info["floor_points"] >= 40
    with pytest.raises(ValueError, match="floor"):
        floor_scale(walls[:3], h)


def test_floor_scale_takes_the_lowest_wide_plane_not_the_densest():
    """A bed top with three times the floor's points, a few strays and a small cluster (a reflection) under
    the floor, a small box on it: the floor is the lowest slab that is both well supported and wide."""
    rng = np.random.default_rng(1)
    h = 2.2
    floor = np.c_[rng.uniform(-3, 3, 40), np.full(40, h), rng.uniform(-3, 3, 40)]
    bed = np.c_[rng.uniform(0.5, 2.0, 120), np.full(120, h - 0.6), rng.uniform(-1.0, 1.0, 120)]
    mirrored = np.c_[rng.uniform(-2, 2, 9), np.full(9, h + 0.5), rng.uniform(-2, 2, 9)]
    box = np.c_[rng.uniform(-2.0, -1.9, 12), np.full(12, h - 0.25), rng.uniform(1.0, 1.1, 12)]  # small, not a floor
    strays = np.c_[rng.uniform(-3, 3, 4), rng.uniform(h + 0.3, h + 1.5, 4), rng.uniform(-3, 3, 4)]
    walls = np.c_[rng.uniform(-3, 3, 100), rng.uniform(0.3, h, 100), np.full(100, 3.0)]
    pts = np.concatenate([floor, bed, box, strays, mirrored, walls]) / 0.8  # the estimate's unit is 0.8 m
    scale, info = floor_scale(pts, h)
    assert abs(scale / 0.8 - 1) < 0.02 and info["floor_points"] >= 35


def test_floor_scale_slab_is_as_thick_as_the_floor_points_depth_scatter():
    """Seen with 6-8 deg of parallax, a floor scatters by about +-5% in depth (0.5 deg / sin 6 deg): a thin slab
    splits it below a third of the bed top's count and takes the bed; with the parallax the slab widens."""
    rng = np.random.default_rng(4)
    h = 2.2
    floor = np.c_[rng.uniform(-3, 3, 40), h * np.exp(rng.normal(0, 0.05, 40)), rng.uniform(-3, 3, 40)]
    bed = np.c_[rng.uniform(0.5, 2.0, 90), np.full(90, h - 0.5), rng.uniform(-1.0, 1.0, 90)]
    pts = np.concatenate([floor, bed])
    parallax = np.radians(np.r_[np.full(40, 6.0), np.full(90, 8.0)])
    assert floor_scale(pts, h)[0] > 1.2  # thin slab: the bed top
    scale, info = floor_scale(pts, h, parallax)
    assert abs(scale - 1) < 0.06 and info["floor_points"] >= 15


def test_floor_scale_refuses_when_the_floor_is_not_seen():
    rng = np.random.default_rng(2)
    walls = np.c_[rng.uniform(-3, 3, 200), rng.uniform(0.3, 2.2, 200), np.full(200, 3.0)]  # no plane at all
    with pytest.raises(ValueError, match="floor is not seen"):
        floor_scale(walls, 2.2)


def test_refine_general_recovers_a_tilted_pose_from_the_upright_guess():
    """B tilted 4 deg against A: starting from the best upright pose, the 5-dof refinement finds the tilt."""
    rng = np.random.default_rng(3)
    X = rng.uniform([-4, -1.2, -4], [4, 1.5, 4], (300, 3))
    tilt = rotation_exp(np.radians([3.0, 0.0, -2.5]))
    R_true, t_true = yaw_rotation(np.radians(40)) @ tilt, np.array([0.8, 0.05, 0.4])
    fa = _unit(X + rng.normal(0, 0.003, X.shape))
    fb = _unit((X - t_true) @ R_true)
    fb[:60] = _unit(rng.normal(size=(60, 3)))  # 20% outliers
    R, t = refine_general(fa, fb, yaw_rotation(np.radians(40)), _unit(np.array([0.8, 0.0, 0.4])))
    assert tilt_between(R_true) > 3.5
    assert np.degrees(np.arccos(np.clip((np.trace(R.T @ R_true) - 1) / 2, -1, 1))) < 0.2
    assert _angle(t, t_true) < 0.5


def test_rotation_exp_is_a_rotation_by_the_vector_length():
    R = rotation_exp(np.array([0.0, np.radians(30), 0.0]))
    assert np.allclose(R, yaw_rotation(np.radians(30))) and abs(tilt_between(R)) < 1e-6
    assert abs(tilt_between(rotation_exp(np.radians([5.0, 0, 0]))) - 5.0) < 1e-9
