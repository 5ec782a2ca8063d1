"""Poses from the images: a textured synthetic box room rendered to ERPs with known poses, and m3d without poses; a
panorama flipped as a whole against the other is refused as such."""

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rasterizer.geometry import lat_lon_from_direction
from rasterizer.relative_pose import yaw_rotation
from rasterizer.scene_folder import load_scene
from service.matching import Distances, putative_matches
from service.pose_flips import FLIPS, MIRROR_BINS
from service.poses import PoseEstimationFailed, PoseOptions, estimate_poses, poses_for_scene
from tests.service._support import LiveServer, make_settings, room_erp


def _pose(yaw_deg: float, t) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = yaw_rotation(np.radians(yaw_deg)), t
    return m


def _angle(u, v):
    u, v = np.asarray(u) / np.linalg.norm(u), np.asarray(v) / np.linalg.norm(v)
    return np.degrees(np.arccos(np.clip(u @ v, -1, 1)))


def _rot_err(R1, R2):
    return np.degrees(np.arccos(np.clip((np.trace(R1.T @ R2) - 1) / 2, -1, 1)))


@pytest.fixture(scope="module")
def room_a():
    return room_erp(np.eye(4))


@pytest.mark.parametrize("yaw_deg, t, opts, scale_tol", [
    (35.0, [1.2, 0.0, 0.6], PoseOptions(baseline=2.0), 1e-9),
    (178.0, [0.0, 0.0, -1.5], PoseOptions(camera_height=1.5), 0.05),  # B faces A's seam, moving along it
])
def test_estimate_recovers_the_synthetic_pose(room_a, yaw_deg, t, opts, scale_tol):
    true = _pose(yaw_deg, t)
    c2w_a, c2w_b, info = estimate_poses(room_a, room_erp(true), opts)
    assert np.array_equal(c2w_a[:3, 3], np.zeros(3)) and _rot_err(c2w_a[:3, :3], np.eye(3)) < 0.3  # a level room
    c2w_b = np.linalg.inv(c2w_a) @ c2w_b
    assert _rot_err(c2w_b[:3, :3], true[:3, :3]) < 0.5
    assert _angle(c2w_b[:3, 3], true[:3, 3]) < 2.0
    expected = opts.baseline if opts.baseline is not None else np.linalg.norm(t)
    assert abs(np.linalg.norm(c2w_b[:3, 3]) / expected - 1) < max(scale_tol, 1e-9) + 1e-9
    assert info["inliers"] >= 50 and info["residual_deg"]["median"] < 0.5 and info["scale"]["source"] in (
        "baseline", "camera_height")


def test_tilted_panoramas_are_levelled_and_the_pose_recovered():
    """Both cameras tilted (A 3 deg, B 5 deg): the world comes out level (gravity along +y) and B's pose
    relative to A matches within the upright figures."""
    from rasterizer.relative_pose import rotation_exp

    tilt_a, tilt_b = rotation_exp(np.radians([2.0, 0, -2.2])), rotation_exp(np.radians([-3.0, 0, 4.0]))
    pose_a = np.eye(4)
    pose_a[:3, :3] = tilt_a
    pose_b = _pose(50.0, [1.1, 0.05, 0.7])
    pose_b[:3, :3] = pose_b[:3, :3] @ tilt_b
    c2w_a, c2w_b, info = estimate_poses(room_erp(pose_a, 512, 2), room_erp(pose_b, 512, 2), PoseOptions(camera_height=1.5))
    for c2w, true in ((c2w_a, pose_a), (c2w_b, pose_b)):  # each camera's tilt: its down axis in the world
        assert _angle(c2w[:3, :3].T @ [0, 1, 0], true[:3, :3].T @ [0, 1, 0]) < 0.5
    rel, rel_true = np.linalg.inv(c2w_a) @ c2w_b, np.linalg.inv(pose_a) @ pose_b
    assert _rot_err(rel[:3, :3], rel_true[:3, :3]) < 0.5 and _angle(rel[:3, 3], rel_true[:3, 3]) < 2.0
    assert abs(np.linalg.norm(rel[:3, 3]) / np.linalg.norm(rel_true[:3, 3]) - 1) < 0.05
    assert [g["source"] for g in info["gravity"]] == ["lines", "lines"] and info["gravity"][1]["tilt_deg"] > 4


