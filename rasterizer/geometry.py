"""Camera geometry: the one source of truth for frames and pixel conventions.

Conventions (``docs/conventions.md`` section 1):

* Camera frame is OpenCV: +x right, +y down, +z forward. Poses are
  camera-to-world 4x4 ``c2w`` matrices.
* Direction of (lat, lon): ``d = (cos lat sin lon, -sin lat, cos lat cos lon)``.
* Pixel *centres*: ERP column ``c`` has ``lon = (c + 0.5) / W * 2 pi - pi``.
  Continuous pixel coordinates used here put the centre of pixel ``c`` at
  coordinate ``c`` (so the left image border is at -0.5).
* Yin grid (h x w, w = 3h): lat in [-pi/4, pi/4], lon in [-3pi/4, 3pi/4].
* Yang grid: Yin layout, direction ``M d(lat', lon')`` with
  ``M = [[0,1,0],[1,0,0],[0,0,-1]]`` (a proper rotation, its own inverse).
* Depth is Euclidean range along the ray.

Every function is vectorised over leading axes and works in float64 unless
the caller passes float32 (dtype follows the input).
"""

from __future__ import annotations

from functools import lru_cache
from typing import Literal

import numpy as np

GridKind = Literal["erp", "yin", "yang"]

#: Rotation taking Yin-frame directions to Yang directions (camera frame).
YANG_ROTATION = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])

#: Half extents of the Yin domain (radians).
YIN_LAT_MAX = np.pi / 4
YIN_LON_MAX = 3 * np.pi / 4

#: Floor on cos(lat) and on squared radii, so Jacobians stay finite at poles
#: and at the camera centre.
EPS = 1e-12


# ---------------------------------------------------------------------------
# Spherical coordinates
# ---------------------------------------------------------------------------

def unit_vectors(v: np.ndarray, floor: float) -> np.ndarray:
    """``v`` (..., 3) scaled to unit length; lengths below ``floor`` are divided by ``floor`` (no NaN at 0)."""
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), floor)


