"""Gaussians container and covariance <-> scale/rotation conversions."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rasterizer.gaussians import (
    Gaussians,
    GaussiansError,
    covariance_from_scale_rotation,
    quat_to_rotmat,
    rotmat_to_quat,
    scale_rotation_from_covariance,
)


def random_quats(rng, n):
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def test_quaternion_round_trip_and_proper_rotation():
    rng = np.random.default_rng(0)
    q = random_quats(rng, 500)
    q[:3] = [[0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]  # 180-degree turns
    rot = quat_to_rotmat(q)
    assert np.allclose(np.linalg.det(rot), 1)
    assert np.allclose(rot @ np.swapaxes(rot, 1, 2), np.eye(3), atol=1e-12)
    q2 = rotmat_to_quat(rot)
    assert np.allclose(np.abs(np.sum(q * q2, axis=1)), 1.0)


@settings(max_examples=40, deadline=None)
@given(log_s=st.lists(st.floats(-8, 4), min_size=3, max_size=3), seed=st.integers(0, 10_000))
def test_covariance_round_trip(log_s, seed):
    rng = np.random.default_rng(seed)
    s = 10.0 ** np.array([log_s])
    q = random_quats(rng, 1)
    cov = covariance_from_scale_rotation(s, q)
    s2, q2 = scale_rotation_from_covariance(cov)
    cov2 = covariance_from_scale_rotation(s2, q2)
    assert np.allclose(cov2, cov, rtol=1e-6, atol=1e-12 * s.max() ** 2 + 1e-30)
    # eigh is accurate to eps * |cov|, so small scales are exact only up to ~sqrt(eps) * s_max
    assert np.allclose(np.sort(s2[0]), np.sort(s[0]), rtol=1e-4, atol=1e-7 * s.max())


def test_rank_deficient_covariance_gives_finite_scales():
    cov = np.zeros((2, 3, 3))
    cov[1, 0, 0] = 1.0
    s, q = scale_rotation_from_covariance(cov)
    assert np.isfinite(np.log(s)).all() and np.isfinite(q).all()


def test_container_validates_shapes_and_values():
    g = Gaussians(np.zeros((2, 3)), np.ones((2, 3)), [[1, 0, 0, 0]] * 2, [0.5, 1.0], np.zeros((2, 3)))
    assert len(g) == 2 and g.sh.shape == (2, 1, 3) and g.means.dtype == np.float32
    assert np.allclose(g.rgb, 0.5)
    with pytest.raises(GaussiansError, match="scales"):
        Gaussians(np.zeros((2, 3)), np.ones((3, 3)), [[1, 0, 0, 0]] * 2, [0.5, 1.0], np.zeros((2, 3)))
    with pytest.raises(GaussiansError, match="NaN"):
        g.with_(means=np.array([[np.nan, 0, 0], [0, 0, 0]])).check_finite()
    both = Gaussians.concatenate([g, g.subset(np.array([True, False]))])
    assert len(both) == 3


def test_concatenate_keeps_order_and_pads_missing_sh_bands_with_zeros():
    rng = np.random.default_rng(3)

    def random_gaussians(n, k):
        return Gaussians(rng.normal(size=(n, 3)), rng.random((n, 3)), rng.normal(size=(n, 4)), rng.random(n),
                         rng.normal(size=(n, k, 3)))

    parts = [random_gaussians(5, 4), random_gaussians(0, 1), random_gaussians(3, 1), random_gaussians(2, 9)]
    both = Gaussians.concatenate(parts)
    assert len(both) == 10 and both.sh.shape == (10, 9, 3)
    for name in ("means", "scales", "quats", "opacities"):
        np.testing.assert_array_equal(getattr(both, name), np.concatenate([getattr(p, name) for p in parts]))
    start = 0
    for p in parts:
        k = p.sh.shape[1]
        np.testing.assert_array_equal(both.sh[start:start + len(p), :k], p.sh)
        assert not both.sh[start:start + len(p), k:].any()
        start += len(p)
    assert len(Gaussians.concatenate([])) == 0