def test_identical_images_and_zero_baseline_are_refused(room_a):
    with pytest.raises(PoseEstimationFailed) as exc:
        estimate_poses(room_a, room_a.copy(), PoseOptions())
    assert exc.value.status == 422 and exc.value.code == "no_parallax"
    turned = room_erp(_pose(60.0, [0.0, 0.0, 0.0]))  # same centre, turned: still no depth
    with pytest.raises(PoseEstimationFailed, match="same point"):
        estimate_poses(room_a, turned, PoseOptions())


def test_one_picture_twice_is_refused_whatever_the_given_poses_say(room_a):
    from service.inputs import Poses
    from service.poses import poses_for_scene

    given = Poses("opencv", np.eye(4), _pose(0.0, [1.0, 0.0, 0.0]))
    with pytest.raises(PoseEstimationFailed, match="same picture") as exc:
        poses_for_scene(room_a, room_a.copy(), given, PoseOptions())
    assert exc.value.status == 422 and exc.value.code == "no_parallax"
    noisy = np.clip(room_a + np.random.default_rng(0).normal(0.0, 8.0, room_a.shape), 0, 255).astype(room_a.dtype)
    with pytest.raises(PoseEstimationFailed, match="same picture"):  # not the same bytes: the same picture
        poses_for_scene(room_a, noisy, given, PoseOptions())
    other = room_erp(_pose(0.0, [0.3, 0.0, 0.0]))  # the room 0.3 m away: another picture
    c2w_a, c2w_b, _ = poses_for_scene(room_a, other, given, PoseOptions())
    assert np.array_equal(c2w_b, given.c2w_b)


def test_unrelated_and_flat_images_are_refused():
    from service.photometric import photometric_scores

    noise = np.random.default_rng(0).integers(0, 255, (256, 512, 3), dtype=np.uint8)
    with pytest.raises(PoseEstimationFailed):
        estimate_poses(noise, np.roll(noise[::-1], 77, axis=1), PoseOptions())
    flat = np.full((64, 128, 3), 128, np.uint8)
    with pytest.raises(PoseEstimationFailed, match="feature matches"):
        estimate_poses(flat, flat, PoseOptions())
    assert photometric_scores(flat, flat, [(np.eye(3), np.array([1.0, 0, 0]))]) == [0.0]


def test_a_mirror_flipped_panorama_is_refused_not_given_a_vertical_baseline(monkeypatch):
    """An ERP flipped upside down and turned: every feature moves along its meridian, which a baseline
    along gravity explains exactly (its epipolar planes are the meridians); no two captures of a room do.
    The flip check names the flip; without it, the travel's elevation still refuses the pose."""
    import service.poses as poses

    noise = np.random.default_rng(0).integers(0, 255, (256, 512, 3), dtype=np.uint8)
    with pytest.raises(PoseEstimationFailed, match="flipped top-bottom"):
        estimate_poses(noise, np.roll(noise[::-1], 77, axis=1), PoseOptions())
    monkeypatch.setattr(poses, "flipped", lambda *args, **kwargs: None)
    with pytest.raises(PoseEstimationFailed, match="deg from horizontal"):
        estimate_poses(noise, np.roll(noise[::-1], 77, axis=1), PoseOptions())


def test_the_flip_check_runs_once_per_estimate_on_the_seed_matches(room_a, monkeypatch):
    """A weak seed asks whether B is flipped, and so does a refusal after it: the verdict is found once, and B's
    descriptors as sent are matched once (the seed's matches), only the mirrored ones for the check."""
    import service.pose_flips as pose_flips
    import service.poses as poses
    from service import matching

    checks, matched = [], []

    def counted(fn, log, skip):
        def wrapper(*args, **kwargs):
            log.append(args[skip:])
            return fn(*args, **kwargs)
        return wrapper

    mutual = matching.mutual_matches
    monkeypatch.setattr(pose_flips, "flip_supports", counted(pose_flips.flip_supports, checks, 2))
    monkeypatch.setattr(matching, "mutual_matches", counted(mutual, matched, 1))
    monkeypatch.setattr(poses, "mutual_matches", counted(mutual, matched, 1))
    monkeypatch.setattr(poses, "FLIP_CHECK_SHARE", 1.01)  # every seed is weak: the check runs before guiding
    monkeypatch.setattr(poses, "RESIDUAL_TILT_DEG", 90.0)
    guided = poses._guided_refine

    def few(*args, **kwargs):  # too few guided inliers: the estimate refuses after the check
        yaw, t, inl, err = guided(*args, **kwargs)
        return yaw, t, inl[:5], err[:5]

    monkeypatch.setattr(poses, "_guided_refine", few)
    room_b = room_erp(_pose(-40.0, [0.9, 0.0, -0.8]))
    with pytest.raises(PoseEstimationFailed, match="only 5 matches agree") as exc:
        estimate_poses(room_a, room_b, PoseOptions())
    assert exc.value.code == "pose_estimation_failed"
    assert len(checks) == 1
    assert matched == [(poses.SEED_RATIOS[0],)] * 2, matched  # B as sent (the seed's), B mirrored (the check's)


