"""Dense floor sweep: a ray-cast room with a textured floor and a textured bed (a higher plane), known floor depth."""

import numpy as np
import pytest

from rasterizer.floor_sweep import floor_ratio
from rasterizer.geometry import direction_from_lat_lon, erp_lat_lon
from rasterizer.relative_pose import rotation_exp, yaw_rotation

FLOOR_Y = 1.6  # A's levelled frame (OpenCV, y down), A at the origin; baselines of 1
ROOM_MIN, ROOM_MAX = np.array([-3.0, -1.0, -3.5]), np.array([3.5, FLOOR_Y, 4.0])
BED_MIN, BED_MAX = np.array([-3.0, 1.0, -0.6]), np.array([-0.5, FLOOR_Y, 4.0])  # top 0.6 m above the floor
_LATTICE = np.random.default_rng(3).random((48, 48, 48)).astype(np.float32)


def _noise(p: np.ndarray, cell: float) -> np.ndarray:
    """Trilinear value noise (...,) in [0, 1] on a random lattice ``cell`` metres apart."""
    q = p / cell
    i = np.floor(q).astype(int)
    f = q - i
    out = 0.0
    for corner in np.ndindex(2, 2, 2):
        w = np.prod([f[..., k] if c else 1 - f[..., k] for k, c in enumerate(corner)], axis=0)
        out = out + w * _LATTICE[tuple((i[..., k] + c) % 48 for k, c in enumerate(corner))]
    return out


