"""A panorama posted again keeps its features: :func:`service.poses.prepare` returns what it found for the same
grey pixels and file bytes, and an estimate from kept features equals a fresh one."""

import numpy as np
import pytest

from rasterizer.relative_pose import yaw_rotation
from service import poses
from service.poses import PoseOptions, estimate_poses, prepare
from tests.service._support import room_erp


@pytest.fixture()
def counted(monkeypatch):
    """The SIFT calls of each test, on an empty cache."""
    calls = []
    real = poses.features
    monkeypatch.setattr(poses, "features", lambda gray: calls.append(gray.shape) or real(gray))
    poses.clear_prepared_cache()
    yield calls
    poses.clear_prepared_cache()


@pytest.fixture(scope="module")
def pair():
    c2w_b = np.eye(4)
    c2w_b[:3, :3], c2w_b[:3, 3] = yaw_rotation(np.radians(35.0)), [1.2, 0.0, 0.6]
    return room_erp(np.eye(4), height=256), room_erp(c2w_b, height=256)


def test_the_same_picture_is_prepared_once(pair, counted):
    a, _ = pair
    first = prepare(a, b"file")
    again = prepare(a.copy(), b"file")
    assert len(counted) == 1
    for name in ("gray", "bearings", "descriptors", "level"):
        assert np.array_equal(getattr(first, name), getattr(again, name))
        assert not getattr(again, name).flags.writeable
    assert again.gravity == first.gravity and again.gravity is not first.gravity
    again.gravity["applied"] = "changed by a caller"
    assert prepare(a, b"file").gravity == first.gravity


def test_other_pixels_or_other_bytes_are_prepared_anew(pair, counted):
    a, _ = pair
    prepare(a, b"file")
    prepare(a, b"other file")  # another XMP reading may hold another tilt
    prepare(a, None)
    changed = a.copy()
    changed[10, 10] = 255 - changed[10, 10]
    prepare(changed, b"file")
    assert len(counted) == 4


def test_the_least_recently_used_goes_first(pair, counted, monkeypatch):
    monkeypatch.setattr(poses, "PREPARED_CACHE_SIZE", 2)
    a, b = pair
    c = np.ascontiguousarray(a[:, ::-1])
    prepare(a)
    prepare(b)
    prepare(a)  # a is now the newest
    prepare(c)  # b goes
    prepare(a)
    assert len(counted) == 3
    prepare(b)
    assert len(counted) == 4


def test_a_grey_upload_is_not_made_read_only(counted):
    grey = np.ascontiguousarray(room_erp(np.eye(4), height=128)[..., 1])
    pano = prepare(grey)
    assert grey.flags.writeable and not pano.gray.flags.writeable
    grey[0, 0] ^= 1  # the caller's array stays its own
    assert pano.gray[0, 0] != grey[0, 0]


def test_an_estimate_from_kept_features_equals_a_fresh_one(pair, counted):
    a, b = pair
    fresh = estimate_poses(a, b, PoseOptions(baseline=2.0))
    kept = estimate_poses(a, b, PoseOptions(baseline=2.0))
    assert len(counted) == 2
    assert np.array_equal(fresh[0], kept[0]) and np.array_equal(fresh[1], kept[1])
    assert fresh[2]["inliers"] == kept[2]["inliers"]