def test_a_tilt_beyond_the_search_is_refused_as_such():
    """A panorama tilted beyond the gravity search is levelled wrong or not at all, and its pose fails in any way
    (m3d 00+02 with B pitched 25 deg was refused as "ambiguous ... as in a symmetric room", pitched 30 deg posed
    29 deg off): it is refused before matching, naming the tilt and the way out."""
    from service.poses import Panorama

    def pano(gravity):
        return Panorama(np.zeros((4, 8), np.uint8), np.zeros((0, 3)), np.zeros((0, 128), np.float32), np.eye(3), gravity)

    level = {"source": "lines", "tilt_deg": 0.5, "lines": {"inliers": 30}}
    wrong = {"source": "lines", "tilt_deg": 12.8, "lines": {"inliers": 11, "beyond_search_deg": 25.2}}
    unlevelled = {"source": "none", "tilt_deg": 0.0, "lines": {"error": "only 5 line segments meet", "beyond_search_deg": 29.9}}
    with pytest.raises(PoseEstimationFailed) as exc:
        estimate_poses(None, None, PoseOptions(), prepared=(pano(level), pano(wrong)))
    assert exc.value.code == "pose_estimation_failed"
    assert exc.value.message.startswith("poses: image_b seems tilted by 25 deg, beyond the 20 deg searched")
    assert "level it" in exc.value.message and "give poses" in exc.value.message
    with pytest.raises(PoseEstimationFailed, match="image_a and image_b seem tilted by 30 and 25 deg"):
        estimate_poses(None, None, PoseOptions(), prepared=(pano(unlevelled), pano(wrong)))


def test_too_few_seed_matches_at_the_first_ratio_retry_at_the_second(room_a, monkeypatch):
    """A wide baseline leaves too few ratio-0.8 matches to seed RANSAC: the guided matching's 0.9 seeds it."""
    import service.poses as poses
    from service import matching

    tried = []

    def putative(dist, ratio=0.8):
        tried.append(ratio)
        pairs = matching.mutual_matches(dist, ratio)
        return pairs[:poses.MIN_INLIERS - 1] if ratio == poses.SEED_RATIOS[0] else pairs

    monkeypatch.setattr(poses, "putative_matches", putative)
    true = _pose(35.0, [1.2, 0.0, 0.6])
    c2w_a, c2w_b, info = estimate_poses(room_a, room_erp(true), PoseOptions(baseline=2.0))
    assert tried == list(poses.SEED_RATIOS) and info["seed_ratio"] == poses.SEED_RATIOS[1]
    rel = np.linalg.inv(c2w_a) @ c2w_b
    assert _rot_err(rel[:3, :3], true[:3, :3]) < 0.5 and _angle(rel[:3, 3], true[:3, 3]) < 2.0


def test_pose_modes_photometry_decides_then_the_floor_then_no_one():
    """Two pose modes (a best and a rival): photometric scores 1.15x apart decide; else floor shares 1.5x
    apart (bedroom_theta 2+8: the true pose lines up 7.0% of the band through the floor, the rival 2.6%,
    at photometric 0.30 vs 0.29); else the inlier counts pick without deciding."""
    from service.poses import _mode_choice

    def never():
        raise AssertionError("the floor sweep runs only when the photometric scores are close")

    assert _mode_choice((0.40, 0.30), (200, 150), never) == (False, True)
    assert _mode_choice((0.30, 0.40), (200, 150), never) == (True, True)
    assert _mode_choice((0.30, 0.297), (261, 225), lambda: (0.070, 0.026)) == (False, True)
    assert _mode_choice((0.30, 0.297), (261, 225), lambda: (0.026, 0.070)) == (True, True)
    assert _mode_choice((0.30, 0.297), (261, 225), lambda: (0.0, 0.03)) == (True, True)  # no floor under the best
    assert _mode_choice((0.30, 0.297), (261, 225), lambda: (0.05, 0.041)) == (False, False)
    assert _mode_choice((0.30, 0.297), (225, 261), lambda: (0.0, 0.0)) == (True, False)