def render(origin, world_from_cam: np.ndarray, height: int = 256, ss: int = 2) -> np.ndarray:
    """Grey ERP (height, 2 height) in [0, 1] seen from ``origin`` with camera-to-world turn ``world_from_cam``."""
    lat, lon = erp_lat_lon(height * ss, 2 * height * ss)
    d = direction_from_lat_lon(lat, lon) @ world_from_cam.T
    o = np.asarray(origin, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_room = np.min(np.where(d > 0, (ROOM_MAX - o) / d, (ROOM_MIN - o) / d), axis=-1)
        t1, t2 = (BED_MIN - o) / d, (BED_MAX - o) / d
    near, far = np.max(np.minimum(t1, t2), axis=-1), np.min(np.maximum(t1, t2), axis=-1)
    t = np.where((near <= far) & (near > 0) & (near < t_room), near, t_room)
    p = o + t[..., None] * d
    contrast = np.where(p[..., 1] > FLOOR_Y - 1e-6, 0.22, 1.0)  # a plain floor: the bed top holds more texture
    tex = 0.5 + contrast * (0.5 * _noise(p, 0.05) + 0.3 * _noise(p, 0.25) - 0.4)
    return tex.reshape(height, ss, 2 * height, ss).mean((1, 3)).astype(np.float32)


def _case(yaw_deg: float, t, tilt_a=(0.0, 0.0, 0.0), tilt_b=(0.0, 0.0, 0.0)):
    """Images and levelling turns of A (at the origin) and B (at ``t``, turned by ``yaw_deg``), each camera
    tilted by the rotation vector ``tilt_*`` (deg); the pose is returned in the levelled frames."""
    R = yaw_rotation(np.radians(yaw_deg))
    cams = []
    for origin, turn, tilt in ((np.zeros(3), np.eye(3), tilt_a), (np.asarray(t, float), R, tilt_b)):
        level = rotation_exp(np.radians(tilt))  # levelled-from-camera: the camera's tilt
        cams.append((render(origin, turn @ level), level))
    return cams, R, np.asarray(t, float)


@pytest.mark.parametrize("yaw_deg, t, tilt_b", [
    (30.0, [0.8, 0.0, 0.6], (0.0, 0.0, 0.0)),
    (-70.0, [0.0, 0.05, -1.0], (3.0, 0.0, -2.5)),  # B tilted 4 deg and 5 cm lower than A
])
def test_floor_ratio_finds_the_floor_below_a_bed(yaw_deg, t, tilt_b):
    ((a, level_a), (b, level_b)), R, tt = _case(yaw_deg, t, tilt_b=tilt_b)
    d, info = floor_ratio(a, b, level_a, level_b, R, tt / np.linalg.norm(tt))
    true = FLOOR_Y / np.linalg.norm(tt)
    assert abs(d / true - 1) < 0.03, (d, true, info)
    bed = min(info["planes"], key=lambda p: abs(np.log(p["ratio"] * np.linalg.norm(tt) / BED_MIN[1])))
    assert abs(bed["ratio"] * np.linalg.norm(tt) / BED_MIN[1] - 1) < 0.1, info  # the bed top is a plane too ...
    assert bed["share"] > info["floor_share"] > 0.02, info  # ... and holds more of the pixels than the plain floor


def test_flat_images_have_no_floor():
    flat = np.full((128, 256), 0.5, np.float32)
    with pytest.raises(ValueError, match="floor is not seen"):
        floor_ratio(flat, flat, np.eye(3), np.eye(3), np.eye(3), np.array([1.0, 0.0, 0.0]))


def test_votes_piled_at_the_deepest_candidate_are_not_a_floor_there(monkeypatch):
    """Pixels whose best plane is the deepest candidate say "this deep or deeper" (far content, nearly no
    parallax), not that a plane lies there: on a real pair (bedroom_theta 3+9) such a pile, the deepest peak,
    gave a baseline 20x too small. The floor is the deepest peak inside the candidates."""
    import rasterizer.floor_sweep as fs

    height = 80
    k, (h, w) = len(fs.FLOOR_RATIOS), fs.band_directions(height, fs.BAND_DEG).shape[:2]
    floor, rng = 40, np.random.default_rng(0)

    def zncc(ref, other, level_ref, level_other, R, t, normal, offsets, **_):
        z = rng.uniform(-0.2, 0.5, (len(offsets), h, w)).astype(np.float32)  # the last: the parallax-free plane
        z[floor, -h // 4:] = 0.9  # a quarter of the band, nearest the nadir, agrees on the floor's plane
        z[k - 1, :h // 10] = 0.9  # a tenth on the deepest candidate, the strongest pile
        z[k - 2, :h // 10] = 0.8
        return z

    monkeypatch.setattr(fs, "plane_zncc", zncc)
    d, info = fs.floor_ratio(np.zeros((height, 2 * height)), np.zeros((height, 2 * height)), np.eye(3), np.eye(3),
                             np.eye(3), np.array([1.0, 0.0, 0.0]))
    assert abs(np.log(d / fs.FLOOR_RATIOS[floor])) < 0.06, (d, info)
    assert all(p["ratio"] < fs.FLOOR_RATIOS[-1] for p in info["planes"]), info


def _black_cap(img: np.ndarray, deg: float) -> np.ndarray:
    """``img`` with the rows within ``deg`` of the nadir black (a camera's nadir logo or a masked tripod)."""
    out = img.copy()
    out[int(round(img.shape[0] * (1 - deg / 180))):] = 0.0
    return out


def test_windows_reaching_a_uniform_area_are_not_scored():
    """A black nadir cap's edge is the same curve in both views under any plane far enough below, so its windows
    voted for deep planes (bedroom_theta 1+9 with a 30-deg cap: a baseline 0.07x). Windows of either view that
    reach a uniform area are not compared; on a capture without one nothing changes."""
    from rasterizer.floor_sweep import FLOOR_RATIOS, near_uniform, plane_zncc

    ((a, level_a), (b, level_b)), R, t = _case(30.0, [0.8, 0.0, 0.6])
    t = t / np.linalg.norm(t)
    assert near_uniform(a, 2) is None and near_uniform(b, 2) is None
    ca, cb = _black_cap(a, 30.0), _black_cap(b, 30.0)
    args = (level_a, level_b, R, t, np.array([0.0, 1.0, 0.0]), FLOOR_RATIOS)
    plain, capped = plane_zncc(a, b, *args), plane_zncc(ca, cb, *args)
    height = a.shape[0]
    lat = np.pi / 2 - (np.arange(height) + 0.5) / height * np.pi
    in_band = (lat >= np.radians(20.0) - np.pi / 2 - 0.05) & (lat <= np.radians(80.0) - np.pi / 2 + 0.05)
    cap_row = int(round(height * (1 - 30.0 / 180)))
    edge = (np.arange(height) >= cap_row - 2) & (np.arange(height) < cap_row)  # not black; their 5x5 windows reach it
    assert np.isfinite(plain[:, edge[in_band]]).any()
    assert not np.isfinite(capped[:, edge[in_band]]).any()
    far = (lat > np.radians(-45.0))[in_band]  # clear of the cap and its margin: mostly scored as before
    assert np.isfinite(capped[:, far]).sum() > 0.5 * np.isfinite(plain[:, far]).sum()


@pytest.mark.parametrize("cap_deg", [45.0, 60.0])
def test_a_floor_hidden_near_the_cameras_is_refused(cap_deg):
    """With the band within NEAR_FLOOR_DEG of both nadirs mostly (45 deg) or wholly (60 deg) black, no plane is
    trusted as the floor (bedroom_theta 2+5 with a 60-deg cap took a bed top: a baseline 1.7x; 1+9 with a 45-deg
    cap a pile of far votes: 0.33x); the sweep still compares poses without the rule."""
    from rasterizer.floor_sweep import FloorHidden

    ((a, level_a), (b, level_b)), R, t = _case(30.0, [0.8, 0.0, 0.6])
    ca, cb = _black_cap(a, cap_deg), _black_cap(b, cap_deg)
    with pytest.raises(FloorHidden, match="not seen well enough"):
        floor_ratio(ca, cb, level_a, level_b, R, t / np.linalg.norm(t))
    d, info = floor_ratio(ca, cb, level_a, level_b, R, t / np.linalg.norm(t), near_deg=None)
    assert d > 0 and "near_floor_scored" not in info


def test_a_deep_peak_voted_only_far_from_the_nadir_is_not_the_floor(monkeypatch):
    """Votes from the band's rows near the horizon only (far content) can pile on a plane below the floor that no
    candidate end censors (bedroom_theta 1+9 with a 30-deg cap, after the cap's edge was masked: a baseline 0.33x).
    The floor is the deepest peak that the rows near a nadir vote for."""
    import rasterizer.floor_sweep as fs

    height = 40
    h, w = fs.band_directions(height, fs.BAND_DEG).shape[:2]
    ang = np.degrees(np.arccos(np.clip(fs.band_directions(height, fs.BAND_DEG)[..., 1], -1, 1)))
    floor, deep, rng = 30, 60, np.random.default_rng(0)

    def zncc(ref, other, level_ref, level_other, R, t, normal, offsets, **_):
        z = rng.uniform(-0.2, 0.5, (len(offsets), h, w)).astype(np.float32)
        z[floor, (ang < 45)[:, 0], :12] = 0.9  # the floor, seen near the nadir
        z[deep, (ang > 70)[:, 0], :] = 0.9  # a pile from the rows near the horizon
        return z

    monkeypatch.setattr(fs, "plane_zncc", zncc)
    args = (np.zeros((height, 2 * height)), np.zeros((height, 2 * height)), np.eye(3), np.eye(3), np.eye(3),
            np.array([1.0, 0.0, 0.0]))
    d, info = fs.floor_ratio(*args)
    assert abs(np.log(d / fs.FLOOR_RATIOS[floor])) < 0.06, (d, info)
    assert any(abs(np.log(p["ratio"] / fs.FLOOR_RATIOS[deep])) < 0.06 for p in info["planes"]), info  # a strong peak


def _stamped_cap(img: np.ndarray, deg: float) -> np.ndarray:
    """``img`` with a textured logo over the rows within ``deg`` of the nadir, the same pixels in every image: dark,
    with bright rings of latitude every 4 rows and bright meridians every 16 columns."""
    out = img.copy()
    r0 = int(round(img.shape[0] * (1 - deg / 180)))
    out[r0:] = 0.15
    out[r0:, ::16] = 1.0
    out[r0::4] = 1.0
    return out


def test_windows_that_match_without_parallax_do_not_vote(monkeypatch):
    """A logo stamped on both panoramas' nadirs moves with the cameras: its windows match under every plane deep
    enough, and on zind_room09 pano_4+5 with a 35-deg logo they piled on the next-to-deepest candidate, which no end
    censors, seen near the nadir: a baseline 0.045x. Windows that also match through the parallax-free plane (the
    last offset the sweep is given) tell no height and do not vote."""
    import rasterizer.floor_sweep as fs

    k, height = len(fs.FLOOR_RATIOS), 40
    h, w = fs.band_directions(height, fs.BAND_DEG).shape[:2]
    ang = np.degrees(np.arccos(np.clip(fs.band_directions(height, fs.BAND_DEG)[..., 1], -1, 1)))
    floor, rng = 30, np.random.default_rng(0)

    def zncc(ref, other, level_ref, level_other, R, t, normal, offsets, **_):
        assert len(offsets) == k + 1 and offsets[-1] >= 100 * offsets[:-1].max()
        z = rng.uniform(-0.2, 0.5, (len(offsets), h, w)).astype(np.float32)
        z[floor, (ang < 45)[:, 0], :12] = 0.9  # the floor, seen near the nadir
        logo = (ang < 35)[:, 0]
        z[k - 3:, logo, 12:] = 0.85  # the logo: every deep plane and the parallax-free one ...
        z[k - 2, logo, 12:] = 0.9  # ... and best on the next-to-deepest candidate
        return z

    monkeypatch.setattr(fs, "plane_zncc", zncc)
    d, info = fs.floor_ratio(np.zeros((height, 2 * height)), np.zeros((height, 2 * height)), np.eye(3), np.eye(3),
                             np.eye(3), np.array([1.0, 0.0, 0.0]))
    assert abs(np.log(d / fs.FLOOR_RATIOS[floor])) < 0.06, (d, info)
    assert all(p["ratio"] < fs.FLOOR_RATIOS[k - 6] for p in info["planes"]), info


def test_a_logo_stamped_on_both_nadirs_leaves_the_floor():
    """On the ray-cast room with a textured logo over both nadirs, the logo's windows match through the
    parallax-free plane (so they do not vote) and the floor is found as without it."""
    import rasterizer.floor_sweep as fs

    ((a, level_a), (b, level_b)), R, t = _case(30.0, [0.8, 0.0, 0.6])
    t = t / np.linalg.norm(t)
    sa, sb = _stamped_cap(a, 30.0), _stamped_cap(b, 30.0)
    far = fs.plane_zncc(sa, sb, level_a, level_b, R, t, np.array([0.0, 1.0, 0.0]),
                        np.array([fs.FLOOR_RATIOS[-1] * fs.PARALLAX_FREE_FACTOR]))[0]
    assert np.nanmean(far > 0.7) > 0.05
    d, info = floor_ratio(sa, sb, level_a, level_b, R, t)
    assert abs(d / FLOOR_Y - 1) < 0.03, (d, info)
    assert info["near_parallax_free"] > 0.05, info  # counted near the nadir, and the floor found all the same
