"""Geometry conventions against closed forms and finite differences."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rasterizer import geometry as geo

KINDS = ["erp", "yin", "yang"]


def test_erp_landmarks():
    h, w = 8, 16
    d = geo.grid_directions("erp", h, w)
    # image centre looks along +z, top rows up (-y), column 3W/4 right (+x)
    centre = 0.5 * (d[h // 2 - 1, w // 2 - 1] + d[h // 2, w // 2])
    assert np.allclose(centre / np.linalg.norm(centre), [0, 0, 1], atol=1e-12)
    assert d[0, :, 1].max() < -0.9
    lat, lon = geo.lat_lon_from_direction(d[:, 3 * w // 4])
    assert np.allclose(lon, 2 * np.pi * (3 * w / 4 + 0.5) / w - np.pi)
    assert np.allclose(np.linalg.norm(d, axis=-1), 1.0)


def test_yang_rotation_is_proper_involution():
    m = geo.YANG_ROTATION
    assert np.isclose(np.linalg.det(m), 1.0)
    assert np.allclose(m @ m, np.eye(3))
    assert np.allclose(m, m.T)


@pytest.mark.parametrize("kind", KINDS)
def test_pixel_direction_round_trip(kind):
    h, w = (16, 32) if kind == "erp" else (16, 48)
    d = geo.grid_directions(kind, h, w)
    col, row = geo.project_to_grid(kind, d * 3.7, h, w)
    rr, cc = np.mgrid[0:h, 0:w]
    assert np.allclose(col, cc, atol=1e-9)
    assert np.allclose(row, rr, atol=1e-9)
    assert geo.in_grid_domain(kind, d).all()


def test_yin_yang_cover_sphere_with_small_overlap():
    rng = np.random.default_rng(0)
    v = rng.normal(size=(400_000, 3))
    yin = geo.in_grid_domain("yin", v)
    yang = geo.in_grid_domain("yang", v)
    assert (yin | yang).all()  # no gap
    overlap = (yin & yang).mean()
    assert 0.055 < overlap < 0.067  # analytic 3*sqrt(2)/4 - 1 = 6.07%
    assert abs(yin.mean() - 3 * np.sqrt(2) / 8) < 0.003


@pytest.mark.parametrize("kind", KINDS)
@settings(max_examples=60, deadline=None)
@given(
    lat=st.floats(-1.45, 1.45),
    lon=st.floats(-3.0, 3.0),
    r=st.floats(0.01, 100.0),
)
def test_jacobian_matches_finite_differences(kind, lat, lon, r):
    h, w = (64, 128) if kind == "erp" else (64, 192)
    p = r * geo.direction_from_lat_lon(np.array(lat), np.array(lon))
    q = geo.to_grid_frame(kind, p)
    qlat, qlon = geo.lat_lon_from_direction(q)
    if abs(qlon) > 3.0 or abs(qlat) > 1.45:  # stay off the seam and poles of this grid's own frame
        return
    jac = geo.grid_jacobian(kind, p, h, w)
    eps = 1e-6 * r
    num = np.zeros((2, 3))
    for k in range(3):
        dp = np.zeros(3)
        dp[k] = eps
        c1, r1 = geo.project_to_grid(kind, p + dp, h, w)
        c0, r0 = geo.project_to_grid(kind, p - dp, h, w)
        num[:, k] = [(c1 - c0) / (2 * eps), (r1 - r0) / (2 * eps)]
    assert np.allclose(jac, num, rtol=1e-4, atol=1e-6 * np.abs(num).max())


def test_jacobian_finite_at_poles_and_origin():
    pts = np.array([[0, -1.0, 0], [0, 1.0, 0], [0, 0, 0], [1e-30, 0, 0]])
    for kind in KINDS:
        assert np.isfinite(geo.grid_jacobian(kind, pts, 64, 192)).all()


def test_yang_jacobian_is_yin_jacobian_of_rotated_point():
    rng = np.random.default_rng(1)
    p = rng.normal(size=(100, 3))
    j_yang = geo.grid_jacobian("yang", p, 32, 96)
    j_yin = geo.grid_jacobian("yin", p @ geo.YANG_ROTATION.T, 32, 96)
    assert np.allclose(j_yang, j_yin @ geo.YANG_ROTATION)


def test_pinhole_round_trip_and_jacobian():
    d = geo.pinhole_directions(40, 30, 90.0)
    fx, fy, cx, cy = geo.pinhole_intrinsics(40, 30, 90.0)
    col, row = geo.pinhole_project(d * 2.0, fx, fy, cx, cy)
    rr, cc = np.mgrid[0:30, 0:40]
    assert np.allclose(col, cc) and np.allclose(row, rr)
    p = np.array([0.3, -0.2, 1.7])
    jac = geo.pinhole_jacobian(p, fx, fy)
    eps = 1e-6
    for k in range(3):
        dp = np.zeros(3)
        dp[k] = eps
        a = np.array(geo.pinhole_project(p + dp, fx, fy, cx, cy))
        b = np.array(geo.pinhole_project(p - dp, fx, fy, cx, cy))
        assert np.allclose(jac[:, k], (a - b) / (2 * eps), rtol=1e-5)


def test_pose_validation():
    good = np.eye(4)
    good[:3, 3] = [1, 2, 3]
    assert np.allclose(geo.as_c2w(good), good)
    assert np.allclose(geo.as_c2w(good[:3]), good)
    gl = geo.as_c2w(good, "opengl")
    assert np.allclose(gl[:3, 1], [0, -1, 0])
    bad_cases = {
        "shape": np.eye(3),
        "NaN": np.full((4, 4), np.nan),
        "orthonormal": np.diag([2.0, 1, 1, 1]),
        "mirror": np.diag([-1.0, 1, 1, 1]),
        "bottom row": np.vstack([np.eye(4)[:3], [0, 0, 1, 1]]),
    }
    for word, m in bad_cases.items():
        with pytest.raises(geo.PoseError, match=word):
            geo.as_c2w(m)
    with pytest.raises(geo.PoseError, match="convention"):
        geo.as_c2w(good, "blender")


@pytest.mark.parametrize("entries", [
    [[str(v) for v in row] for row in np.eye(4)],  # "1.0": numpy would read the text as a number
    np.eye(4).astype(bool).tolist(),
    [[1, 0, 0, 0], [0, 1, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
    [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, None], [0, 0, 0, 1]],
])
def test_a_pose_of_entries_that_are_not_numbers_is_refused(entries):
    """Entries written as text, booleans, None or rows of different lengths are no pose, as the API's JSON check
    says (the scene folders' and the CLI's pose files read through this one)."""
    with pytest.raises(geo.PoseError, match="not a numeric 4x4 or 3x4 matrix"):
        geo.as_c2w(entries)
    assert np.allclose(geo.as_c2w(np.eye(4, dtype=np.float32)), np.eye(4))
    assert np.allclose(geo.as_c2w(np.eye(4, dtype=int).tolist()), np.eye(4))


def test_rigid_inverse_and_yang_pose():
    rng = np.random.default_rng(2)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    c2w = np.eye(4)
    c2w[:3, :3] = q
    c2w[:3, 3] = rng.normal(size=3)
    assert np.allclose(geo.rigid_inverse(c2w) @ c2w, np.eye(4))
    # the Yin image of yang_pose(c2w) is the Yang image of c2w
    world = rng.normal(size=(50, 3)) * 5
    p_cam = geo.world_to_camera(world, c2w)
    p_yang_cam = geo.world_to_camera(world, geo.yang_pose(c2w))
    a = geo.project_to_grid("yang", p_cam, 16, 48)
    b = geo.project_to_grid("yin", p_yang_cam, 16, 48)
    assert np.allclose(a, b)