def test_default_scale_is_one_and_says_so(room_a):
    _, c2w_b, info = estimate_poses(room_a, room_erp(_pose(-20.0, [0.8, 0.0, -0.9])), PoseOptions())
    assert abs(np.linalg.norm(c2w_b[:3, 3]) - 1.0) < 1e-9
    assert info["scale"]["source"] == "default" and "arbitrary" in info["scale"]["note"]


def test_camera_height_floor_dense_then_points_then_refused(room_a, monkeypatch):
    """The dense sweep's floor first; when it finds none, the triangulated points' floor; when neither, 422."""
    import service.poses as poses

    true = _pose(-40.0, [0.9, 0.0, -0.8])
    room_b = room_erp(true)

    def baseline_and_floor():
        _, c2w_b, info = estimate_poses(room_a, room_b, PoseOptions(camera_height=1.5))  # floor 1.5 m below A
        return np.linalg.norm(c2w_b[:3, 3]) / np.linalg.norm(true[:3, 3]), info["scale"]["floor"]

    ratio, floor = baseline_and_floor()
    assert floor == "dense" and abs(ratio - 1) < 0.03

    def no_floor(*args, **kwargs):
        raise ValueError("the floor is not seen in both views")

    monkeypatch.setattr(poses, "floor_ratio", no_floor)
    ratio, floor = baseline_and_floor()
    assert floor == "points" and abs(ratio - 1) < 0.05
    monkeypatch.setattr(poses, "floor_scale", no_floor)
    with pytest.raises(PoseEstimationFailed) as exc:
        baseline_and_floor()
    assert exc.value.status == 422 and exc.value.code == "scale_failed"


def test_camera_height_with_the_floor_hidden_near_the_cameras_is_refused_with_a_way_out(room_a, monkeypatch):
    """A black 60-deg nadir cap on both panoramas hides the floor near the cameras: the scale is refused (the sweep's
    deepest plane left was a bed top on bedroom_theta 2+5, a baseline 1.7x) and the message names the way out; the
    points' floor, hidden the same way, is not asked."""
    import service.poses as poses

    def capped(img):
        out = img.copy()
        out[int(img.shape[0] * (1 - 60 / 180)):] = 0
        return out

    def points_floor(*args, **kwargs):
        raise AssertionError("the points' floor was asked")

    monkeypatch.setattr(poses, "floor_scale", points_floor)
    room_b = room_erp(_pose(-40.0, [0.9, 0.0, -0.8]))
    with pytest.raises(PoseEstimationFailed) as exc:
        estimate_poses(capped(room_a), capped(room_b), PoseOptions(camera_height=1.5))
    assert exc.value.code == "scale_failed", exc.value.message
    assert "not seen well enough" in exc.value.message and "give baseline" in exc.value.message
    assert "or poses" in exc.value.message
    _, c2w_b, info = estimate_poses(capped(room_a), capped(room_b), PoseOptions(baseline=1.2))  # the way out
    assert abs(np.linalg.norm(c2w_b[:3, 3]) - 1.2) < 1e-9 and info["scale"]["source"] == "baseline"


