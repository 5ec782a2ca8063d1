"""EWA projection and culling: world Gaussians -> screen-space ellipses of one camera.

:func:`project` turns world Gaussians into screen-space ellipses for one
:class:`~rasterizer.camera.Camera`: centre (col, row), 2-D covariance
``J Sigma J^T + 0.3 I`` with the camera's exact analytic Jacobian ``J`` (from
:mod:`rasterizer.geometry`; the Yang kernel's sign bug is not copied) and its
inverse, the conic. :func:`footprint_boxes` gives each ellipse's pixel box.

Culled here: range below ``camera.near`` (and z below it for a pinhole),
Gaussians certainly outside a Yin/Yang grid's domain (:func:`grid_keep`), and
pinhole Gaussians whose 3-D extent lies outside the view frustum (tested in
3-D: beside the camera plane the EWA ellipse is meaningless and huge).

Speed notes: depth ranks are over all N Gaussians of a pose (one sort shared
by the Yin and Yang cameras of a render, see :class:`SharedPose`); the Yin/Yang
domain cull needs no trigonometry beyond one arctan2/arcsin and runs before
any Jacobian; per-Gaussian maths (factors, projection, boxes) runs in
cache-sized chunks, because streaming dozens of temporaries of N float64
through memory cost several times the arithmetic. Results are the same as
computing everything at once.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np

from .. import geometry as geo
from ..camera import Camera

#: Low-pass filter added to every 2-D covariance (px^2), as in 3DGS / ODGS.
LOW_PASS = 0.3
#: Smallest alpha that is composited.
ALPHA_MIN = 1.0 / 255.0
#: A footprint cut short (:func:`sigma_cuts`) still reaches this far from its centre (px) along its narrowest
#: axis, so that a sub-pixel Gaussian's footprint, the pixel filter alone (sigma 0.55 px), is not cut at all:
#: at 1.5 px ERP thumbnails of a reconstruction (64-256 px wide) moved by 35-48 dB, at 2 px by none.
CUT_KEEPS_PX = 2.0
#: Mahalanobis radius^2 where an opacity-1 Gaussian falls to ALPHA_MIN: 2 ln 255.
Q_MAX = float(2.0 * np.log(255.0))
#: Gaussians per chunk of the per-Gaussian maths (factors, projection): its temporaries then
#: stay in the core's cache instead of streaming ~50 arrays of N float64 through memory.
_PROJECT_CHUNK = 16384
#: Dense elements per block before a class is split into chunks (cache-sized: more, shorter
#: sorted runs cost the final merge sort little, streaming big blocks through memory costs more).
_CHUNK_ELEMENTS = 1 << 17


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


def gaussian_factors(gaussians, index: np.ndarray | None = None) -> np.ndarray:
    """Camera-independent factor F = R(q) diag(s) of every covariance (Sigma = F F^T), (9, N) float64,
    or of the Gaussians ``index`` (n,) only, (9, n).

    Row ``3 * i + k`` holds F[i, k]. Elementwise from the (normalised)
    quaternions; a zero quaternion means the identity rotation. Computed in
    cache-sized chunks of Gaussians.
    """
    quats = np.asarray(gaussians.quats)
    scales = np.asarray(gaussians.scales)
    n = quats.shape[0] if index is None else index.size
    out = np.empty((9, n))
    for c0 in range(0, n, _PROJECT_CHUNK):
        c = slice(c0, c0 + _PROJECT_CHUNK)
        rows = c if index is None else index[c]
        for k, row in enumerate(_factor_rows(quats[rows], scales[rows])):
            out[k, c] = row
    return out


def _factor_rows(quats: np.ndarray, scales: np.ndarray) -> list:
    """The nine rows of :func:`gaussian_factors` for quaternions (n, 4) and scales (n, 3)."""
    q = np.asarray(quats, dtype=np.float64)
    nrm = np.sqrt(np.einsum("ij,ij->i", q, q))
    ok = nrm > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, nrm, 1.0), 0.0)
    w = np.where(ok, q[:, 0] * inv, 1.0)
    x, y, z = q[:, 1] * inv, q[:, 2] * inv, q[:, 3] * inv
    s = np.asarray(scales, dtype=np.float64)
    s0, s1, s2 = s[:, 0], s[:, 1], s[:, 2]
    return [(1 - 2 * (y * y + z * z)) * s0, 2 * (x * y - w * z) * s1, 2 * (x * z + w * y) * s2,
            2 * (x * y + w * z) * s0, (1 - 2 * (x * x + z * z)) * s1, 2 * (y * z - w * x) * s2,
            2 * (x * z - w * y) * s0, 2 * (y * z + w * x) * s1, (1 - 2 * (x * x + y * y)) * s2]


def covariance_2d(jac: np.ndarray, factors: np.ndarray, low_x=LOW_PASS, low_y=LOW_PASS):
    """2-D covariance entries (a, b, c) and det of ``J F F^T J^T + diag(low_x, low_y)``, J (n, 2, 3).

    See :func:`_covariance_rows` (the same with J given as rows of columns).
    """
    rows = [[np.ascontiguousarray(jac[:, i, j]) for j in range(3)] for i in range(2)]
    return _covariance_rows(rows[0], rows[1], factors, low_x, low_y)


@dataclass
class SharedPose:
    """Camera-frame data of all N Gaussians for one pose, shared by the cameras of that pose.

    x, y, z (N,) float64 contiguous camera-frame centres; ranges (N,) float64;
    s_max (N,) float64 largest scale; factors (9, N) :func:`gaussian_factors`
    (lazily; the Yin/Yang projection computes the rows it needs chunk by chunk
    when none were given); order (N,) the Gaussian of each front-to-back rank and rank (N,) its
    inverse (by range, ties in input order; by camera-frame z when ``depth_order``, as every 3DGS
    viewer sorts for a pinhole camera); grid_keep: per Yin/Yang camera, the indices of the
    Gaussians that pass the near and domain culls.
    """

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    ranges: np.ndarray
    s_max: np.ndarray
    gaussians: object
    factors_: np.ndarray | None = None
    order_: np.ndarray | None = None
    rank_: np.ndarray | None = None
    p_cam_: np.ndarray | None = None
    grid_keep: dict = field(default_factory=dict, repr=False)
    depth_order: bool = False
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    @property
    def factors(self) -> np.ndarray:
        if self.factors_ is None:
            self.factors_ = gaussian_factors(self.gaussians)
        return self.factors_

    @property
    def p_cam(self) -> np.ndarray:
        if self.p_cam_ is None:
            self.p_cam_ = np.stack([self.x, self.y, self.z], axis=1)
        return self.p_cam_

    def _depth_keys(self, index=slice(None)) -> np.ndarray:
        # keys >= 0: their float64 bit patterns sort like the values (and a stable sort of
        # integers is faster than of floats); ties keep the input order. z < 0 is culled anyway.
        key = np.maximum(self.z[index], 0.0) if self.depth_order else self.ranges[index]
        return key.view(np.int64)

    def _order_and_ranks(self, index=slice(None)) -> tuple[np.ndarray, np.ndarray]:
        """(order, rank) of the Gaussians ``index`` by depth, ties in input order: rank[order] = 0, 1, ..."""
        order = np.argsort(self._depth_keys(index), kind="stable")
        rank = np.empty_like(order)
        rank[order] = np.arange(order.size)
        return order, rank

    def _ranks(self) -> None:
        order, rank = self._order_and_ranks()
        self.rank_ = rank  # before order_: :attr:`rank` reads rank_ once order_ is set, without the lock
        self.order_ = order

    def ranks_among(self, index: np.ndarray) -> np.ndarray:
        """(n,) depth ranks of the Gaussians ``index`` (ascending indices) among themselves: the order
        of :attr:`rank` restricted to them (ties in input order), without sorting all N."""
        return self._order_and_ranks(index)[1]

    @property
    def order(self) -> np.ndarray:
        if self.order_ is None:
            with self.lock:  # threads of one render share it: computed once
                if self.order_ is None:
                    self._ranks()
        return self.order_

    @property
    def rank(self) -> np.ndarray:
        self.order
        return self.rank_


def shared_pose(gaussians, camera: Camera, factors: np.ndarray | None = None,
          camera_points: tuple[np.ndarray, np.ndarray] | None = None) -> SharedPose:
    """The :class:`SharedPose` of ``camera``'s pose (reuse it for other cameras with the same pose)."""
    scales = np.asarray(gaussians.scales)
    s_max = np.maximum(np.maximum(scales[:, 0], scales[:, 1]), scales[:, 2]).astype(np.float64)
    if camera_points is not None:  # shared by cameras with the same pose
        p_cam = np.asarray(camera_points[0], dtype=np.float64)
        ranges = np.asarray(camera_points[1], dtype=np.float64)
        cols = [np.ascontiguousarray(p_cam[:, k]) for k in range(3)]
        return SharedPose(cols[0], cols[1], cols[2], ranges, s_max, gaussians, factors_=factors, p_cam_=p_cam,
                          depth_order=camera.kind == "perspective")
    # camera.to_camera and the ranges, chunk by chunk, straight into contiguous columns
    pts = np.asarray(gaussians.means)
    n = pts.shape[0]
    xyz = np.empty((3, n))
    ranges = np.empty(n)
    rot, t = camera.c2w[:3, :3], camera.c2w[:3, 3]
    for c0 in range(0, n, _PROJECT_CHUNK):
        c = slice(c0, c0 + _PROJECT_CHUNK)
        p = np.asarray(pts[c], dtype=np.float64)
        d = [p[:, j] - t[j] for j in range(3)]
        pc = np.empty((p.shape[0], 3))
        for k in range(3):
            pc[:, k] = d[0] * rot[0, k] + d[1] * rot[1, k] + d[2] * rot[2, k]
        ranges[c] = np.sqrt(np.einsum("ij,ij->i", pc, pc))
        xyz[:, c] = pc.T
    return SharedPose(xyz[0], xyz[1], xyz[2], ranges, s_max, gaussians, factors_=factors,
                      depth_order=camera.kind == "perspective")


