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

    k, h, w = len(fs.FLOOR_RATIOS), 40, 80
    floor, rng = 40, np.random.default_rng(0)

    def zncc(ref, other, level_ref, level_other, R, t, normal, offsets, **_):
        z = rng.uniform(-0.2, 0.5, (k, h, w)).astype(np.float32)
        z[floor, :10] = 0.9  # a quarter of the band agrees on the floor's plane
        z[k - 1, 10:14] = 0.9  # a tenth on the deepest candidate, the strongest pile
        z[k - 2, 10:14] = 0.8
        return z

    monkeypatch.setattr(fs, "plane_zncc", zncc)
    d, info = fs.floor_ratio(np.zeros((8, 16)), np.zeros((8, 16)), np.eye(3), np.eye(3), np.eye(3),
                             np.array([1.0, 0.0, 0.0]))
    assert abs(np.log(d / fs.FLOOR_RATIOS[floor])) < 0.06, (d, info)
    assert all(p["ratio"] < fs.FLOOR_RATIOS[-1] for p in info["planes"]), info