def test_a_logo_stamped_on_both_nadirs_is_not_taken_for_a_deep_floor(zind_dir):
    """zind_room09 pano_4+5 (2.12 m apart) with the same patterned 35-deg logo on both nadirs: the logo's windows
    matched under every deep plane and made a floor 22 times too deep, a baseline of 0.095 m. They match without
    parallax, so they do not vote: what floor is left near the cameras is too little, and the scale is refused with
    a message that names them."""
    scene = load_scene(zind_dir)
    a, b = scene.frames["pano_4"], scene.frames["pano_5"]

    def logo(img):
        out = img.copy()
        h, w = img.shape[:2]
        r0 = int(h * (1 - 35 / 180))
        out[r0:] = 0.15
        out[r0:, ::w // 64] = 1.0
        out[r0::8] = 1.0
        return out

    with pytest.raises(PoseEstimationFailed) as exc:
        estimate_poses(logo(a.image()), logo(b.image()), PoseOptions(camera_height=1.435))
    assert exc.value.code == "scale_failed" and "give baseline" in exc.value.message, exc.value.message
    assert "line up with no parallax" in exc.value.message and "logo" in exc.value.message, exc.value.message


def test_vignetted_alike_m3d_is_refused_as_ambiguous_not_given_the_wrong_mode(m3d_dir):
    """m3d 00+02 with both images darkened alike towards the poles and two opposite sides: RANSAC's two pose modes
    (13 deg apart in yaw) score close photometrically, and the floor shares decide only beyond their margin. With
    the windows that match with no parallax left out of those shares the wrong mode's share was 1.9 times the
    right one's and the estimate came out 11 deg off with a 1.8x baseline; they vote there, and it is refused."""
    scene = load_scene(m3d_dir)
    h, w = 512, 1024
    lat = (np.arange(h) + 0.5) / h * np.pi - np.pi / 2
    lon = (np.arange(w) + 0.5) / w * 2 * np.pi
    gain = ((np.cos(lat)[:, None] * (0.6 + 0.4 * np.cos(2 * lon)[None])) ** 2)[..., None].astype(np.float32)
    a, b = (scene.frames[name].image() for name in ("00", "02"))
    assert a.shape[:2] == (h, w)
    with pytest.raises(PoseEstimationFailed) as exc:
        estimate_poses(a * gain, b * gain, PoseOptions(camera_height=1.5))
    assert exc.value.code == "ambiguous_pose", exc.value.message


def test_refine_given_poses_moves_a_wrong_yaw_back(room_a):
    from service.inputs import Poses

    true = _pose(25.0, [1.0, 0.0, 0.8])
    wrong = true @ _pose(2.0, [0, 0, 0])
    _, c2w_b, meta = poses_for_scene(room_a, room_erp(true), Poses("opencv", np.eye(4), wrong),
                                     PoseOptions(refine_poses=True))
    assert meta["source"] == "refined" and json.dumps(meta)
    assert _rot_err(c2w_b[:3, :3], true[:3, :3]) < 0.3 < _rot_err(wrong[:3, :3], true[:3, :3])
    assert abs(np.linalg.norm(c2w_b[:3, 3]) - np.linalg.norm(true[:3, 3])) < 1e-9  # baseline kept


def test_m3d_without_poses(m3d_dir):
    scene = load_scene(m3d_dir)
    a, b = scene.frames["00"], scene.frames["02"]
    rel = np.linalg.inv(a.c2w) @ b.c2w
    c2w_a, c2w_b, info = estimate_poses(a.image(), b.image(), PoseOptions(baseline=1.0))
    assert _rot_err(c2w_a[:3, :3], np.eye(3)) < 0.5  # a level capture stays (nearly) as it is
    c2w_b = np.linalg.inv(c2w_a) @ c2w_b
    assert _rot_err(c2w_b[:3, :3], rel[:3, :3]) < 0.5
    assert _angle(c2w_b[:3, 3], rel[:3, 3]) < 1.0
    assert info["inliers"] > 200


# -- through the API ---------------------------------------------------------------------------------

def _png(img: np.ndarray) -> bytes:
    import io

    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    return buf.getvalue()


@pytest.fixture(scope="module")
def api(model_path, tmp_path_factory):
    with LiveServer(make_settings(model_path, tmp_path_factory.mktemp("store"))) as server, server.client() as c:
        yield c


def _post(client, a: bytes, b: bytes, data: dict):
    return client.post("/v1/scenes", files={"image_a": ("a.png", a), "image_b": ("b.png", b)}, data=data)


def test_post_without_poses_returns_the_estimate(api, room_a):
    true = _pose(30.0, [1.0, 0.0, 0.7])
    a, b = _png(room_a), _png(room_erp(true))
    for data in ({"options": json.dumps({"baseline": 1.2207})}, {"poses": json.dumps({"c2w": None}),
                                                                 "options": json.dumps({"baseline": 1.2207})}):
        r = _post(api, a, b, data)
        assert r.status_code == 201, r.text
        meta = api.get(f"/v1/scenes/{r.json()['id']}").json()
        poses = meta["poses"]
        assert poses["source"] == "estimated" and poses["convention"] == "opencv"
        c2w_a, c2w_b = np.array(poses["c2w"][0]), np.array(poses["c2w"][1])
        assert _rot_err(c2w_a[:3, :3], np.eye(3)) < 0.3 and _rot_err(c2w_b[:3, :3], true[:3, :3]) < 0.5
        assert [g["source"] for g in poses["support"]["gravity"]] == ["lines", "lines"]
        assert abs(np.linalg.norm(c2w_b[:3, 3]) - 1.2207) < 1e-6
        assert poses["support"]["inliers"] >= 50 and poses["support"]["method"]
        assert "poses" in r.json()["timings"]


@pytest.mark.parametrize("options, code", [
    ({}, "no_parallax"),                                   # identical images
    ({"baseline": -1}, "invalid_options"),
    ({"camera_height": 1.5, "baseline": 2}, "invalid_options"),
    ({"refine_poses": 1}, "invalid_options"),
])
def test_post_without_poses_bad_cases_are_422(api, room_a, options, code):
    a = _png(room_a)
    r = _post(api, a, a, {"options": json.dumps(options)})
    assert r.status_code == 422, r.text
    assert r.json()["error"]["code"] == code and r.json()["error"]["message"]


def test_a_panorama_of_one_flat_colour_is_refused_whatever_the_given_poses_say(room_a):
    """One flat colour (a capped lens, a blank export) shows no scene: 422 blank_image naming the upload, before the
    poses are used or estimated; detail the coarse look skips is still seen."""
    from service.errors import BadInput
    from service.inputs import Poses
    from service.poses import poses_for_scene

    given = Poses("opencv", np.eye(4), _pose(0.0, [1.0, 0.0, 0.0]))
    flat = np.full_like(room_a, 40)
    flat[::7, ::5] = 42  # within two levels: still one colour
    with pytest.raises(BadInput, match="^image_a: every pixel shows the same colour") as exc:
        poses_for_scene(flat, room_a, given, PoseOptions())
    assert exc.value.status == 422 and exc.value.code == "blank_image"
    with pytest.raises(BadInput, match="^image_b: every pixel"):  # float [0, 1] images, as the CLI reads them
        poses_for_scene(room_a / 255.0, np.full(room_a.shape, 0.3), None, PoseOptions())
    dotted = np.full_like(room_a, 90)
    dotted[3::8, 5::8] = 200  # only between the coarse look's samples
    assert np.array_equal(poses_for_scene(room_a, dotted, given, PoseOptions())[1], given.c2w_b)


def test_a_16bit_png_of_8bit_values_is_a_422_not_a_black_scene(api, room_a):
    """8-bit values stored in a 16-bit greyscale PNG read as black (at most 255 of 65535) in every viewer: the POST
    says so instead of building a black scene."""
    import io

    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(room_a[..., 1].astype(np.uint16)).save(buf, format="PNG")
    poses = json.dumps({"c2w": [np.eye(4).tolist(), _pose(0.0, [1.0, 0.0, 0.0]).tolist()]})
    r = _post(api, buf.getvalue(), _png(room_erp(_pose(0.0, [1.0, 0.0, 0.0]))), {"poses": poses})
    assert r.status_code == 422, r.text
    assert r.json()["error"]["code"] == "blank_image" and r.json()["error"]["message"].startswith("image_a: ")


def test_photometric_score_prefers_the_true_pose_over_a_flip_and_a_turn(room_a):
    from service.photometric import photometric_scores
    from service.poses import PHOTOMETRIC_MARGIN

    true = _pose(40.0, [1.0, 0.0, -0.6])
    img_b = room_erp(true)
    R, t = true[:3, :3], true[:3, 3]
    poses = [(R, t), (R @ yaw_rotation(np.pi), -t), (R @ yaw_rotation(0.35), yaw_rotation(0.35) @ t)]
    right, flipped, turned = photometric_scores(room_a, img_b, poses)
    assert right > PHOTOMETRIC_MARGIN * max(flipped, turned)
    # the poses share the images' preparation, and each scores as it does alone
    assert [right, flipped, turned] == [photometric_scores(room_a, img_b, [pose])[0] for pose in poses]


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([64, 256, 1000]))
def test_erp_pixels_place_directions_as_the_geometry_does(seed, height):
    """The OpenCV angles of ``_erp_pixels`` place a direction within 2e-4 rad of lat_lon_from_direction's pixel, at
    the poles and across the seam too (columns compared around the panorama), at any length of the direction."""
    from service.photometric import _erp_pixels

    rng = np.random.default_rng(seed)
    d = rng.normal(size=(50, 3, 3))
    d[0, 0] = [0.0, 1.0, 0.0]  # the nadir and the zenith
    d[0, 1] = [0.0, -2.0, 0.0]
    d[1, :, 0] = -rng.uniform(0, 1e-6, 3)  # just either side of the seam (lon = +-pi)
    d[1, :, 2] = -1.0
    d[2] *= 1e4
    lat, lon = lat_lon_from_direction(d)
    col, row = _erp_pixels(*(d[..., i].astype(np.float32) for i in range(3)), height)
    assert col.dtype == row.dtype == np.float32 and col.shape == row.shape == d.shape[:-1]
    ref_col = (lon + np.pi) / (2 * np.pi) * 2 * height - 0.5
    ref_row = (np.pi / 2 - lat) / np.pi * height - 0.5
    d_col = np.abs((col - ref_col + height) % (2 * height) - height)
    polar = np.abs(lat) > np.radians(89.9)  # longitude is arbitrary there
    tol = 2e-4 * height / np.pi + 1e-3  # pixels per radian: height / pi in both directions
    assert np.abs(row - ref_row).max() < tol and d_col[~polar].max() < tol