def _grid_frame(kind: str, x, y, z):
    """Grid-frame coordinates (x', y', z') of camera-frame columns: Yang uses M p = (y, x, -z)."""
    return (y, x, -z) if kind == "yang" else (x, y, z)


def grid_keep(pose: SharedPose, camera: Camera) -> np.ndarray:
    """Indices of the Gaussians a Yin/Yang camera keeps: near test and not certainly outside its domain.

    A lower bound on the angular distance of the centre to the domain,
    ``max(|lat| - pi/4, asin(cos(lat) sin(|lon| - 3pi/4)))`` (the second term
    written as ``-(|x'| + z') / (sqrt 2 r)`` in the grid frame, the same
    value without trigonometry), is compared with a generous bound on the
    footprint's angular radius (1.5 asin(sqrt(Q_MAX) s_max / r) plus the
    low-pass and two pixels). The domain bound is shared by the cameras of a
    pose; the pixel margin is the camera's.
    """
    kind = camera.kind
    key = (kind, camera.height, camera.near)
    if key in pose.grid_keep:
        return pose.grid_keep[key]
    pitch = (2 * geo.YIN_LAT_MAX) / camera.height
    margin = (np.sqrt(Q_MAX * LOW_PASS) + 2.0) * pitch
    n = pose.ranges.size
    keep = np.empty(n, dtype=bool)
    for c0 in range(0, n, _PROJECT_CHUNK):
        c = slice(c0, c0 + _PROJECT_CHUNK)
        r = pose.ranges[c]
        gx, gy, gz = _grid_frame(kind, pose.x[c], pose.y[c], pose.z[c])
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.sqrt(Q_MAX) * pose.s_max[c] / r
            np.clip(t, 0.0, 1.0, out=t)
            theta = np.minimum(1.5 * np.arcsin(t), np.pi)
            rho = np.sqrt(gx * gx + gz * gz)
            d_lat = np.abs(np.arctan2(-gy, rho)) - geo.YIN_LAT_MAX
            s = (np.abs(gx) + gz) * (-1.0 / np.sqrt(2.0)) / r
            np.clip(s, 0.0, 1.0, out=s)
            dist = np.maximum(d_lat, np.arcsin(s))
        k = r >= camera.near
        k &= ~(dist > theta + margin)
        keep[c] = k
    idx = np.flatnonzero(keep)
    pose.grid_keep[key] = idx
    return idx