def direction_from_lat_lon(lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
    """Unit camera-frame direction(s) for latitude/longitude, shape (..., 3)."""
    lat, lon = np.broadcast_arrays(np.asarray(lat), np.asarray(lon))
    cl = np.cos(lat)
    return np.stack([cl * np.sin(lon), -np.sin(lat), cl * np.cos(lon)], axis=-1)


def lat_lon_from_direction(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Latitude and longitude of camera-frame point(s) ``p`` (..., 3).

    Any non-zero length works. At the poles longitude is 0 by convention
    (``arctan2(0, 0) = 0`` in numpy); at the origin both are 0.
    """
    p = np.asarray(p)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    lat = np.arctan2(-y, np.hypot(x, z))
    lon = np.arctan2(x, z)
    return lat, lon


# ---------------------------------------------------------------------------
# Pixel <-> direction, per grid
# ---------------------------------------------------------------------------

def erp_lat_lon(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Latitude (H, 1) and longitude (1, W) of ERP pixel centres."""
    rows = np.arange(height, dtype=np.float64)[:, None]
    cols = np.arange(width, dtype=np.float64)[None, :]
    lat = np.pi / 2 - (rows + 0.5) / height * np.pi
    lon = (cols + 0.5) / width * 2 * np.pi - np.pi
    return lat, lon


def yin_lat_lon(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Latitude (h, 1) and longitude (1, w) of Yin (or Yang-local) pixel centres."""
    rows = np.arange(height, dtype=np.float64)[:, None]
    cols = np.arange(width, dtype=np.float64)[None, :]
    lat = YIN_LAT_MAX - (rows + 0.5) * (2 * YIN_LAT_MAX) / height
    lon = -YIN_LON_MAX + (cols + 0.5) * (2 * YIN_LON_MAX) / width
    return lat, lon


@lru_cache(maxsize=32)
def _grid_directions_cached(kind: str, height: int, width: int) -> np.ndarray:
    if kind == "erp":
        lat, lon = erp_lat_lon(height, width)
        d = direction_from_lat_lon(lat, lon)
    elif kind in ("yin", "yang"):
        lat, lon = yin_lat_lon(height, width)
        d = direction_from_lat_lon(lat, lon)
        if kind == "yang":
            d = d @ YANG_ROTATION.T
    else:
        raise ValueError(f"unknown grid kind {kind!r}; expected 'erp', 'yin' or 'yang'")
    d.setflags(write=False)
    return d


def grid_directions(kind: GridKind, height: int, width: int) -> np.ndarray:
    """Camera-frame unit ray of every pixel centre of a grid, (H, W, 3) float64.

    Cached per (kind, size) and returned read-only.
    """
    if height <= 0 or width <= 0:
        raise ValueError(f"grid size must be positive, got {height}x{width}")
    return _grid_directions_cached(kind, int(height), int(width))


def to_grid_frame(kind: GridKind, p: np.ndarray) -> np.ndarray:
    """Express camera-frame points in the frame whose Yin layout the grid uses.

    ERP and Yin use the camera frame itself; Yang uses ``M p`` (M = M^-1).
    """
    if kind == "yang":
        p = np.asarray(p)
        return np.stack([p[..., 1], p[..., 0], -p[..., 2]], axis=-1)
    return np.asarray(p)


def project_to_grid(kind: GridKind, p: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Continuous pixel coordinates (col, row) of camera-frame points ``p``.

    Pixel centre (r, c) sits at coordinate (c, r). For Yin/Yang the result
    may fall outside [-0.5, size - 0.5]: the caller decides what is in view
    (see :func:`in_grid_domain`).
    """
    lat, lon = lat_lon_from_direction(to_grid_frame(kind, p))
    return grid_coords_from_lat_lon(kind, lat, lon, height, width)


def grid_coords_from_lat_lon(kind: GridKind, lat: np.ndarray, lon: np.ndarray, height: int,
                             width: int) -> tuple[np.ndarray, np.ndarray]:
    """Continuous pixel coordinates (col, row) of latitude/longitude (radians) in the grid's own frame
    (:func:`to_grid_frame`): the second half of :func:`project_to_grid`, for callers that hold them already."""
    if kind == "erp":
        col = (lon + np.pi) / (2 * np.pi) * width - 0.5
        row = (np.pi / 2 - lat) / np.pi * height - 0.5
    else:
        col = (lon + YIN_LON_MAX) / (2 * YIN_LON_MAX) * width - 0.5
        row = (YIN_LAT_MAX - lat) / (2 * YIN_LAT_MAX) * height - 0.5
    return col, row


def in_grid_domain(kind: GridKind, p: np.ndarray) -> np.ndarray:
    """True where the direction of ``p`` lies inside the grid's angular domain."""
    if kind == "erp":
        return np.ones(np.shape(p)[:-1], dtype=bool)
    lat, lon = lat_lon_from_direction(to_grid_frame(kind, p))
    return (np.abs(lat) <= YIN_LAT_MAX) & (np.abs(lon) <= YIN_LON_MAX)


def grid_jacobian(kind: GridKind, p: np.ndarray, height: int, width: int) -> np.ndarray:
    """Analytic 2x3 Jacobian d(col, row)/dp of :func:`project_to_grid`, (..., 2, 3).

    In the grid frame q, row 0 is d col/dq = s_x (z, 0, -x) / (x^2 + z^2) and
    row 1 is d row/dq = s_y (-x y / rho, rho, -z y / rho) / r^2 with
    rho = sqrt(x^2 + z^2), both floored so poles and the origin stay finite. For Yang the chain rule multiplies by M on the
    right (the u-row sign bug of the official Yang kernel is not copied).
    """
    q = to_grid_frame(kind, p)
    x, y, z = q[..., 0], q[..., 1], q[..., 2]
    if kind == "erp":
        sx, sy = width / (2 * np.pi), height / np.pi
    else:
        sx, sy = width / (2 * YIN_LON_MAX), height / (2 * YIN_LAT_MAX)
    rho2 = np.maximum(x * x + z * z, EPS)
    rho = np.sqrt(rho2)
    r2 = np.maximum(rho2 + y * y, EPS)
    zero = np.zeros_like(x)
    dcol = np.stack([sx * z / rho2, zero, -sx * x / rho2], axis=-1)
    # row grows as lat falls; d(-lat)/dq = (-x y / rho, rho, -z y / rho) / r^2.
    drow = np.stack([-sy * y * x / (rho * r2), sy * rho / r2, -sy * y * z / (rho * r2)], axis=-1)
    jac = np.stack([dcol, drow], axis=-2)
    if kind == "yang":
        jac = jac[..., [1, 0, 2]] * np.array([1.0, 1.0, -1.0])
    return jac


# ---------------------------------------------------------------------------
# Pinhole (perspective) camera
# ---------------------------------------------------------------------------

def pinhole_intrinsics(width: int, height: int, fov_deg: float) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) of a pinhole camera with horizontal field of view ``fov_deg``.

    Square pixels; the principal point is the image centre in the pixel-centre
    coordinates used here (centre of pixel c at coordinate c).
    """
    if not (0.0 < fov_deg < 180.0):
        raise ValueError(f"fov_deg must be in (0, 180), got {fov_deg}")
    fx = 0.5 * width / np.tan(np.radians(fov_deg) / 2)
    return float(fx), float(fx), (width - 1) / 2.0, (height - 1) / 2.0


def pinhole_directions(width: int, height: int, fov_deg: float) -> np.ndarray:
    """Unit camera-frame rays of a pinhole camera's pixel centres, (H, W, 3)."""
    return pinhole_rays(width, height, pinhole_intrinsics(width, height, fov_deg)[0])


def pinhole_rays(width: int, height: int, focal: float) -> np.ndarray:
    """Unit camera-frame rays (H, W, 3) of the pixel centres of a pinhole camera of ``focal`` pixels
    (square pixels, the principal point at the image centre)."""
    fx = fy = focal
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    cols = np.arange(width, dtype=np.float64)[None, :]
    rows = np.arange(height, dtype=np.float64)[:, None]
    d = np.stack(np.broadcast_arrays((cols - cx) / fx, (rows - cy) / fy, np.ones((height, width))), axis=-1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def pinhole_project(p: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> tuple[np.ndarray, np.ndarray]:
    """(col, row) of camera-frame points; only meaningful for z > 0."""
    p = np.asarray(p)
    z = np.where(np.abs(p[..., 2]) < EPS, EPS, p[..., 2])
    return fx * p[..., 0] / z + cx, fy * p[..., 1] / z + cy


def pinhole_jacobian(p: np.ndarray, fx: float, fy: float) -> np.ndarray:
    """Analytic d(col, row)/dp of :func:`pinhole_project`, (..., 2, 3)."""
    p = np.asarray(p)
    x, y = p[..., 0], p[..., 1]
    z = np.where(np.abs(p[..., 2]) < EPS, EPS, p[..., 2])
    zero = np.zeros_like(x)
    r0 = np.stack([fx / z, zero, -fx * x / (z * z)], axis=-1)
    r1 = np.stack([zero, fy / z, -fy * y / (z * z)], axis=-1)
    return np.stack([r0, r1], axis=-2)


# ---------------------------------------------------------------------------
# Poses
# ---------------------------------------------------------------------------

OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


class PoseError(ValueError):
    """A pose matrix that is not a finite rigid transform."""


def as_c2w(matrix, convention: str = "opencv", *, tol: float = 1e-3) -> np.ndarray:
    """Validate a 4x4 or 3x4 camera-to-world pose and return it as 4x4 OpenCV float64.

    Raises :class:`PoseError` naming the problem for a wrong shape, NaN/Inf,
    a non-orthonormal or mirrored rotation, or a bad bottom row. The rotation
    is re-orthonormalised (SVD) so later maths sees an exact rotation.
    """
    try:
        raw = np.asarray(matrix)
    except (TypeError, ValueError):
        raw = np.asarray(None, dtype=object)  # rows of different lengths
    if raw.dtype.kind not in "iuf":  # text ("0.5", which numpy would convert), booleans, objects, ragged rows
        raise PoseError("pose is not a numeric 4x4 or 3x4 matrix (rows of different lengths, or entries that are "
                        "not numbers)")
    m = raw.astype(np.float64)
    if m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    if m.shape != (4, 4):
        raise PoseError(f"pose must be 4x4 or 3x4, got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise PoseError("pose contains NaN or Inf")
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=tol):
        raise PoseError(f"pose bottom row must be [0, 0, 0, 1], got {m[3].tolist()}")
    rot = m[:3, :3]
    if not np.allclose(rot @ rot.T, np.eye(3), atol=tol):
        raise PoseError("pose rotation is not orthonormal (scale or shear is not allowed)")
    if np.linalg.det(rot) <= 0:
        raise PoseError("pose rotation has determinant -1 (a mirror), not a proper rotation")
    if convention == "opengl":
        m = m @ OPENGL_TO_OPENCV
    elif convention != "opencv":
        raise PoseError(f"unknown pose convention {convention!r}; expected 'opencv' or 'opengl'")
    u, _, vt = np.linalg.svd(m[:3, :3])
    out = m.copy()
    out[:3, :3] = u @ vt
    out[3] = [0.0, 0.0, 0.0, 1.0]
    return out


def rigid_inverse(c2w: np.ndarray) -> np.ndarray:
    """Closed-form inverse of a rigid 4x4 transform (no general matrix inverse)."""
    c2w = np.asarray(c2w, dtype=np.float64)
    rot = c2w[..., :3, :3]
    t = c2w[..., :3, 3]
    out = np.zeros_like(c2w)
    rot_t = np.swapaxes(rot, -1, -2)
    out[..., :3, :3] = rot_t
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", rot_t, t)
    out[..., 3, 3] = 1.0
    return out


def yang_pose(c2w: np.ndarray) -> np.ndarray:
    """Pose whose Yin image is the Yang image of ``c2w``: ``c2w @ [[M, 0], [0, 1]]``."""
    m4 = np.eye(4)
    m4[:3, :3] = YANG_ROTATION
    return np.asarray(c2w, dtype=np.float64) @ m4


def world_to_camera(points: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    """Camera-frame coordinates of world points (..., 3) for pose ``c2w``."""
    rot = np.asarray(c2w)[:3, :3]
    t = np.asarray(c2w)[:3, 3]
    return (np.asarray(points) - t) @ rot