def _masked_dense_matches(desc_a, desc_b, ratio, mask):
    """Reference for ``_mutual_among``: every distance (the same chunks of rows: a GEMM's rounding depends on its
    shape), inf outside ``mask``, nearest both ways by argmin."""
    from service.matching import Distances

    dense = np.concatenate([d2 for _, d2 in Distances(desc_a, desc_b).chunks()])
    d2 = np.where(mask, dense, np.inf).astype(np.float64)
    srt = np.sort(d2, axis=1)
    best_d, second = srt[:, 0], srt[:, 1] if d2.shape[1] > 1 else np.full(len(d2), np.inf)
    best_j, col_arg = np.argmin(d2, axis=1), np.argmin(d2, axis=0)
    keep = np.isfinite(best_d) & (best_d < ratio * ratio * second) & (col_arg[best_j] == np.arange(len(d2)))
    return np.stack([np.nonzero(keep)[0], best_j[keep]], 1)


@settings(max_examples=60, deadline=None)
@given(na=st.integers(1, 40), nb=st.integers(1, 40), density=st.floats(0.0, 1.0), levels=st.sampled_from([2, 3, 256]),
       rows=st.sampled_from([1024, 3, 7]), seed=st.integers(0, 2**31 - 1))
def test_sparse_mutual_matches_equal_the_masked_dense_ones(na, nb, density, levels, rows, seed):
    """Guided matching sorts its candidate pairs instead of scanning masked dense rows: the same pairs, ties
    (coarsely quantised descriptors give many) included, whether A's rows are one chunk or several (``rows``),
    which run on two threads."""
    from unittest import mock

    from service import matching

    rng = np.random.default_rng(seed)
    desc_a = np.round(rng.random((na, 8)) * (levels - 1)).astype(np.float32) / levels
    desc_b = np.round(rng.random((nb, 8)) * (levels - 1)).astype(np.float32) / levels
    mask = rng.random((na, nb)) < density
    with mock.patch.object(matching, "_DIST_ROWS", rows):
        got = matching._mutual_among(matching.Distances(desc_a, desc_b), 0.9, lambda sl: np.nonzero(mask[sl]))
        want = _masked_dense_matches(desc_a, desc_b, 0.9, mask)
    assert np.array_equal(got.reshape(-1, 2), want)


