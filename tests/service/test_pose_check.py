"""Given poses against their images (service.pose_check): a swapped pair, the other convention, world-to-camera
matrices sent as c2w, or panoramas whose longitude origin is turned or that are mirrored, are a 422."""

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

import service.pose_check as pose_check
from rasterizer.relative_pose import yaw_rotation
from rasterizer.scene_folder import load_scene
from service.errors import BadInput
from service.pose_check import CHECK_BELOW_CONFIDENCE, check_given_poses, feature_support, readings

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
    expected = {"given": (a, b), "swapped": (b, a), "other convention": (a @ _FLIP, b @ _FLIP),
                "world-to-camera": (np.linalg.inv(a), np.linalg.inv(b))}
    for deg in (90, 180, 270):  # the cameras' forward axis a quarter, half or three quarters of a turn from +z
        expected[f"longitude {deg}"] = (a @ _c2w(deg, [0, 0, 0]), b @ _c2w(deg, [0, 0, 0]))
    mirror = np.diag([-1.0, 1.0, 1.0, 1.0])  # mirrored panoramas: each camera's x axis reversed
    expected["mirrored"] = (a @ mirror, b @ mirror)
    turned_over = np.diag([-1.0, -1.0, 1.0, 1.0])  # one panorama upside down: that camera turned about its z axis
    expected["image_a upside down"] = (a @ turned_over, b)
    expected["image_b upside down"] = (a, b @ turned_over)
    assert set(got) == set(expected)
    for name, (pa, pb) in expected.items():
        R, t = _relative(pa, pb)
        assert np.allclose(got[name][0], R) and np.allclose(got[name][1], t), name


def test_the_world_to_camera_reading_inverts_the_matrices_as_they_were_sent():
    """OpenGL world-to-camera matrices W sent as c2w arrive as W @ flip (the OpenGL -> OpenCV turn); the reading
    recovers the cameras those W describe: inv(W) in OpenGL axes, inv(W) @ flip in OpenCV's."""
    true_a, true_b = _c2w(20.0, [0.3, -0.1, 0.2]), _c2w(-65.0, [1.4, 0.05, -0.8])  # OpenCV c2w
    w_a, w_b = np.linalg.inv(true_a @ _FLIP), np.linalg.inv(true_b @ _FLIP)  # OpenGL world-to-camera
    R, t = readings(w_a @ _FLIP, w_b @ _FLIP, "opengl")["world-to-camera"]
    R_true, t_true = _relative(true_a, true_b)
    assert np.allclose(R, R_true) and np.allclose(t, t_true)


def test_confident_reconstructions_and_flat_images_are_not_refused():
    flat = np.full((64, 128, 3), 0.5, np.float32)
    a, b = np.eye(4), _c2w(30.0, [1.0, 0.2, 0.5])  # no two readings are one relative pose
    assert check_given_poses(flat, flat, a, b, CHECK_BELOW_CONFIDENCE) is None  # not checked
    assert check_given_poses(flat, flat, a, b, None) is None
    scores = check_given_poses(flat, flat, a, b, 0.0)  # checked: nothing agrees with anything
    assert set(scores) == {"photometric"}  # no feature matches are sought where the photometric test decides
    assert set(scores["photometric"]) == {"given", "swapped", "other convention", "world-to-camera", "longitude 90",
                                          "longitude 180", "longitude 270", "mirrored", "image_a upside down",
                                          "image_b upside down"}
    assert max(scores["photometric"].values()) == 0.0


def _small(img):
    import cv2

    return cv2.resize(img, (1024, 512), interpolation=cv2.INTER_AREA)