@dataclass
class Columns:
    """Screen-space ellipses as contiguous (n,) float64 columns (what :class:`Projected` stacks)."""

    index: np.ndarray
    mx: np.ndarray
    my: np.ndarray
    cov_a: np.ndarray
    cov_b: np.ndarray
    cov_c: np.ndarray
    con_a: np.ndarray
    con_b: np.ndarray
    con_c: np.ndarray
    ranges: np.ndarray
    pose: SharedPose | None = None
    p_cam_: np.ndarray | None = None

    @property
    def p_cam(self) -> np.ndarray:
        if self.p_cam_ is None:
            self.p_cam_ = np.stack([self.pose.x[self.index], self.pose.y[self.index], self.pose.z[self.index]],
                                   axis=1)
        return self.p_cam_

    def subset(self, sel: np.ndarray) -> "Columns":
        p = None if self.p_cam_ is None else self.p_cam_[sel]
        return Columns(*(getattr(self, f)[sel] for f in ("index", "mx", "my", "cov_a", "cov_b", "cov_c", "con_a",
                                                       "con_b", "con_c", "ranges")), pose=self.pose, p_cam_=p)

    def projected(self) -> Projected:
        return Projected(index=self.index, mean=np.stack([self.mx, self.my], axis=1),
                         cov=np.stack([self.cov_a, self.cov_b, self.cov_c], axis=1),
                         conic=np.stack([self.con_a, self.con_b, self.con_c], axis=1),
                         ranges=self.ranges, p_cam=self.p_cam)


