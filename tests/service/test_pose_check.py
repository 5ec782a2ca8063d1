"""Given poses against their images (service.pose_check): a swapped pair or the other convention is a 422."""

import numpy as np
import pytest

from rasterizer.relative_pose import yaw_rotation
from rasterizer.scene_folder import load_scene
from service.errors import BadInput
from service.pose_check import CHECK_BELOW_CONFIDENCE, check_given_poses, readings

_FLIP = np.diag([1.0, -1.0, -1.0, 1.0])


def _c2w(yaw_deg, t):
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = yaw_rotation(np.radians(yaw_deg)), t
    return m


def _relative(c2w_a, c2w_b):
    rel = np.linalg.inv(c2w_a) @ c2w_b
    return rel[:3, :3], rel[:3, 3]


def test_each_reading_is_the_relative_pose_of_those_cameras():
    a, b = _c2w(20.0, [0.3, -0.1, 0.2]), _c2w(-65.0, [1.4, 0.05, -0.8])
    got = readings(a, b)
    for name, (pa, pb) in {"given": (a, b), "swapped": (b, a), "other convention": (a @ _FLIP, b @ _FLIP)}.items():
        R, t = _relative(pa, pb)
        assert np.allclose(got[name][0], R) and np.allclose(got[name][1], t), name


def test_confident_reconstructions_and_flat_images_are_not_refused():
    flat = np.full((64, 128, 3), 0.5, np.float32)
    a, b = np.eye(4), _c2w(0.0, [1.0, 0.0, 0.0])
    assert check_given_poses(flat, flat, a, b, CHECK_BELOW_CONFIDENCE) is None  # not checked
    assert check_given_poses(flat, flat, a, b, None) is None
    scores = check_given_poses(flat, flat, a, b, 0.0)  # checked: nothing agrees with anything
    assert set(scores) == {"given", "swapped", "other convention"} and max(scores.values()) == 0.0


def _small(img):
    import cv2

    return cv2.resize(img, (1024, 512), interpolation=cv2.INTER_AREA)


def test_swapped_images_and_the_other_convention_are_refused_the_right_poses_pass(bedroom_theta_dir):
    """A hand-held pair 0.8 m apart: the poses as captured agree best; the two images swapped, or both
    cameras read in OpenGL's axes, are 422 poses_mismatch naming what to check (forced: confidence 0)."""
    scene = load_scene(bedroom_theta_dir)
    fa, fb = scene.frames["3"], scene.frames["5"]
    img_a, img_b = _small(fa.image()), _small(fb.image())
    scores = check_given_poses(img_a, img_b, fa.c2w, fb.c2w, 0.0)
    assert scores["given"] > max(scores["swapped"], scores["other convention"])
    with pytest.raises(BadInput, match="two images swapped") as exc:
        check_given_poses(img_b, img_a, fa.c2w, fb.c2w, 0.0)
    assert exc.value.code == "poses_mismatch" and exc.value.status == 422
    with pytest.raises(BadInput, match="other axis convention.*check \"convention\"") as exc:
        check_given_poses(img_a, img_b, fa.c2w @ _FLIP, fb.c2w @ _FLIP, 0.0)
    assert exc.value.code == "poses_mismatch"


def test_post_with_the_images_swapped_is_a_422_and_stores_nothing(bedroom_theta_dir, model_path, tmp_path,
                                                                   monkeypatch):
    """Through the API (the small test model; the check forced on by its confidence gate): the right order is
    built, the swapped order is a 422 ``poses_mismatch`` and leaves no scene behind."""
    import io
    import json

    from PIL import Image

    import service.pose_check as pose_check

    from ._support import LiveServer, make_settings, post_scene, stored_scene_count

    monkeypatch.setattr(pose_check, "CHECK_BELOW_CONFIDENCE", 2.0)
    scene = load_scene(bedroom_theta_dir)
    fa, fb = scene.frames["3"], scene.frames["5"]

    def png(img):
        buf = io.BytesIO()
        Image.fromarray((np.clip(_small(img), 0, 1) * 255 + 0.5).astype(np.uint8)).save(buf, format="PNG")
        return buf.getvalue()

    a, b = png(fa.image()), png(fb.image())
    poses = json.dumps({"convention": "opencv", "c2w": [fa.c2w.tolist(), fb.c2w.tolist()]})
    store = tmp_path / "store"
    with LiveServer(make_settings(model_path, store, max_upload_bytes=8_000_000)) as server, server.client() as client:
        swapped = post_scene(client, b, a, poses)
        assert swapped.status_code == 422, swapped.text
        assert swapped.json()["error"]["code"] == "poses_mismatch" and "swapped" in swapped.json()["error"]["message"]
        assert stored_scene_count(store) == 0
        right = post_scene(client, a, b, poses)
        assert right.status_code == 201, right.text
        assert right.json()["timings"]["pose_check"] > 0  # the check ran, and its time is reported


def test_cli_reconstruct_refuses_the_swapped_images_as_the_api_does(bedroom_theta_dir, model_path, tmp_path,
                                                                     monkeypatch, capsys):
    import json

    from PIL import Image

    import service.pose_check as pose_check
    from service import cli

    monkeypatch.setattr(pose_check, "CHECK_BELOW_CONFIDENCE", 2.0)
    scene = load_scene(bedroom_theta_dir)
    fa, fb = scene.frames["3"], scene.frames["5"]
    for name, frame in (("a.png", fb), ("b.png", fa)):  # swapped
        Image.fromarray((np.clip(_small(frame.image()), 0, 1) * 255 + 0.5).astype(np.uint8)).save(tmp_path / name)
    (tmp_path / "poses.json").write_text(json.dumps({"c2w": [fa.c2w.tolist(), fb.c2w.tolist()]}))
    out = tmp_path / "scene.ply"
    assert cli.main(["reconstruct", str(tmp_path / "a.png"), str(tmp_path / "b.png"), "--poses",
                     str(tmp_path / "poses.json"), "--model", str(model_path), "--no-build", "-o", str(out)]) == 2
    assert "two images swapped" in capsys.readouterr().err and not out.exists()


def test_when_both_readings_fit_as_well_the_refusal_names_both(m3d_dir):
    """m3d's cameras are level and 1 m apart along a horizontal axis: the pair swapped and the pair read in
    OpenGL's axes are almost the same relative pose, so a refusal cannot tell which mistake was made."""
    scene = load_scene(m3d_dir)
    fa, fb = scene.frames["00"], scene.frames["02"]
    img_a, img_b = _small(fa.image()), _small(fb.image())
    with pytest.raises(BadInput, match="two images swapped or read in the other axis convention") as exc:
        check_given_poses(img_b, img_a, fa.c2w, fb.c2w, 0.0)
    assert "image_a is the panorama taken at the first pose" in exc.value.message
    assert 'check "convention"' in exc.value.message