def test_swapped_images_and_the_other_convention_are_refused_the_right_poses_pass(bedroom_theta_dir):
    """A hand-held pair 0.8 m apart: the poses as captured agree best; the two images swapped, or both
    cameras read in OpenGL's axes, are 422 poses_mismatch naming what to check (forced: confidence 0)."""
    scene = load_scene(bedroom_theta_dir)
    fa, fb = scene.frames["3"], scene.frames["5"]
    img_a, img_b = _small(fa.image()), _small(fb.image())
    scores = check_given_poses(img_a, img_b, fa.c2w, fb.c2w, 0.0)["photometric"]
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
    built, the swapped order is a 422 ``poses_mismatch`` and leaves no scene behind, and so are OpenGL
    world-to-camera matrices sent as c2w (read in the request's convention)."""
    import io
    import json

    from PIL import Image

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
        w2c_gl = [np.linalg.inv(f.c2w @ _FLIP).tolist() for f in (fa, fb)]  # OpenGL world-to-camera, sent as c2w
        inverted = post_scene(client, a, b, json.dumps({"convention": "opengl", "c2w": w2c_gl}))
        assert inverted.status_code == 422, inverted.text
        assert "poses inverted" in inverted.json()["error"]["message"]
        assert stored_scene_count(store) == 1


def test_cli_reconstruct_refuses_swapped_images_and_inverted_poses_as_the_api_does(bedroom_theta_dir, model_path,
                                                                                   tmp_path, monkeypatch, capsys):
    import json

    from PIL import Image

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
    for name, frame in (("a.png", fa), ("b.png", fb)):  # the right order, with OpenGL world-to-camera matrices
        Image.fromarray((np.clip(_small(frame.image()), 0, 1) * 255 + 0.5).astype(np.uint8)).save(tmp_path / name)
    w2c_gl = [np.linalg.inv(f.c2w @ _FLIP).tolist() for f in (fa, fb)]
    (tmp_path / "poses.json").write_text(json.dumps({"convention": "opengl", "c2w": w2c_gl}))
    assert cli.main(["reconstruct", str(tmp_path / "a.png"), str(tmp_path / "b.png"), "--poses",
                     str(tmp_path / "poses.json"), "--model", str(model_path), "--no-build", "-o", str(out)]) == 2
    assert "poses inverted" in capsys.readouterr().err and not out.exists()


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


def _pose(rotvec, t):
    from rasterizer.relative_pose import rotation_exp

    m = np.eye(4)
    m[:3, :3], m[:3, 3] = rotation_exp(np.asarray(rotvec, np.float64)), t
    return m


_vec = st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3)


@settings(max_examples=40, deadline=None)
@given(_vec, _vec, _vec, st.floats(0.05, 20.0), st.integers(0, 2**16))
def test_true_matches_support_the_true_reading_whatever_the_poses(rot_a, rot_b, direction, baseline, seed):
    """Bearings of random points seen from any two cameras (any turn, baselines 0.05-20 m, points 1-6 m from A with
    2 deg of parallax or more) all lie on their epipolar planes and meet in front of both cameras under the pose
    they were made with: the feature step never counts a true match against the given poses."""
    d = np.asarray(direction)
    if np.linalg.norm(d) < 1e-3:
        d = np.array([1.0, 0.0, 0.0])
    a, b = _pose(rot_a, [0.0, 0.0, 0.0]), _pose(rot_b, d / np.linalg.norm(d) * baseline)
    fa, fb = _matched_bearings(a, b, n=100, seed=seed)
    assume(len(fa) >= 10)
    R, t = readings(a, b)["given"]
    assert feature_support(fa, fb, {"given": (R, t)})["given"] == len(fa)