def _finish(idx, col, row, a, b, c, det, ranges, pose, p_cam=None) -> Columns:
    """Conics of the 2-D covariances; drops non-finite projections and det <= 0."""
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        ka, kb, kc = c / det, -b / det, a / det
    ok = np.isfinite(col) & np.isfinite(row) & np.isfinite(a) & np.isfinite(c) & np.isfinite(b)
    ok &= np.isfinite(ka) & np.isfinite(kb) & np.isfinite(kc) & (det > 0)
    cols = Columns(idx, col, row, a, b, c, ka, kb, kc, ranges, pose, p_cam)
    return cols if ok.all() else cols.subset(np.flatnonzero(ok))


def _project_grid(pose: SharedPose, camera: Camera) -> Columns:
    """Yin/Yang EWA projection: lat/lon and the analytic Jacobian from one set of grid-frame columns.

    Same maths as ``camera.project`` / ``camera.jacobian`` (geometry.project_to_grid,
    grid_jacobian, times R_cw), written once on contiguous columns of the kept Gaussians,
    chunk by chunk (see ``_PROJECT_CHUNK``).
    """
    idx = grid_keep(pose, camera)
    kind, h, w = camera.kind, camera.height, camera.width
    n = idx.size
    out = np.empty((6, n))
    col, row, a, b, c, det = out
    rcw = camera.world_to_camera_rotation
    # world-frame Jacobian rows: J_grid (grid frame) times Rg = M R_cw (rows of R_cw permuted for Yang)
    rg = rcw[[1, 0, 2]] * np.array([[1.0], [1.0], [-1.0]]) if kind == "yang" else rcw
    sx, sy = w / (2 * geo.YIN_LON_MAX), h / (2 * geo.YIN_LAT_MAX)
    factors = pose.factors_  # None: computed per chunk, only for the kept Gaussians
    quats, scales = np.asarray(pose.gaussians.quats), np.asarray(pose.gaussians.scales)
    px, py, pz = pose.x, pose.y, pose.z
    for s0 in range(0, n, _PROJECT_CHUNK):
        s = slice(s0, s0 + _PROJECT_CHUNK)
        ii = idx[s]
        gx, gy, gz = _grid_frame(kind, px[ii], py[ii], pz[ii])
        rho2 = gx * gx + gz * gz
        lat = np.arctan2(-gy, np.sqrt(rho2))
        lon = np.arctan2(gx, gz)
        col[s] = (lon + geo.YIN_LON_MAX) / (2 * geo.YIN_LON_MAX) * w - 0.5
        row[s] = (geo.YIN_LAT_MAX - lat) / (2 * geo.YIN_LAT_MAX) * h - 0.5
        pole = rho2 < geo.EPS
        if pole.any():  # on the grid's pole axis: linearised at the floor's distance from it, toward ``lon``
            gx = np.where(pole, np.sqrt(geo.EPS) * np.sin(lon), gx)
            gz = np.where(pole, np.sqrt(geo.EPS) * np.cos(lon), gz)
        np.maximum(rho2, geo.EPS, out=rho2)
        rho = np.sqrt(rho2)
        r2 = np.maximum(rho2 + gy * gy, geo.EPS)
        u = sx / rho2
        v = sy / (rho * r2)
        uz, ux = u * gz, u * gx
        vxy, vr, vzy = v * gx * gy, v * rho2, v * gz * gy
        j0 = [uz * rg[0, k] - ux * rg[2, k] for k in range(3)]
        j1 = [vr * rg[1, k] - vxy * rg[0, k] - vzy * rg[2, k] for k in range(3)]
        if factors is None:  # straight from the quaternions of this chunk
            f = _factor_rows(quats[ii], scales[ii])
        else:
            f = [factors[k][ii] for k in range(9)]
        with np.errstate(over="ignore", invalid="ignore"):
            a[s], b[s], c[s], det[s] = _covariance_rows(j0, j1, f)
    return _finish(idx, col, row, a, b, c, det, pose.ranges[idx], pose)