def test_distances_are_computed_once_per_chunk_and_match_fresh_ones(monkeypatch):
    """One estimate matches the same descriptors many times: a Distances computes each chunk of rows once, and
    every matching through it gives the pairs a fresh computation gives."""
    from service import matching

    rng = np.random.default_rng(3)
    desc_a, desc_b = (rng.random((n, 16)).astype(np.float32) for n in (70, 50))
    desc_a /= np.linalg.norm(desc_a, axis=1, keepdims=True)
    desc_b /= np.linalg.norm(desc_b, axis=1, keepdims=True)
    fa, fb = (rng.normal(size=(n, 3)) for n in (70, 50))
    fa /= np.linalg.norm(fa, axis=1, keepdims=True)
    fb /= np.linalg.norm(fb, axis=1, keepdims=True)
    R, t = np.eye(3), np.array([1.0, 0.0, 0.0])
    monkeypatch.setattr(matching, "_DIST_ROWS", 16)
    fresh = [matching.putative_matches(matching.Distances(desc_a, desc_b), 0.9),
             matching.guided_matches(fa, fb, matching.Distances(desc_a, desc_b), R, t, max_deg=20.0)]
    calls = []
    compute = matching._distance_rows
    monkeypatch.setattr(matching, "_distance_rows", lambda rows, b: calls.append(len(rows)) or compute(rows, b))
    dist = matching.Distances(desc_a, desc_b)
    for _ in range(2):
        shared = [matching.putative_matches(dist, 0.9), matching.guided_matches(fa, fb, dist, R, t, max_deg=20.0)]
        assert all(np.array_equal(x, y) for x, y in zip(shared, fresh, strict=True))
    assert calls == [16, 16, 16, 16, 6]
    assert len(fresh[1]) > 0