def _matched_bearings(c2w_a, c2w_b, n=300, seed=0):
    """Unit bearings (n, 3) of A and B in their camera frames of random points 1-6 m from A, all around it, with at
    least 2 deg of parallax between the two cameras."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(4 * n, 3))
    world = c2w_a[:3, 3] + d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(1.0, 6.0, (4 * n, 1))

    def bearings(c2w):
        v = (world - c2w[:3, 3]) @ c2w[:3, :3]
        return v / np.linalg.norm(v, axis=1, keepdims=True)

    fa, fb = bearings(c2w_a), bearings(c2w_b)
    ray_b_in_world = fb @ c2w_b[:3, :3].T
    parallax = np.degrees(np.arccos(np.clip(np.sum((fa @ c2w_a[:3, :3].T) * ray_b_in_world, 1), -1.0, 1.0)))
    keep = np.flatnonzero(parallax > 2.0)[:n]
    return fa[keep], fb[keep]


@pytest.mark.parametrize("yaw_b", [10.0, 35.0, -120.0])
def test_a_swap_loses_the_matches_that_meet_in_front_of_both_cameras(yaw_b):
    """Matches of a true pair (bearings of random points): every one supports the given reading, few the swapped
    or misread ones. Cameras turned alike (a pure translation): reversing the baseline keeps every epipolar plane,
    but no pair of rays meets in front of both cameras, so none supports the swap."""
    from rasterizer.relative_pose import INLIER_DEG, epipolar_error

    a, b = _c2w(10.0, [0.0, 0.0, 0.0]), _c2w(yaw_b, [1.2, 0.05, -0.7])
    fa, fb = _matched_bearings(a, b)
    support = feature_support(fa, fb, readings(a, b))
    assert support["given"] == len(fa) == 300
    assert max(support["swapped"], support["other convention"]) < len(fa) // 10
    swapped = feature_support(fb, fa, readings(a, b))  # the uploads in the wrong order
    assert swapped["swapped"] == len(fa) and swapped["given"] < len(fa) // 10
    if yaw_b == 10.0:
        R, t = readings(a, b)["swapped"]
        assert np.all(epipolar_error(fa, fb, R, t) < np.radians(INLIER_DEG))  # the planes alone cannot tell
        assert support["swapped"] == 0


def test_feature_matches_decide_what_the_photometric_margins_leave_open(zind_dir):
    """zind_room09 pano_2 + pano_5 (2.5 m apart): read in OpenGL's axes, the poses agree with the images within the
    photometric margins (0.316 against 0.34 for the true reading), so the feature matches decide: 21 meet in
    front of both cameras under the true reading, 4 under the misread one. The right upload passes."""
    scene = load_scene(zind_dir)
    fa, fb = scene.frames["pano_2"], scene.frames["pano_5"]
    img_a, img_b = fa.image(), fb.image()
    scores = check_given_poses(img_a, img_b, fa.c2w, fb.c2w, 0.0)
    photometric, support = scores["photometric"], scores["feature_support"]
    assert photometric["given"] < pose_check.MISMATCH_RATIO * photometric["other convention"]  # undecided there
    assert support["given"] >= pose_check.FEATURE_MARGIN * max(support["swapped"], support["other convention"])
    with pytest.raises(BadInput, match="other axis convention .*feature matches meet in front") as exc:
        check_given_poses(img_a, img_b, fa.c2w @ _FLIP, fb.c2w @ _FLIP, 0.0)
    assert exc.value.code == "poses_mismatch" and "swapped" not in exc.value.message


def test_world_to_camera_matrices_sent_as_c2w_are_refused(zind_dir):
    """zind_room09 pano_4 + pano_5: their world-to-camera matrices sent as c2w (as COLMAP writes poses) give a
    relative pose 48 deg off in rotation, refused as such in either convention; the right matrices sent in
    OpenGL's axes pass."""
    scene = load_scene(zind_dir)
    fa, fb = scene.frames["pano_4"], scene.frames["pano_5"]
    img_a, img_b = fa.image(), fb.image()
    with pytest.raises(BadInput, match="poses inverted .*takes camera-to-world matrices.*invert world-to-camera") as exc:
        check_given_poses(img_a, img_b, np.linalg.inv(fa.c2w), np.linalg.inv(fb.c2w), 0.0)
    assert exc.value.code == "poses_mismatch"
    gl_a, gl_b = fa.c2w @ _FLIP, fb.c2w @ _FLIP  # OpenGL c2w; the server turns what it is sent by _FLIP
    with pytest.raises(BadInput, match="world-to-camera"):
        check_given_poses(img_a, img_b, np.linalg.inv(gl_a) @ _FLIP, np.linalg.inv(gl_b) @ _FLIP, 0.0, "opengl")
    assert check_given_poses(img_a, img_b, gl_a @ _FLIP, gl_b @ _FLIP, 0.0, "opengl") is not None  # checked, passed


def test_poses_of_panoramas_whose_forward_axis_is_not_at_the_image_centre_are_refused(zind_dir):
    """zind_room09 pano_4 + pano_5 with both cameras turned about their vertical axis, as poses from a tool whose
    panoramas start their longitude elsewhere: refused as a turn (a quarter or a half), with the fix."""
    scene = load_scene(zind_dir)
    fa, fb = scene.frames["pano_4"], scene.frames["pano_5"]
    img_a, img_b = fa.image(), fb.image()
    for deg, turn in ((90, "a quarter"), (180, "a half"), (270, "a quarter")):
        with pytest.raises(BadInput, match=r"poses turned .*turn about the cameras' vertical axis .*longitude origin") as exc:
            check_given_poses(img_a, img_b, fa.c2w @ _c2w(deg, [0, 0, 0]), fb.c2w @ _c2w(deg, [0, 0, 0]), 0.0)
        assert exc.value.code == "poses_mismatch" and turn in exc.value.message.split(" turn about")[0], deg


