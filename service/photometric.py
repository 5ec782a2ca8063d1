"""Photometric agreement of two panoramas under relative poses: a test of poses, not an estimate.

:func:`photometric_scores` asks, for each pose ``[R | t]`` (B in A's camera frame), how many textured pixels of A
find their 7x7 window again in B along their epipolar curve. Estimating poses uses it to choose between two pose
modes (:mod:`service.poses`), and checking given poses to compare readings of them (:mod:`service.pose_check`).
What does not depend on the pose (the grey images at the working height, A's gradients and pixel directions) is
made once for all poses of a call; each pose's score is the same to the bit as when it is scored alone.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from rasterizer.geometry import erp_lat_lon, grid_directions
from rasterizer.threads import map_threads

#: Grey ERPs wider than this are area-downsampled first (what every pose step reads).
MAX_ERP_WIDTH = 2048


def gray_erp(erp: np.ndarray) -> np.ndarray:
    """Grey uint8 ERP (h, w) of an RGB or grey, uint8 or [0, 1] float ERP, area-downsampled to at most
    :data:`MAX_ERP_WIDTH` wide; a grey uint8 ERP within that width comes back as it is."""
    import cv2

    img = np.asarray(erp)
    if img.dtype != np.uint8:
        img = np.clip(np.asarray(img, np.float32) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    gray = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img
    if gray.shape[1] > MAX_ERP_WIDTH:
        gray = cv2.resize(gray, (MAX_ERP_WIDTH, MAX_ERP_WIDTH // 2), interpolation=cv2.INTER_AREA)
    return gray


def small_gray(erp: np.ndarray, height: int) -> np.ndarray:
    """Grey ERP (height, 2 * height) float32 in [0, 1], area-downsampled."""
    import cv2

    return cv2.resize(gray_erp(erp), (2 * height, height), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0


class _Pair(NamedTuple):
    """What every pose's score of one image pair reads: the grey images ``ga``, ``gb`` (height, 2 height) float32,
    the unit directions ``grid`` (height, 2 height, 3) of the ERP's pixel centres
    (:func:`rasterizer.geometry.grid_directions`, cached), and over the band ``radius`` rows from either pole A's
    gradient magnitude ``band`` (rows, 2 height) and whether the rows lie within 60 deg of the horizon (``level``,
    (rows, 1))."""

    ga: np.ndarray
    gb: np.ndarray
    grid: np.ndarray
    band: np.ndarray
    level: np.ndarray
    height: int
    radius: int


def _pair(erp_a: np.ndarray, erp_b: np.ndarray, height: int, radius: int) -> _Pair:
    """The pose-free part of :func:`photometric_scores` for one image pair."""
    ga, gb = small_gray(erp_a, height), small_gray(erp_b, height)
    gy, gx = np.gradient(ga)
    lat, _ = erp_lat_lon(height, 2 * height)
    return _Pair(ga, gb, grid_directions("erp", height, 2 * height), np.hypot(gx, gy)[radius:height - radius],
                 np.abs(lat[radius:height - radius]) < np.radians(60), height, radius)


def photometric_scores(erp_a: np.ndarray, erp_b: np.ndarray, poses: Sequence[tuple[np.ndarray, np.ndarray]], *,
                       height: int = 256, samples: int = 1500, planes: int = 48, radius: int = 3,
                       seed: int = 0) -> list[float]:
    """How well B's image agrees with A's under each pose ``(R, t)`` of ``poses`` (``X_a = R X_b + t``; ``t``
    any non-zero length): the share of up to ``samples`` textured pixels of A (away from the epipoles, within
    60 deg of the horizon) whose best 7x7 ZNCC along the pixel's epipolar curve in B (``planes`` ranges, 0.3-30
    baselines, fronto-parallel patches) exceeds 0.8; about 1 for the true pose, lower for a wrong one, 0 for flat
    images. erp_a, erp_b: RGB or grey, uint8 or [0, 1] float ERPs of any 2:1 size, compared at ``height`` rows.
    The poses are scored two at a time (:func:`rasterizer.threads.map_threads`)."""
    pair = _pair(erp_a, erp_b, height, radius)
    return map_threads(lambda pose: _score(pair, *pose, samples=samples, planes=planes, seed=seed), poses)


def _score(pair: _Pair, R: np.ndarray, t: np.ndarray, *, samples: int, planes: int, seed: int) -> float:
    """One pose's score (:func:`photometric_scores`)."""
    import cv2

    ga, gb, band, height, radius = pair.ga, pair.gb, pair.band, pair.height, pair.radius
    t = np.asarray(t, np.float64) / np.linalg.norm(t)
    ok = pair.level & (np.abs(pair.grid[radius:height - radius] @ t) < np.cos(np.radians(15)))
    if np.count_nonzero(ok) < 50:
        return 0.0
    ok &= band > np.percentile(band[ok], 70)
    if np.count_nonzero(ok) < 20:  # flat image: nothing to compare
        return 0.0
    idx = np.random.default_rng(seed).choice(np.count_nonzero(ok), size=min(samples, np.count_nonzero(ok)), replace=False)
    r0, c0 = (v[idx] for v in np.nonzero(ok))
    r0 = r0 + radius  # the band's rows in the image
    dr, dc = np.mgrid[-radius:radius + 1, -radius:radius + 1]
    pr, pc = r0[:, None] + dr.ravel(), (c0[:, None] + dc.ravel()) % (2 * height)  # (N, P)
    patch_a = ga[pr, pc]
    dirs = pair.grid[pr, pc]
    inv = np.linspace(1 / 0.3, 1 / 30.0, planes)
    # fronto-parallel patch: each offset ray meets the plane through the centre point, normal to the centre ray
    centre = dirs[:, dr.size // 2:dr.size // 2 + 1]
    lam = ((1 / inv)[None, None, :] / np.maximum(np.sum(dirs * centre, -1), 1e-3)[..., None]).astype(np.float32)
    rays_b, t_b = (dirs @ R).astype(np.float32), (t @ R).astype(np.float32)  # R^T d, R^T t (row vectors)
    x, y, z = (lam * rays_b[..., i:i + 1] for i in range(3))  # R^T (lam d - t): (N, P, K) each
    for v, ti in zip((x, y, z), t_b):
        v -= ti
    mx, my = _erp_pixels(x, y, z, height)
    patch_b = cv2.remap(gb, mx.reshape(len(r0), -1), my.reshape(len(r0), -1), cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_WRAP).reshape(mx.shape)  # (N, P, K)
    za = patch_a - patch_a.mean(1, keepdims=True)
    za /= np.maximum(np.linalg.norm(za, axis=1, keepdims=True), 1e-6)
    zb = patch_b
    zb -= patch_b.mean(1, keepdims=True)
    zb /= np.maximum(np.linalg.norm(zb, axis=1, keepdims=True), 1e-6)
    best = np.max(np.einsum("np,npk->nk", za, zb), axis=1)
    return float(np.mean(best > 0.8))


def _erp_pixels(x: np.ndarray, y: np.ndarray, z: np.ndarray, height: int) -> tuple[np.ndarray, np.ndarray]:
    """ERP pixel coordinates (column, row), float32, of the camera-frame directions ``(x, y, z)`` (float32
    arrays of one shape, at least 1-D) on a ``height`` x ``2 height`` panorama, as
    :func:`rasterizer.geometry.lat_lon_from_direction` and ``project_to_grid("erp")`` place them.

    OpenCV's vectorised ``cartToPolar`` and ``phase`` stand in for numpy's ``arctan2``, which took most of
    the score's time; their angles are within 2e-4 rad of it (0.02 px at 256 rows). The rest runs in place on
    the angle arrays."""
    import cv2

    shape = x.shape
    x, y, z = (np.ascontiguousarray(v, np.float32).reshape(-1, shape[-1]) for v in (x, y, z))
    horizontal, lon = cv2.cartToPolar(z, x)  # hypot(x, z) and atan2(x, z) in [0, 2 pi)
    lat = cv2.phase(horizontal, -y)  # atan2(-y, hypot) in [0, pi / 2] or [3 pi / 2, 2 pi)
    two_pi, pi = np.float32(2 * np.pi), np.float32(np.pi)
    lon -= two_pi * (lon >= pi)  # to [-pi, pi); a mask product, several times faster than np.where
    lat -= two_pi * (lat > pi)
    per_rad, half = np.float32(height / np.pi), np.float32(0.5)
    lon += pi
    lon *= per_rad
    lon -= half
    np.subtract(np.float32(np.pi / 2), lat, out=lat)
    lat *= per_rad
    lat -= half
    return lon.reshape(shape), lat.reshape(shape)