def _covariance_rows(j0, j1, factors, low_x=LOW_PASS, low_y=LOW_PASS):
    """2-D covariance (a, b, c) and det of ``J F F^T J^T + diag(low_x, low_y)``, J as two rows of three (n,) columns.

    Elementwise: T = J F is 2x3 and Sigma2D = T T^T; the determinant uses
    Cauchy-Binet (sum of squared 2x2 minors of T) so it is never negative,
    even for rank-deficient Gaussians.
    """
    t = [[None] * 3 for _ in range(2)]
    for i, (a0, a1, a2) in enumerate((j0, j1)):
        for k in range(3):
            t[i][k] = a0 * factors[k] + a1 * factors[3 + k] + a2 * factors[6 + k]
    a = t[0][0] * t[0][0] + t[0][1] * t[0][1] + t[0][2] * t[0][2]
    b = t[0][0] * t[1][0] + t[0][1] * t[1][1] + t[0][2] * t[1][2]
    c = t[1][0] * t[1][0] + t[1][1] * t[1][1] + t[1][2] * t[1][2]
    m0 = t[0][0] * t[1][1] - t[0][1] * t[1][0]
    m1 = t[0][0] * t[1][2] - t[0][2] * t[1][0]
    m2 = t[0][1] * t[1][2] - t[0][2] * t[1][1]
    det = m0 * m0 + m1 * m1 + m2 * m2 + low_y * a + low_x * c + low_x * low_y
    return a + low_x, b, c + low_y, det


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