def test_sift_crops_cover_their_share_of_the_sphere_with_the_margin():
    """A crop keeps the keypoints nearer its axis than any other's (above the tripod latitude): every such
    direction lies inside its crop, CROP_MARGIN_DEG from the edge, and each ring's size reaches no farther
    than its farthest share needs."""
    from service import poses

    n = 200_000
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = np.pi * (1 + 5**0.5) * i
    d = np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], -1)
    d = d[lat_lon_from_direction(d)[0] > np.radians(poses.TRIPOD_LAT_DEG)]
    own = np.argmax(d @ poses.CROP_ROTATIONS[:, :, 2].T, axis=1)
    sizes = [size for _, yaws, size in poses.CROPS for _ in yaws]
    for k, (w, h) in enumerate(sizes):
        local = d[own == k] @ poses.CROP_ROTATIONS[k]
        assert local.size and np.all(local[:, 2] > 0)
        for axis, side in ((0, w), (1, h)):
            need = np.degrees(np.arctan(np.abs(local[:, axis] / local[:, 2]).max()))
            half = np.degrees(np.arctan((side / 2) / poses.CROP_FOCAL))
            assert poses.CROP_MARGIN_DEG - 0.2 < half - need < poses.CROP_MARGIN_DEG + 0.5, (k, axis, half, need)


def test_mirror_bins_match_sift_of_the_mirrored_image():
    """SIFT of a left-right mirrored image, its descriptors' bins permuted, matches the image's own keypoints at
    their mirrored places (without the permutation few match)."""
    import cv2

    img = room_erp(_pose(20.0, [0.3, 0.0, 0.2]), 256)[40:216, 100:400]
    gray = np.ascontiguousarray(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY))
    sift = cv2.SIFT_create(contrastThreshold=0.02)
    (k1, d1), (k2, d2) = sift.detectAndCompute(gray, None), sift.detectAndCompute(np.ascontiguousarray(gray[:, ::-1]), None)
    d1, d2 = (np.sqrt(d / d.sum(1, keepdims=True)).astype(np.float32) for d in (d1, d2))

    def at_mirrored_place(pairs):
        p1 = np.array([k1[i].pt for i in pairs[:, 0]])
        p2 = np.array([k2[j].pt for j in pairs[:, 1]])
        return int(np.sum(np.hypot(gray.shape[1] - 1 - p2[:, 0] - p1[:, 0], p2[:, 1] - p1[:, 1]) < 1.5))

    mirrored, plain = putative_matches(Distances(d1, d2[:, MIRROR_BINS])), putative_matches(Distances(d1, d2))
    assert at_mirrored_place(mirrored) > 0.8 * len(k1) and at_mirrored_place(plain) < 0.2 * len(k1)


@pytest.mark.parametrize("flip, name", [(lambda img: img[:, ::-1], "mirrored left-right"),
                                        (lambda img: img[::-1, ::-1], "upside down")])
def test_a_flipped_panorama_is_refused_not_given_a_pose_180_deg_wrong(flip, name):
    """B 1 m to A's right and turned 90 deg: mirrored, or upside down, the estimate gave a pose 170-180 deg off
    with 300-370 guided inliers and a baseline off by up to 63%."""
    img_b = np.ascontiguousarray(flip(room_erp(_pose(90.0, [1.0, 0.0, 0.0]))))
    with pytest.raises(PoseEstimationFailed) as exc:
        estimate_poses(room_erp(np.eye(4)), img_b, PoseOptions(camera_height=1.5))
    assert exc.value.status == 422 and exc.value.code == "flipped_panorama"
    assert name in exc.value.message and "image_b" in exc.value.message


def test_the_mirror_permutation_undoes_itself_and_each_flip_is_a_reflection_or_a_half_turn():
    """Mirroring twice is the identity; a flip's bearing signs are a mirror (one axis, descriptors mirrored) or a
    half turn (two axes, descriptors as they are)."""
    assert sorted(MIRROR_BINS) == list(range(128)) and np.array_equal(MIRROR_BINS[MIRROR_BINS], np.arange(128))
    for _, sign, mirror in FLIPS:
        assert np.all(np.abs(sign) == 1) and (np.prod(sign) < 0) == mirror