def test_mirrored_panoramas_with_their_poses_are_refused(bedroom_theta_dir):
    """bedroom_theta 3 + 7, both images mirrored left to right (as from a tool whose longitude grows to the left)
    with the poses they were captured at: refused as mirrored, with the fix; the same images unmirrored pass."""
    scene = load_scene(bedroom_theta_dir)
    fa, fb = scene.frames["3"], scene.frames["7"]
    img_a, img_b = _small(fa.image()), _small(fb.image())
    with pytest.raises(BadInput, match="read for panoramas mirrored left to right .*flip both images") as exc:
        check_given_poses(img_a[:, ::-1], img_b[:, ::-1], fa.c2w, fb.c2w, 0.0)
    assert exc.value.code == "poses_mismatch"
    assert check_given_poses(img_a, img_b, fa.c2w, fb.c2w, 0.0) is not None  # checked, passed


def test_one_panorama_upside_down_with_its_poses_is_refused(bedroom_theta_dir):
    """bedroom_theta 3 + 7 with the poses they were captured at, one image turned 180 deg in its plane (a camera
    mounted upside down, or an orientation tag that does not fit the pixels): refused naming that image, with the
    fix; the same images the right way up pass."""
    scene = load_scene(bedroom_theta_dir)
    fa, fb = scene.frames["3"], scene.frames["7"]
    img_a, img_b = _small(fa.image()), _small(fb.image())
    for which, (a, b) in (("image_b", (img_a, img_b[::-1, ::-1])), ("image_a", (img_a[::-1, ::-1], img_b))):
        with pytest.raises(BadInput, match=f"read for {which} upside down .*turn {which} the right way up") as exc:
            check_given_poses(a, b, fa.c2w, fb.c2w, 0.0)
        assert exc.value.code == "poses_mismatch" and exc.value.status == 422
    scores = check_given_poses(img_a, img_b, fa.c2w, fb.c2w, 0.0)["photometric"]
    assert scores["given"] > max(scores["image_a upside down"], scores["image_b upside down"])


def test_a_reading_that_is_the_given_relative_pose_is_no_alternative(m3d_dir):
    """m3d's cameras are turned alike, by 180 deg about their x axis: inverting both matrices gives the same relative
    pose, so the world-to-camera reading is not scored (it would tie with the given one and call in the feature
    matches for nothing), and the pair's world-to-camera matrices sent as c2w, which describe it as well, pass."""
    scene = load_scene(m3d_dir)
    fa, fb = scene.frames["00"], scene.frames["02"]
    img_a, img_b = _small(fa.image()), _small(fb.image())
    for c2w_a, c2w_b in ((fa.c2w, fb.c2w), (np.linalg.inv(fa.c2w), np.linalg.inv(fb.c2w))):
        scores = check_given_poses(img_a, img_b, c2w_a, c2w_b, 0.0)
        assert set(scores) == {"photometric"} and "world-to-camera" not in scores["photometric"]
        assert {"given", "swapped", "other convention", "longitude 90"} <= set(scores["photometric"])


def test_matches_without_parallax_support_no_reading():
    """Identical bearings (one picture twice, or one place) meet nowhere: their ranges' sign is rounding, so they
    support none of the readings that keep the cameras' relative turn (the upside-down ones turn one camera over, and
    the same bearings are then other rays, of which a few may meet)."""
    rng = np.random.default_rng(1)
    f = rng.normal(size=(200, 3))
    f /= np.linalg.norm(f, axis=1, keepdims=True)
    poses = readings(np.eye(4), _c2w(0.0, [1.0, 0.0, 0.2]))
    assert len(poses) == 10
    same_turn = {name: p for name, p in poses.items() if "upside down" not in name}
    assert all(np.allclose(R, np.eye(3)) for R, _ in same_turn.values())
    assert feature_support(f, f.copy(), same_turn) == dict.fromkeys(same_turn, 0)


def test_one_place_twice_with_poses_is_refused_as_no_parallax(bedroom_theta_dir):
    """bedroom_theta 3 sent as both images, the second turned by 45 deg (a camera turned on an unmoved tripod) with a
    little noise, with the poses of 3 and 5: its matches move by a turn alone, which no baseline explains: 422
    no_parallax, not a verdict on the poses' reading."""
    from service.images import same_picture

    scene = load_scene(bedroom_theta_dir)
    fa, fb = scene.frames["3"], scene.frames["5"]
    img = _small(fa.image())
    turned = np.roll(img, img.shape[1] // 8, axis=1)
    turned = np.clip(turned + np.random.default_rng(0).normal(0.0, 0.02, img.shape), 0.0, 1.0).astype(np.float32)
    assert not same_picture(img, turned)  # not one picture pixel for pixel: it reaches the check
    with pytest.raises(BadInput, match="move by a turn of the camera alone") as exc:
        check_given_poses(img, turned, fa.c2w, fb.c2w, 0.0)
    assert exc.value.code == "no_parallax" and exc.value.status == 422
