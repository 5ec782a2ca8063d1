"""bench/poses.py helpers: pose errors, the similarity into the estimate's frame, camera height."""

from types import SimpleNamespace

import numpy as np
import pytest

from bench.poses import camera_height, into_estimate, pose_errors
from rasterizer.relative_pose import yaw_rotation
from rasterizer.scene_folder import load_scene


def _pose(yaw_deg, t):
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = yaw_rotation(np.radians(yaw_deg)), t
    return m


def test_pose_errors():
    e = pose_errors(_pose(10, [1, 0, 0]), _pose(12, [0, 0, 1.1]))
    assert abs(e["rotation_deg"] - 2) < 1e-9 and abs(e["direction_deg"] - 90) < 1e-9 and abs(e["scale_pct"] - 10) < 1e-9


def test_into_estimate_maps_a_to_identity_and_scales():
    c2w_a, c2w_t = _pose(30, [1, 2, 3]), _pose(50, [2, 2, 3])
    assert np.allclose(into_estimate(c2w_a, c2w_a, 2.0), np.eye(4))
    m = into_estimate(c2w_a, c2w_t, 2.0)
    assert abs(np.linalg.norm(m[:3, 3]) - 2.0) < 1e-9 and np.allclose(m[:3, :3], yaw_rotation(np.radians(20)))


def test_camera_height_from_depth_and_from_z(m3d_dir, zind_dir):
    m3d = load_scene(m3d_dir)
    assert 0.8 < camera_height(m3d, m3d.frames["00"]) < 2.0
    zind = load_scene(zind_dir)
    assert abs(camera_height(zind, zind.frames["pano_2"]) - 1.435) < 1e-3


def test_camera_height_without_depth_or_height_asks_for_the_option():
    """A structure-from-motion frame (no depth map, world origin at a camera) gives no height: the bench
    says so instead of building a scene at zero baseline."""
    frame = SimpleNamespace(name="1", depth=lambda: None, c2w=np.eye(4))
    with pytest.raises(SystemExit, match="--camera-height"):
        camera_height(SimpleNamespace(name="handheld"), frame)


def test_pairs_markdown_counts_a_422_as_a_miss():
    from bench.poses import pairs_markdown

    ok = {"rotation_deg": 0.5, "direction_deg": 1.0, "scale_pct": 10.0, "inliers": 300, "method": "m", "seconds": 1.0}
    far = {**ok, "rotation_deg": 1.5, "scale_pct": -20.0}
    rows = [{"scene": "s", "references": [a, b], "baseline_m": 1.0, "estimate": e}
            for a, b, e in (("1", "2", ok), ("1", "3", far), ("2", "3", {"error": "ambiguous_pose", "seconds": 1.0}))]
    rows[0]["estimate"]["scale"] = {"floor": "dense", "seconds": 0.25}
    text = pairs_markdown(rows)
    assert "| dense (0.25) |" in text and "median 0.25 s per pair" in text
    assert "422 `ambiguous_pose`" in text and "1.10x" in text and "0.80x" in text
    assert "3 pairs: rotation <= 1 deg on 33%, travel direction <= 2 deg on 67%, baseline within 15% on 33%" in text
