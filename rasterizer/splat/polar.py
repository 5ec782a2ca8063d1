"""Polar ERP footprints: Gaussians near a pole evaluated in their own tangent plane.

Near the ERP poles the pixel-space linearisation breaks down (1/cos lat
changes across the footprint; at the pole the column Jacobian is undefined),
so "polar" Gaussians - those whose footprint comes within two rows of a pole
or spans more than a third of the distance to it (:func:`polar_split`) - are
evaluated in the tangent plane of their own direction instead: the pixel's
ray is projected gnomonically onto that plane and
``q = t^T (P Sigma P^T / r^2 + low-pass)^-1 t`` with P the (east, south)
tangent basis. At the centre this is the same first-order EWA as the
pixel-space path (J_erp = diag(sx / cos lat, sy) P / r) except that the
low-pass is isotropic on the sphere (0.3 row pitches^2: near a pole a pixel
row is an annulus one pitch wide); away from the centre it follows the
sphere, so a pole Gaussian becomes a proper cap over all columns. Its cost
is bounded by its band of rows x W.

The gnomonic projection reaches only the hemisphere around the Gaussian's
direction: a footprint wider than that (a camera inside or beside a Gaussian
of its own size) is drawn within it alone, and "direct" ERP renders of such a
scene miss the rest. The Yin-Yang ERP, which the service renders, splats on
two pinhole-like grids and draws all of it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import geometry as geo
from ..camera import Camera
from .blocks import KeyLayout
from .projection import LOW_PASS, Q_MAX, Projected, covariance_2d


def polar_split(my: np.ndarray, cov_c: np.ndarray, camera: Camera):
    """(pixel-space, polar) index arrays: ERP Gaussians whose footprint nears a pole go to the sphere path."""
    n = my.shape[0]
    if camera.kind != "erp" or n == 0:
        return np.arange(n), np.zeros(0, dtype=np.int64)
    h = camera.height
    ry = np.sqrt(Q_MAX * cov_c)
    to_pole = np.minimum(my + 0.5, h - 0.5 - my)  # rows from the centre to the nearer pole
    polar = (to_pole - ry < 2.0) | (ry > to_pole / 3.0)
    return np.flatnonzero(~polar), np.flatnonzero(polar)


def polar_rows(proj: Projected, camera: Camera):
    """Split ERP Gaussians into (pixel-space, polar) index arrays into ``proj``."""
    return polar_split(proj.mean[:, 1], proj.cov[:, 2], camera)


@dataclass(frozen=True)
class _Sphere:
    """Tangent-plane ellipses of polar ERP Gaussians (all float64, (n,))."""

    lat: np.ndarray
    lon: np.ndarray
    conic: np.ndarray  # (n, 3) inverse tangent covariance (tangent units = radians at the centre)
    theta: np.ndarray  # angular radius of the footprint (rad)


def sphere_ellipses(proj: Projected, sel: np.ndarray, camera: Camera, factors_sel: np.ndarray) -> _Sphere:
    p = proj.p_cam[sel]
    r = proj.ranges[sel]
    lat, lon = geo.lat_lon_from_direction(p)
    cl, sl, co, so = np.cos(lat), np.sin(lat), np.cos(lon), np.sin(lon)
    zero = np.zeros_like(lat)
    h = camera.height
    east = np.stack([co, zero, -so], axis=1) / r[:, None]
    south = np.stack([sl * so, cl, sl * co], axis=1) / r[:, None]
    jac = camera.jacobian_from_camera(np.stack([east, south], axis=1))
    # isotropic low-pass of 0.3 row pitches^2: near a pole a pixel row is an annulus one pitch wide
    low = LOW_PASS * (np.pi / h) ** 2
    a, b, c, det = covariance_2d(jac, factors_sel, low, low)
    conic = np.stack([c / det, -b / det, a / det], axis=1)
    lam = 0.5 * (a + c) + np.sqrt(np.maximum(0.25 * (a - c) ** 2 + b * b, 0.0))
    theta = np.arctan(np.sqrt(Q_MAX * lam))
    return _Sphere(lat, lon, conic, np.minimum(theta, np.radians(85.0)))


def sphere_boxes(sph: _Sphere, camera: Camera):
    """Row/column boxes (x0, kx, y0, ky) covering each polar footprint cap."""
    h, w = camera.height, camera.width
    top = sph.lat + sph.theta
    bottom = sph.lat - sph.theta
    row0 = np.clip(np.floor((np.pi / 2 - np.minimum(top, np.pi / 2)) / np.pi * h - 0.5), 0, h - 1)
    row1 = np.clip(np.ceil((np.pi / 2 - np.maximum(bottom, -np.pi / 2)) / np.pi * h - 0.5), 0, h - 1)
    over_pole = (top >= np.pi / 2) | (bottom <= -np.pi / 2)
    ratio = np.sin(sph.theta) / np.maximum(np.cos(sph.lat), 1e-12)
    half = np.where(over_pole | (ratio >= 1), np.pi, np.arcsin(np.minimum(ratio, 1.0)))
    cx = (sph.lon + np.pi) / (2 * np.pi) * w - 0.5
    rx = half / (2 * np.pi) * w + 1.0
    x0 = np.floor(cx - rx)
    kx = np.minimum(np.ceil(cx + rx) - x0 + 1, w)
    x0 = np.where(kx >= w, 0, x0)
    return x0.astype(np.int64), kx.astype(np.int64), row0.astype(np.int64), (row1 - row0 + 1).astype(np.int64)


def _pack(rows, cols, bad_y, bad_x, rank_sel, q, hit, w, layout: KeyLayout) -> np.ndarray:
    """Keys of the hit elements of a dense (n, KY, KX) block."""
    rowkey = (np.where(bad_y, 0, rows) * w).astype(np.uint64) << np.uint64(layout.pix_shift)
    rowkey |= (rank_sel.astype(np.uint64) << np.uint64(layout.rank_shift))[:, None]
    colkey = np.where(bad_x, 0, cols).astype(np.uint64) << np.uint64(layout.pix_shift)
    out = (rowkey[:, :, None] + colkey[:, None, :])[hit]
    qh = q[hit]
    np.maximum(qh, 0.0, out=qh)
    qh *= np.float32(layout.q_scale)
    out |= qh.astype(np.uint32)
    return out


def sphere_keys(part, sel, kxc, kyc, sph: _Sphere, qcut, rank, box, h, w, layout: KeyLayout) -> np.ndarray:
    """Keys of polar ERP footprints: gnomonic tangent-plane offsets of every pixel ray.

    For pixel (lat_r, lon_c) and centre (lat_u, lon_u), with dl = lon_c - lon_u:
    D = cos(lat_r) cos(lat_u) cos(dl) + sin(lat_r) sin(lat_u) (cosine of the angle),
    t_east = cos(lat_r) sin(dl) / D, t_south = (cos(lat_r) sin(lat_u) cos(dl) - sin(lat_r) cos(lat_u)) / D.
    Pixels with D <= 0.05 (more than ~87 degrees away) are skipped.
    """
    x0, kx, y0, ky = box
    ox = np.arange(kxc, dtype=np.int64)
    oy = np.arange(kyc, dtype=np.int64)
    cols = x0[:, None] + ox
    rows = y0[:, None] + oy
    bad_x = ox >= kx[:, None]
    bad_y = (oy >= ky[:, None]) | (rows >= h)
    cols = np.mod(cols, w)
    lon_c = (cols + 0.5) / w * 2 * np.pi - np.pi
    lat_r = np.pi / 2 - (np.minimum(rows, h - 1) + 0.5) / h * np.pi
    lat_u, lon_u = sph.lat[part][:, None], sph.lon[part][:, None]
    dl = lon_c - lon_u
    sd, cd = np.sin(dl)[:, None, :], np.cos(dl)[:, None, :]
    cr, sr = np.cos(lat_r)[:, :, None], np.sin(lat_r)[:, :, None]
    cu, su = np.cos(lat_u)[:, :, None], np.sin(lat_u)[:, :, None]
    den = cr * cu * cd + sr * su
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        te = cr * sd / den
        ts = (cr * su * cd - sr * cu) / den
        cn = sph.conic[part]
        q = cn[:, 0, None, None] * te * te + 2 * cn[:, 1, None, None] * te * ts + cn[:, 2, None, None] * ts * ts
        q = q.astype(np.float32)
        hit = (den > 0.05) & (q <= qcut[sel].astype(np.float32)[:, None, None])
        hit &= ~bad_y[:, :, None] & ~bad_x[:, None, :]
    return _pack(rows, cols, bad_y, bad_x, rank[sel], q, hit, w, layout)
