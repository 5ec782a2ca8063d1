"""Phase (a) of rendering: project Gaussians (EWA) and list their pixel footprints.

:func:`project` turns world Gaussians into screen-space ellipses for one
:class:`~rasterizer.camera.Camera`: centre (col, row), 2-D covariance
``J Sigma J^T + 0.3 I`` with the camera's exact analytic Jacobian ``J`` (from
:mod:`rasterizer.geometry`; the Yang kernel's sign bug is not copied) and its
inverse, the conic.

:func:`footprints` enumerates, for every pixel, the Gaussians that can touch
it, in front-to-back order of Euclidean range, with the *opacity-free*
Gaussian weight ``g = exp(-0.5 d^T conic d)`` (d = pixel centre - projected
centre, pixels). The compositor then uses ``alpha = min(0.99, opacity * g)``.
Only contributions with ``g >= 1/255`` are kept (those are the ones that could
reach alpha >= 1/255 at opacity 1), so a caller that changes opacities later
(the +opt refinement) can reuse the footprints with fixed geometry. A caller
that knows the opacities will not grow may pass ``opacity_bound`` to cut each
footprint at ``g >= 1/(255 * bound)`` instead (smaller, faster; render does).

Culled before enumeration: range below ``camera.near`` (and z below it for a
pinhole), footprints entirely outside the image or a Yin/Yang grid's domain,
and pinhole Gaussians whose 3-D extent lies outside the view frustum (tested
in 3-D: beside the camera plane the EWA ellipse is meaningless and huge).
ERP columns wrap across the seam; a footprint wider than a full turn is
capped at one turn (no duplicate columns). Near the ERP poles the pixel-space
linearisation breaks down (1/cos lat changes across the footprint; at the
pole the column Jacobian is undefined), so "polar" Gaussians - those whose
footprint comes within two rows of a pole or spans more than a third of the
distance to it - are evaluated in the tangent plane of their own direction
instead: the pixel's ray is projected gnomonically onto that plane and
``q = t^T (P Sigma P^T / r^2 + low-pass)^-1 t`` with P the (east, south)
tangent basis. At the centre this is the same first-order EWA as the
pixel-space path (J_erp = diag(sx / cos lat, sy) P / r) except that the
low-pass is isotropic on the sphere (0.3 row pitches^2: near a pole a pixel
row is an annulus one pitch wide); away from the centre it follows the
sphere, so a pole Gaussian becomes a proper cap over all columns. Its cost
is bounded by its band of rows x W.

Implementation (vectorised, no loop over Gaussians or pixels): footprints
are bucketed into size classes, each class is a dense (n, KY, KX) block;
each surviving contribution is packed into one uint64 key
``pixel | depth rank | quantised q`` and a single sort orders all of
them by pixel, then by range. The blocks are laid out (KY, KX, n) with the
Gaussians ordered by (box origin, depth rank), so each box offset emits an
already sorted run of keys and that sort is a stable (timsort) merge of a
few hundred runs, 2-4x cheaper than sorting random keys.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera import Camera
from . import geometry as geo

#: Low-pass filter added to every 2-D covariance (px^2), as in 3DGS / ODGS.
LOW_PASS = 0.3
#: Smallest alpha that is composited.
ALPHA_MIN = 1.0 / 255.0
#: Mahalanobis radius^2 where an opacity-1 Gaussian falls to ALPHA_MIN: 2 ln 255.
Q_MAX = float(2.0 * np.log(255.0))

_SIZE_CLASSES = np.unique(np.concatenate([
    np.arange(1, 13), np.ceil(12 * 1.25 ** np.arange(1, 60)),
]).astype(np.int64))
#: Dense elements per block before a class is split into chunks.
_CHUNK_ELEMENTS = 1 << 22


class RenderLimitError(ValueError):
    """The footprints would need more memory than the caller allowed."""


@dataclass(frozen=True)
class Projected:
    """Screen-space ellipses of the Gaussians kept by :func:`project`.

    index (n,) int64 into the input Gaussians; mean (n, 2) float64 (col, row);
    cov (n, 3) float64 2-D covariance (xx, xy, yy) in px^2 including the
    low-pass; conic (n, 3) float64 its inverse (xx, xy, yy); ranges (n,)
    float64 Euclidean distance from the camera centre; p_cam (n, 3) float64
    camera-frame centres.
    """

    index: np.ndarray
    mean: np.ndarray
    cov: np.ndarray
    conic: np.ndarray
    ranges: np.ndarray
    p_cam: np.ndarray | None = None


@dataclass(frozen=True)
class Footprints:
    """Per-(pixel, Gaussian) contributions of one camera, front-to-back per pixel.

    ``pixel`` (M,) int32 flat index ``row * width + col``, ascending; within
    one pixel the entries are in increasing range of their Gaussian.
    ``gaussian`` (M,) int32 index into the Gaussians given to
    :func:`footprints`; ``weight`` (M,) float32 opacity-free Gaussian weight
    g in [1/255, 1]; ``ranges`` (N,) float32 range of every input Gaussian
    (0 for culled ones); ``height``, ``width``: the image size.
    """

    pixel: np.ndarray
    gaussian: np.ndarray
    weight: np.ndarray
    ranges: np.ndarray
    height: int
    width: int

    def __len__(self) -> int:
        return int(self.pixel.shape[0])


def gaussian_factors(gaussians) -> np.ndarray:
    """Camera-independent factor F = R(q) diag(s) of every covariance (Sigma = F F^T), (9, N) float64.

    Row ``3 * i + k`` holds F[i, k]. Elementwise from the (normalised)
    quaternions; a zero quaternion means the identity rotation.
    """
    q = np.asarray(gaussians.quats, dtype=np.float64)
    nrm = np.sqrt(np.einsum("ij,ij->i", q, q))
    ok = nrm > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, nrm, 1.0), 0.0)
    w = np.where(ok, q[:, 0] * inv, 1.0)
    x, y, z = q[:, 1] * inv, q[:, 2] * inv, q[:, 3] * inv
    s = np.asarray(gaussians.scales, dtype=np.float64)
    s0, s1, s2 = s[:, 0], s[:, 1], s[:, 2]
    out = np.empty((9, q.shape[0]))
    out[0] = (1 - 2 * (y * y + z * z)) * s0
    out[1] = 2 * (x * y - w * z) * s1
    out[2] = 2 * (x * z + w * y) * s2
    out[3] = 2 * (x * y + w * z) * s0
    out[4] = (1 - 2 * (x * x + z * z)) * s1
    out[5] = 2 * (y * z - w * x) * s2
    out[6] = 2 * (x * z - w * y) * s0
    out[7] = 2 * (y * z + w * x) * s1
    out[8] = (1 - 2 * (x * x + y * y)) * s2
    return out


def _covariance_2d(jac: np.ndarray, factors: np.ndarray, low_x=LOW_PASS, low_y=LOW_PASS):
    """2-D covariance entries (a, b, c) and det of ``J F F^T J^T + diag(low_x, low_y)``.

    Written elementwise on (n,) columns: T = J F is 2x3 and Sigma2D = T T^T;
    the determinant uses Cauchy-Binet (sum of squared 2x2 minors of T) so it
    is never negative, even for rank-deficient Gaussians.
    """
    t = [[None] * 3 for _ in range(2)]
    for i in range(2):
        j0, j1, j2 = (np.ascontiguousarray(jac[:, i, j]) for j in range(3))
        for k in range(3):
            t[i][k] = j0 * factors[k] + j1 * factors[3 + k] + j2 * factors[6 + k]
    a = t[0][0] ** 2 + t[0][1] ** 2 + t[0][2] ** 2
    b = t[0][0] * t[1][0] + t[0][1] * t[1][1] + t[0][2] * t[1][2]
    c = t[1][0] ** 2 + t[1][1] ** 2 + t[1][2] ** 2
    det0 = ((t[0][0] * t[1][1] - t[0][1] * t[1][0]) ** 2 + (t[0][0] * t[1][2] - t[0][2] * t[1][0]) ** 2
            + (t[0][1] * t[1][2] - t[0][2] * t[1][1]) ** 2)
    det = det0 + low_y * a + low_x * c + low_x * low_y
    return a + low_x, b, c + low_y, det


def _outside_domain(camera: Camera, p_cam: np.ndarray, ranges: np.ndarray, s_max: np.ndarray) -> np.ndarray:
    """(n,) bool: Yin/Yang Gaussians certainly outside the grid's angular domain.

    A lower bound on the angular distance of the centre to the domain is
    compared with a generous bound on the footprint's angular radius
    (1.5 asin(sqrt(Q_MAX) s_max / r) plus the low-pass and two pixels).
    """
    if camera.kind not in ("yin", "yang"):
        return np.zeros(p_cam.shape[0], dtype=bool)
    lat, lon = geo.lat_lon_from_direction(geo.to_grid_frame(camera.kind, p_cam))
    d_lat = np.abs(lat) - geo.YIN_LAT_MAX
    ex = np.clip(np.abs(lon) - geo.YIN_LON_MAX, 0.0, np.pi / 2)
    d_lon = np.arcsin(np.clip(np.cos(lat) * np.sin(ex), 0.0, 1.0))
    dist = np.maximum(d_lat, d_lon)
    with np.errstate(divide="ignore", invalid="ignore"):
        theta = np.arcsin(np.clip(np.sqrt(Q_MAX) * s_max / ranges, 0.0, 1.0))
    pitch = (2 * geo.YIN_LAT_MAX) / camera.height
    margin = (np.sqrt(Q_MAX * LOW_PASS) + 2.0) * pitch
    return dist > np.minimum(1.5 * theta, np.pi) + margin


def _outside_frustum(camera: Camera, p_cam: np.ndarray, s_max: np.ndarray) -> np.ndarray:
    """(n,) bool: pinhole Gaussians certainly outside the view frustum (3-D test, not EWA).

    Culled when the centre lies more than ``sqrt(Q_MAX) s_max`` (the 3-D
    radius where an opacity-1 Gaussian falls below 1/255) outside one of the
    four side planes through the image border widened by two pixels. Every
    ray through the image lies inside those planes, so it cannot meet such a
    Gaussian above 1/255. Why here and not from the EWA box: near the camera
    plane (z -> 0, large |x|/z) the linearised Jacobian explodes and the
    2-D ellipse of a centimetre-sized Gaussian 2 m away but 89 degrees off
    axis covers the image many times over (the RenderLimitError of an inside
    view); the true Gaussian never touches it.
    """
    if camera.kind != "perspective":
        return np.zeros(p_cam.shape[0], dtype=bool)
    fx, fy, cx, cy = geo.pinhole_intrinsics(camera.width, camera.height, camera.fov_deg)
    x, y, z = p_cam[:, 0], p_cam[:, 1], p_cam[:, 2]
    reach = np.sqrt(Q_MAX) * s_max
    out = np.zeros(p_cam.shape[0], dtype=bool)
    sides = ((x, fx, -2.5 - cx, camera.width + 1.5 - cx), (y, fy, -2.5 - cy, camera.height + 1.5 - cy))
    for coord, f, lo, hi in sides:
        tl, tr = lo / f, hi / f  # tangent of the widened left/top and right/bottom planes
        out |= (coord - tl * z) / np.sqrt(1.0 + tl * tl) < -reach
        out |= (tr * z - coord) / np.sqrt(1.0 + tr * tr) < -reach
    return out


def project(gaussians, camera: Camera, factors: np.ndarray | None = None, *,
            camera_points: tuple[np.ndarray, np.ndarray] | None = None) -> Projected:
    """EWA-project ``gaussians`` into ``camera``; culls those behind/too near.

    Returns a :class:`Projected` for the Gaussians that pass the near test,
    are not certainly outside a Yin/Yang domain, and whose projected centre
    and covariance are finite. Exact domain/image culling happens in
    :func:`footprints`, which knows the footprint extent. ``factors`` is
    :func:`gaussian_factors` of ``gaussians`` when the caller already has it;
    ``camera_points`` (camera-frame centres (N, 3), ranges (N,)) likewise, from
    ``camera.to_camera(gaussians.means)`` of a camera with the same pose.
    """
    if factors is None:
        factors = gaussian_factors(gaussians)
    if camera_points is None:
        p_cam = camera.to_camera(gaussians.means)
        ranges = np.sqrt(np.einsum("ij,ij->i", p_cam, p_cam))
    else:  # shared by cameras with the same pose (Yin and Yang of one render)
        p_cam, ranges = camera_points
    keep = ranges >= camera.near  # = camera.visible_depth(p_cam), without recomputing the ranges
    if camera.kind == "perspective":
        keep &= p_cam[:, 2] >= camera.near
    idx = np.flatnonzero(keep)
    if camera.kind in ("yin", "yang") and idx.size:
        s_max = np.max(gaussians.scales[idx], axis=1).astype(np.float64)
        idx = idx[~_outside_domain(camera, p_cam[idx], ranges[idx], s_max)]
    elif camera.kind == "perspective" and idx.size:
        s_max = np.max(gaussians.scales[idx], axis=1).astype(np.float64)
        idx = idx[~_outside_frustum(camera, p_cam[idx], s_max)]
    p_cam = p_cam[idx]
    col, row = camera.project(p_cam)
    jac = camera.jacobian(p_cam)
    with np.errstate(over="ignore", invalid="ignore"):
        a, b, c, det = _covariance_2d(jac, factors[:, idx])
        conic = np.stack([c / det, -b / det, a / det], axis=1)
    ok = np.isfinite(col) & np.isfinite(row) & np.isfinite(a) & np.isfinite(c) & np.isfinite(b)
    ok &= np.isfinite(conic).all(axis=1) & (det > 0)
    sel = np.flatnonzero(ok)
    return Projected(
        index=idx[sel],
        mean=np.stack([col[sel], row[sel]], axis=1),
        cov=np.stack([a[sel], b[sel], c[sel]], axis=1),
        conic=conic[sel],
        ranges=ranges[idx[sel]],
        p_cam=p_cam[sel],
    )


def _size_class(k: np.ndarray) -> np.ndarray:
    """Smallest size class >= k (k >= 1)."""
    pos = np.searchsorted(_SIZE_CLASSES, k)
    big = pos >= len(_SIZE_CLASSES)
    out = _SIZE_CLASSES[np.minimum(pos, len(_SIZE_CLASSES) - 1)]
    return np.where(big, k, out)


def _boxes(proj: Projected, camera: Camera, qcut: np.ndarray):
    """Integer pixel boxes (x0, kx, y0, ky) of the ellipses' bounding boxes.

    ``qcut`` (n,) is the Mahalanobis radius^2 of each footprint. Rows are
    clipped to the image; columns are clipped (pinhole) or capped at one
    period (wrapping grids). Empty boxes have kx or ky <= 0.
    """
    w, h = camera.width, camera.height
    cx, cy = proj.mean[:, 0], proj.mean[:, 1]
    rx = np.sqrt(qcut * proj.cov[:, 0])
    ry = np.sqrt(qcut * proj.cov[:, 2])
    # clamp huge extents before converting to integers
    lim_x = 4.0 * w + 4.0
    lim_y = 4.0 * h + 4.0
    x0 = np.ceil(np.clip(cx - rx, -lim_x, lim_x))
    x1 = np.floor(np.clip(cx + rx, -lim_x, lim_x))
    y0 = np.ceil(np.clip(cy - ry, -lim_y, lim_y))
    y1 = np.floor(np.clip(cy + ry, -lim_y, lim_y))
    y0 = np.maximum(y0, 0)
    y1 = np.minimum(y1, h - 1)
    period = camera.column_period
    if period is None:
        x0 = np.maximum(x0, 0)
        x1 = np.minimum(x1, w - 1)
    else:
        wide = (x1 - x0 + 1) > period
        x0 = np.where(wide, np.floor(cx) - period // 2 + 1, x0)
        x1 = np.where(wide, x0 + period - 1, x1)
        if camera.kind != "erp":
            # the box must meet the image columns [0, w) after wrapping
            s = camera.period_start
            lo = np.mod(x0 - s, period) + s  # wrapped start column
            kx = x1 - x0 + 1
            # columns lo .. lo + kx - 1 (mod period) meet [0, w) iff either piece does
            hits = (lo < w) | (lo + kx - 1 >= s + period)
            x1 = np.where(hits, x1, x0 - 1)
    return (x0.astype(np.int64), (x1 - x0 + 1).astype(np.int64),
            y0.astype(np.int64), (y1 - y0 + 1).astype(np.int64))


def _polar(proj: Projected, camera: Camera):
    """Split ERP Gaussians into (pixel-space, polar) index arrays into ``proj``."""
    n = proj.mean.shape[0]
    if camera.kind != "erp" or n == 0:
        return np.arange(n), np.zeros(0, dtype=np.int64)
    h = camera.height
    cy = proj.mean[:, 1]
    ry = np.sqrt(Q_MAX * proj.cov[:, 2])
    to_pole = np.minimum(cy + 0.5, h - 0.5 - cy)  # rows from the centre to the nearer pole
    polar = (to_pole - ry < 2.0) | (ry > to_pole / 3.0)
    return np.flatnonzero(~polar), np.flatnonzero(polar)


@dataclass(frozen=True)
class _Sphere:
    """Tangent-plane ellipses of polar ERP Gaussians (all float64, (n,))."""

    lat: np.ndarray
    lon: np.ndarray
    conic: np.ndarray  # (n, 3) inverse tangent covariance (tangent units = radians at the centre)
    theta: np.ndarray  # angular radius of the footprint (rad)


def _sphere_ellipses(proj: Projected, sel: np.ndarray, camera: Camera, factors_sel: np.ndarray) -> _Sphere:
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
    a, b, c, det = _covariance_2d(jac, factors_sel, low, low)
    conic = np.stack([c / det, -b / det, a / det], axis=1)
    lam = 0.5 * (a + c) + np.sqrt(np.maximum(0.25 * (a - c) ** 2 + b * b, 0.0))
    theta = np.arctan(np.sqrt(Q_MAX * lam))
    return _Sphere(lat, lon, conic, np.minimum(theta, np.radians(85.0)))


def _sphere_boxes(sph: _Sphere, camera: Camera):
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


def footprints(gaussians, camera: Camera, *, opacity_bound: np.ndarray | None = None,
               factors: np.ndarray | None = None, max_contributions: int = 60_000_000,
               camera_points: tuple[np.ndarray, np.ndarray] | None = None) -> Footprints:
    """Per-pixel, front-to-back lists of the Gaussians that can reach each pixel.

    Parameters
    ----------
    gaussians : Gaussians (N)
    camera : Camera
    opacity_bound : (N,) optional upper bound on each Gaussian's opacity; the
        footprint is then cut where ``bound * g < 1/255`` and Gaussians with
        bound < 1/255 are culled. Default: 1 (the opacity-free footprint,
        valid for any opacities in [0, 1]).
    factors : optional :func:`gaussian_factors` of ``gaussians`` (reuse it
        across cameras of one render).
    camera_points : optional (camera-frame centres, ranges) shared by cameras
        with the same pose (see :func:`project`).
    max_contributions : refuse (:class:`RenderLimitError`) when the estimated
        number of contributions exceeds this (last-resort memory guard, about
        20 bytes each; ordinary views up to 2048 wide stay far below it).

    Returns
    -------
    Footprints, sorted by pixel then range (see the class docstring).
    """
    n_all = len(gaussians)
    h, w = camera.height, camera.width
    proj = project(gaussians, camera, factors, camera_points=camera_points)
    ranges_all = np.zeros(n_all, dtype=np.float32)
    ranges_all[proj.index] = proj.ranges
    empty = Footprints(np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros(0, np.float32), ranges_all, h, w)
    if proj.index.size == 0:
        return empty

    if opacity_bound is None:
        qcut = np.full(proj.index.size, Q_MAX)
    else:
        bound = np.clip(np.asarray(opacity_bound, dtype=np.float64)[proj.index], 0.0, 1.0)
        qcut = np.where(bound >= ALPHA_MIN, 2.0 * np.log(np.maximum(bound, ALPHA_MIN) * 255.0), -1.0)
    # depth rank: front-to-back by Euclidean range (stable, so ties keep input order)
    order = np.argsort(proj.ranges, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)

    flat_idx, polar_idx = _polar(proj, camera)
    x0, kx, y0, ky = _boxes(proj, camera, np.maximum(qcut, 0.0))
    jobs = []  # (kind, indices into proj, x0, kx, y0, ky)
    live = flat_idx[(kx[flat_idx] > 0) & (ky[flat_idx] > 0) & (qcut[flat_idx] > 0)]
    # Order the pixel-space Gaussians by (box origin row y0, column x0, depth rank). For one fixed
    # box offset (oy, ox) the pixel of every in-image element is (y0 + oy) * w + x0 + ox, which
    # then increases along the Gaussians (two in-image columns differ by less than w),
    # so every offset of a size-class block yields an already sorted run of keys and the final
    # sort is a merge of a few hundred runs (a stable sort, i.e. timsort, merges them ~2-3x faster
    # than sorting at random). Gaussians whose columns wrap around the period break that order:
    # they form their own job.
    period = camera.column_period
    s0 = camera.period_start
    if period is not None and live.size:
        wraps = (x0[live] < s0) | (x0[live] + kx[live] - 1 >= s0 + period)
        wrap_live, live = live[wraps], live[~wraps]
    else:
        wrap_live = live[:0]
    if live.size:
        origin = y0[live] * (w + 2 * (period or 0) + 2) + x0[live]
        okey = (origin - origin.min()).astype(np.int64) * (order.size + 1) + rank[live]
        live = live[np.argsort(okey)]
    for sel in (live, wrap_live):
        if sel.size:
            jobs.append(("flat", sel, x0[sel], kx[sel], y0[sel], ky[sel]))
    sph = None
    if polar_idx.size:
        pf = factors if factors is not None else gaussian_factors(gaussians)
        sph = _sphere_ellipses(proj, polar_idx, camera, pf[:, proj.index[polar_idx]])
        sx0, skx, sy0, sky = _sphere_boxes(sph, camera)
        jobs.append(("sphere", polar_idx, sx0, skx, sy0, sky))
    est = _estimated_hits(proj, qcut, jobs)
    if est > max_contributions:
        raise RenderLimitError(
            f"footprints need about {est} contributions (> max_contributions={max_contributions}); "
            "reduce the image size or the number/size of Gaussians")

    # key layout, high to low bits: [pixel | depth rank | (unused) | q], q in the low 32 bits
    pix_bits = max(1, int(np.ceil(np.log2(h * w))))
    rank_bits = max(1, int(np.ceil(np.log2(order.size + 1))))
    q_bits = min(24, 64 - pix_bits - rank_bits)
    if q_bits < 12:
        raise RenderLimitError(f"image {w}x{h} with {order.size} Gaussians exceeds the 64-bit sort key")
    layout = _KeyLayout(pix_bits, rank_bits, q_bits, 64 - pix_bits - rank_bits)

    keys = []
    for kind, idx, jx0, jkx, jy0, jky in jobs:
        if idx.size == 0:
            continue
        kcx, kcy = _size_class(np.maximum(jkx, 1)), _size_class(np.maximum(jky, 1))
        cls = kcx * (1 << 20) + kcy
        grp_order = np.argsort(cls, kind="stable")
        cuts = np.flatnonzero(np.diff(cls[grp_order])) + 1
        for grp in np.split(grp_order, cuts):
            kxc, kyc = int(kcx[grp[0]]), int(kcy[grp[0]])
            step = max(1, _CHUNK_ELEMENTS // (kxc * kyc))
            for start in range(0, grp.size, step):
                part = grp[start:start + step]
                box = (jx0[part], jkx[part], jy0[part], jky[part])
                if kind == "flat":
                    sel = idx[part]
                    keys.append(_class_keys(sel, kxc, kyc, proj.mean, proj.conic, qcut, rank, box,
                                            h, w, period, s0, layout))
                else:
                    keys.append(_sphere_keys(part, idx[part], kxc, kyc, sph, qcut, rank, box, h, w, layout))
    if not keys:
        return empty
    key = np.concatenate(keys) if len(keys) > 1 else keys[0]
    del keys
    key.sort(kind="stable")  # timsort: merges the pre-sorted runs (keys are unique: order is the same)
    pixel = (key >> np.uint64(layout.pix_shift)).astype(np.int32)
    rnk = (key >> np.uint64(layout.rank_shift)) & np.uint64((1 << rank_bits) - 1)
    gauss = proj.index[order].astype(np.int32)[rnk.astype(np.intp)]
    del rnk
    low = key.view(np.uint32)[0::2] if key.dtype.byteorder in ("<", "=") and np.little_endian else None
    q = (low if low is not None else (key & np.uint64(0xFFFFFFFF)).astype(np.uint32)) & np.uint32((1 << q_bits) - 1)
    weight = np.exp(q.astype(np.float32) * np.float32(-0.5 / layout.q_scale))
    return Footprints(pixel, gauss, weight, ranges_all, h, w)


def _estimated_hits(proj: Projected, qcut: np.ndarray, jobs) -> int:
    """Upper estimate of the contributions (= memory) the jobs will produce.

    Pixel-space footprints: the ellipse area ``pi qcut sqrt(det)`` plus its
    bounding-box perimeter (pixels cut by the border), at most the clipped
    box; polar (sphere) jobs: their whole box. Counting dense, size-class
    rounded boxes instead over-counted thin or diagonal ellipses 2-4x and
    refused ordinary 2048-wide views near a wall.
    """
    total = 0
    for kind, idx, _, kx, _, ky in jobs:
        box = np.maximum(kx, 0).astype(np.float64) * np.maximum(ky, 0)
        if kind == "flat" and idx.size:
            a, b, c = proj.cov[idx, 0], proj.cov[idx, 1], proj.cov[idx, 2]
            q = np.maximum(qcut[idx], 0.0)
            ell = np.pi * q * np.sqrt(np.maximum(a * c - b * b, 0.0)) + 2 * np.sqrt(q) * (np.sqrt(a) + np.sqrt(c)) + 1
            box = np.minimum(box, ell)
        total += int(np.sum(box))
    return total


@dataclass(frozen=True)
class _KeyLayout:
    pix_bits: int
    rank_bits: int
    q_bits: int
    rank_shift: int

    @property
    def pix_shift(self) -> int:
        return self.rank_shift + self.rank_bits

    @property
    def q_scale(self) -> float:
        """q -> integer factor; q <= Q_MAX maps below 2^q_bits - 1 even after rounding."""
        return float((1 << self.q_bits) - 2) / Q_MAX


def _class_keys(sel, kxc, kyc, mean, conic, qcut, rank, box, h, w, period, s0,
                layout: _KeyLayout) -> np.ndarray:
    """Packed sort keys of one dense (kyc, kxc, n) block of pixel-space footprints.

    The Gaussian axis is innermost, so the keys come out offset by offset: each
    offset's keys are sorted when ``sel`` is ordered by (box origin, rank) and no
    column wraps (see :func:`footprints`).
    """
    x0, kx, y0, ky = box
    ox = np.arange(kxc, dtype=np.int64)[:, None]
    oy = np.arange(kyc, dtype=np.int64)[:, None]
    cols = x0[None, :] + ox  # (KX, n) unwrapped columns
    rows = y0[None, :] + oy  # (KY, n)
    dx = (x0 - mean[sel, 0]).astype(np.float32)[None, :] + ox.astype(np.float32)
    dy = (y0 - mean[sel, 1]).astype(np.float32)[None, :] + oy.astype(np.float32)
    if period is not None:
        cols = np.mod(cols - s0, period) + s0
    bad_x = (ox >= kx[None, :]) | (cols < 0) | (cols >= w)
    bad_y = (oy >= ky[None, :]) | (rows < 0) | (rows >= h)
    dx[bad_x] = np.inf
    dy[bad_y] = np.inf
    ca = conic[sel, 0].astype(np.float32)
    cb = (2.0 * conic[sel, 1]).astype(np.float32)
    cc = conic[sel, 2].astype(np.float32)
    with np.errstate(invalid="ignore", over="ignore"):
        q = (cb * dy)[:, None, :] * dx[None, :, :]
        q += (cc * dy * dy)[:, None, :]
        q += (ca * dx * dx)[None, :, :]
        hit = q <= qcut[sel].astype(np.float32)[None, None, :]
    rowkey = (np.where(bad_y, 0, rows) * w).astype(np.uint64) << np.uint64(layout.pix_shift)
    rowkey |= rank[sel].astype(np.uint64) << np.uint64(layout.rank_shift)
    colkey = np.where(bad_x, 0, cols).astype(np.uint64) << np.uint64(layout.pix_shift)
    out = (rowkey[:, None, :] + colkey[None, :, :])[hit]
    qh = q[hit]
    np.maximum(qh, 0.0, out=qh)
    qh *= np.float32(layout.q_scale)
    out |= qh.astype(np.uint32)
    return out


def _pack(rows, cols, bad_y, bad_x, rank_sel, q, hit, w, layout: _KeyLayout) -> np.ndarray:
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


def _sphere_keys(part, sel, kxc, kyc, sph: _Sphere, qcut, rank, box, h, w, layout: _KeyLayout) -> np.ndarray:
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