def project_columns(pose: SharedPose, camera: Camera) -> Columns:
    """EWA projection of the pose's Gaussians into ``camera`` as columns (see :func:`project`)."""
    if camera.kind in ("yin", "yang"):
        return _project_grid(pose, camera)
    ranges = pose.ranges
    keep = ranges >= camera.near  # the near cull on range (and z below for pinhole cameras)
    if camera.kind == "perspective":
        keep &= pose.z >= camera.near
    idx = np.flatnonzero(keep)
    if camera.kind == "perspective":  # the camera-frame centres and factors of the Gaussians in view only
        p_cam = np.stack([pose.x[idx], pose.y[idx], pose.z[idx]], axis=1)
        if idx.size:
            inside = ~_outside_frustum(camera, p_cam, pose.s_max[idx])
            idx, p_cam = idx[inside], p_cam[inside]
        factors = pose.factors_[:, idx] if pose.factors_ is not None else gaussian_factors(pose.gaussians, idx)
    else:
        p_cam = pose.p_cam[idx]
        factors = pose.factors[:, idx]
    col, row = camera.project(p_cam)
    jac = camera.jacobian(p_cam)
    with np.errstate(over="ignore", invalid="ignore"):
        a, b, c, det = covariance_2d(jac, factors)
    return _finish(idx, col, row, a, b, c, det, ranges[idx], pose, p_cam)


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
    return project_columns(shared_pose(gaussians, camera, factors, camera_points), camera).projected()


def footprint_boxes(mx, my, cov_a, cov_c, camera: Camera, qcut: np.ndarray):
    """Integer pixel boxes (x0, kx, y0, ky) of the ellipses' bounding boxes.

    ``qcut`` (n,) is the Mahalanobis radius^2 of each footprint. Rows are
    clipped to the image; columns are clipped (pinhole) or capped at one
    period (wrapping grids). Empty boxes have kx or ky <= 0. Computed in
    cache-sized chunks.
    """
    n = mx.shape[0]
    out = np.empty((4, n), dtype=np.int64)
    for c0 in range(0, n, _PROJECT_CHUNK):
        c = slice(c0, c0 + _PROJECT_CHUNK)
        out[:, c] = _boxes_chunk(mx[c], my[c], cov_a[c], cov_c[c], camera, qcut[c])
    return out[0], out[1], out[2], out[3]


def _boxes_chunk(cx, cy, cov_a, cov_c, camera: Camera, qcut: np.ndarray):
    w, h = camera.width, camera.height
    rx = np.sqrt(qcut * cov_a)
    ry = np.sqrt(qcut * cov_c)
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
        if wide.any():
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
    return x0, x1 - x0 + 1, y0, y1 - y0 + 1


def opacity_cuts(opacity_bound, n: int) -> np.ndarray | None:
    """Mahalanobis radius^2 of every footprint, (N,) float64; None: Q_MAX for all."""
    if opacity_bound is None:
        return None
    bound = np.clip(np.asarray(opacity_bound, dtype=np.float64), 0.0, 1.0)
    return np.where(bound >= ALPHA_MIN, 2.0 * np.log(np.maximum(bound, ALPHA_MIN) * 255.0), -1.0)


def sigma_cuts(cov_a: np.ndarray, cov_b: np.ndarray, cov_c: np.ndarray, cut_sigma: float) -> np.ndarray:
    """(n,) Mahalanobis radius^2 at which footprints of 2-D covariance (a, b; b, c) px^2 are cut short.

    ``cut_sigma`` standard deviations, but never nearer the centre than :data:`CUT_KEEPS_PX` along the
    footprint's narrowest axis: a sub-pixel Gaussian's footprint is mostly the pixel filter
    (:data:`LOW_PASS`), and its tail is what reaches the neighbouring pixel centres that share its coverage.
    """
    q = min(float(cut_sigma), float(np.sqrt(Q_MAX))) ** 2
    lam_min = 0.5 * (cov_a + cov_c) - np.sqrt((0.5 * (cov_a - cov_c)) ** 2 + cov_b ** 2)
    return np.maximum(q, CUT_KEEPS_PX ** 2 / np.maximum(lam_min, LOW_PASS))
