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

Speed notes: depth ranks are over all N Gaussians of a pose (one sort shared
by the Yin and Yang cameras of a render, see :class:`SharedPose`); the Yin/Yang
domain cull needs no trigonometry beyond one arctan2/arcsin and runs before
any Jacobian; per-Gaussian maths (factors, projection, boxes) and the dense
key blocks run in cache-sized chunks, because streaming dozens of
temporaries of N float64 through memory cost several times the arithmetic.
Results are the same as computing everything at once.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np

from . import geometry as geo
from .camera import Camera

#: Default memory guard of :func:`footprints`: refuse renders estimated above this many (Gaussian, pixel)
#: contributions. 120M (was 60M) since the environment shell (rasterizer.shell) added large backdrop discs:
#: a zind scene's direct 1024x512 ERP render estimates ~86M and peaks at ~3.0 GB RSS (1.4 GB without it).
MAX_CONTRIBUTIONS = 120_000_000

#: Low-pass filter added to every 2-D covariance (px^2), as in 3DGS / ODGS.
LOW_PASS = 0.3
#: Smallest alpha that is composited.
ALPHA_MIN = 1.0 / 255.0
#: Mahalanobis radius^2 where an opacity-1 Gaussian falls to ALPHA_MIN: 2 ln 255.
Q_MAX = float(2.0 * np.log(255.0))

_SIZE_CLASSES = np.unique(np.concatenate([
    np.arange(1, 13), np.ceil(12 * 1.25 ** np.arange(1, 60)),
]).astype(np.int64))
#: Gaussians per chunk of the per-Gaussian maths (factors, projection): its temporaries then
#: stay in the core's cache instead of streaming ~50 arrays of N float64 through memory.
_PROJECT_CHUNK = 16384
#: Dense elements per block before a class is split into chunks (cache-sized: more, shorter
#: sorted runs cost the final merge sort little, streaming big blocks through memory costs more).
_CHUNK_ELEMENTS = 1 << 17


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
    quaternions; a zero quaternion means the identity rotation. Computed in
    cache-sized chunks of Gaussians.
    """
    quats = np.asarray(gaussians.quats)
    scales = np.asarray(gaussians.scales)
    n = quats.shape[0]
    out = np.empty((9, n))
    for c0 in range(0, n, _PROJECT_CHUNK):
        c = slice(c0, c0 + _PROJECT_CHUNK)
        for k, row in enumerate(_factor_rows(quats[c], scales[c])):
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


def _covariance_2d(jac: np.ndarray, factors: np.ndarray, low_x=LOW_PASS, low_y=LOW_PASS):
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

    def _ranks(self) -> None:
        # keys >= 0: their float64 bit patterns sort like the values (and a stable sort of
        # integers is faster than of floats); ties keep the input order. z < 0 is culled anyway.
        key = np.maximum(self.z, 0.0) if self.depth_order else self.ranges
        order = np.argsort(key.view(np.int64), kind="stable")
        rank = np.empty_like(order)
        rank[order] = np.arange(order.size)
        self.rank_ = rank
        self.order_ = order

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
class _Cols:
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

    def subset(self, sel: np.ndarray) -> "_Cols":
        p = None if self.p_cam_ is None else self.p_cam_[sel]
        return _Cols(*(getattr(self, f)[sel] for f in ("index", "mx", "my", "cov_a", "cov_b", "cov_c", "con_a",
                                                       "con_b", "con_c", "ranges")), pose=self.pose, p_cam_=p)

    def projected(self) -> Projected:
        return Projected(index=self.index, mean=np.stack([self.mx, self.my], axis=1),
                         cov=np.stack([self.cov_a, self.cov_b, self.cov_c], axis=1),
                         conic=np.stack([self.con_a, self.con_b, self.con_c], axis=1),
                         ranges=self.ranges, p_cam=self.p_cam)


def _finish(idx, col, row, a, b, c, det, ranges, pose, p_cam=None) -> _Cols:
    """Conics of the 2-D covariances; drops non-finite projections and det <= 0."""
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        ka, kb, kc = c / det, -b / det, a / det
    ok = np.isfinite(col) & np.isfinite(row) & np.isfinite(a) & np.isfinite(c) & np.isfinite(b)
    ok &= np.isfinite(ka) & np.isfinite(kb) & np.isfinite(kc) & (det > 0)
    cols = _Cols(idx, col, row, a, b, c, ka, kb, kc, ranges, pose, p_cam)
    return cols if ok.all() else cols.subset(np.flatnonzero(ok))


def _project_grid(pose: SharedPose, camera: Camera) -> _Cols:
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
        np.maximum(rho2, geo._EPS, out=rho2)
        rho = np.sqrt(rho2)
        r2 = np.maximum(rho2 + gy * gy, geo._EPS)
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


def _project_cols(pose: SharedPose, camera: Camera) -> _Cols:
    """EWA projection of the pose's Gaussians into ``camera`` as columns (see :func:`project`)."""
    if camera.kind in ("yin", "yang"):
        return _project_grid(pose, camera)
    ranges = pose.ranges
    keep = ranges >= camera.near  # the near cull on range (and z below for pinhole cameras)
    if camera.kind == "perspective":
        keep &= pose.z >= camera.near
    idx = np.flatnonzero(keep)
    p_cam = pose.p_cam
    if camera.kind == "perspective" and idx.size:
        idx = idx[~_outside_frustum(camera, p_cam[idx], pose.s_max[idx])]
    p_cam = p_cam[idx]
    col, row = camera.project(p_cam)
    jac = camera.jacobian(p_cam)
    with np.errstate(over="ignore", invalid="ignore"):
        a, b, c, det = _covariance_2d(jac, pose.factors[:, idx])
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
    return _project_cols(shared_pose(gaussians, camera, factors, camera_points), camera).projected()


def _size_class(k: np.ndarray) -> np.ndarray:
    """Smallest size class >= k (k >= 1)."""
    pos = np.searchsorted(_SIZE_CLASSES, k)
    big = pos >= len(_SIZE_CLASSES)
    out = _SIZE_CLASSES[np.minimum(pos, len(_SIZE_CLASSES) - 1)]
    return np.where(big, k, out)


def _boxes(mx, my, cov_a, cov_c, camera: Camera, qcut: np.ndarray):
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


def _polar_split(my: np.ndarray, cov_c: np.ndarray, camera: Camera):
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
    return _polar_split(proj.mean[:, 1], proj.cov[:, 2], camera)


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


def opacity_cuts(opacity_bound, n: int) -> np.ndarray | None:
    """Mahalanobis radius^2 of every footprint, (N,) float64; None: Q_MAX for all."""
    if opacity_bound is None:
        return None
    bound = np.clip(np.asarray(opacity_bound, dtype=np.float64), 0.0, 1.0)
    return np.where(bound >= ALPHA_MIN, 2.0 * np.log(np.maximum(bound, ALPHA_MIN) * 255.0), -1.0)


def footprints(gaussians, camera: Camera, *, opacity_bound: np.ndarray | None = None,
               factors: np.ndarray | None = None, max_contributions: int = MAX_CONTRIBUTIONS,
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
    pose = shared_pose(gaussians, camera, factors, camera_points)
    key, layout, cols, _ = sorted_keys(pose, camera, opacity_cuts(opacity_bound, n_all), max_contributions)
    return _unpack_keys(key, layout, cols, pose, camera)


def _unpack_keys(key, layout, cols: _Cols, pose: SharedPose, camera: Camera) -> Footprints:
    """:class:`Footprints` of sorted keys (see :func:`sorted_keys`)."""
    n_all = pose.ranges.size
    ranges_all = np.zeros(n_all, dtype=np.float32)
    ranges_all[cols.index] = cols.ranges
    h, w = camera.height, camera.width
    if key is None:
        return Footprints(np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros(0, np.float32), ranges_all, h, w)
    pixel = layout.pixels(key).astype(np.int32)
    gauss = pose.order.astype(np.int32)[layout.ranks(key)]
    weight = layout.weights(key)
    return Footprints(pixel, gauss, weight, ranges_all, h, w)


def sorted_keys(pose: SharedPose, camera: Camera, qcut_all: np.ndarray | None, max_contributions: int):
    """(keys, layout, columns, job_ranks): the sorted uint64 keys ``pixel | rank | q`` of one camera.

    keys is None when nothing is visible. Ranks are the pose's (all N Gaussians).
    job_ranks: the ranks of the Gaussians in the order their keys were built
    (by size class, then box origin), a spatially coherent order for tables
    indexed per contribution; None when some keys came from elsewhere (polar
    ERP footprints).
    """
    h, w = camera.height, camera.width
    cols = _project_cols(pose, camera)
    n = cols.index.size
    if n == 0:
        return None, None, cols, None
    qcut = np.full(n, Q_MAX) if qcut_all is None else qcut_all[cols.index]
    n_all = pose.ranges.size
    rank = pose.rank[cols.index]

    flat_idx, polar_idx = _polar_split(cols.my, cols.cov_c, camera)
    x0, kx, y0, ky = _boxes(cols.mx, cols.my, cols.cov_a, cols.cov_c, camera, np.maximum(qcut, 0.0))
    ok = (kx > 0) & (ky > 0) & (qcut > 0)
    live = flat_idx[ok[flat_idx]] if polar_idx.size else np.flatnonzero(ok)
    period = camera.column_period
    s0 = camera.period_start

    # key layout, high to low bits: [pixel | depth rank | (unused) | q], q in the low 32 bits
    pix_bits = max(1, int(np.ceil(np.log2(h * w))))
    rank_bits = max(1, int(np.ceil(np.log2(n_all + 1))))
    q_bits = min(24, 64 - pix_bits - rank_bits)
    if q_bits < 12:
        raise RenderLimitError(f"image {w}x{h} with {n_all} Gaussians exceeds the 64-bit sort key")
    layout = _KeyLayout(pix_bits, rank_bits, q_bits, 64 - pix_bits - rank_bits)

    sph = None
    if polar_idx.size:
        sph = _sphere_ellipses(cols, polar_idx, camera, pose.factors[:, cols.index[polar_idx]])
        sph_box = _sphere_boxes(sph, camera)
    est = _estimated_hits(cols, qcut, live, kx, ky, None if sph is None else sph_box, max_contributions)
    if est > max_contributions:
        raise RenderLimitError(
            f"footprints need about {est} contributions (> max_contributions={max_contributions}); "
            "reduce the image size or the number/size of Gaussians")

    keys = []
    job_ranks = None
    if live.size:
        flat, job_ranks = _flat_keys(live, cols, qcut, rank, x0, kx, y0, ky, h, w, period, s0, n_all, layout)
        keys.append(flat)
    if sph is not None:
        sx0, skx, sy0, sky = sph_box
        kcx, kcy = _size_class(np.maximum(skx, 1)), _size_class(np.maximum(sky, 1))
        cls = kcx * (1 << 20) + kcy
        grp_order = np.argsort(cls, kind="stable")
        cuts = np.flatnonzero(np.diff(cls[grp_order])) + 1
        for grp in np.split(grp_order, cuts):
            kxc, kyc = int(kcx[grp[0]]), int(kcy[grp[0]])
            step = max(1, _CHUNK_ELEMENTS // (kxc * kyc))
            for start in range(0, grp.size, step):
                part = grp[start:start + step]
                box = (sx0[part], skx[part], sy0[part], sky[part])
                keys.append(_sphere_keys(part, polar_idx[part], kxc, kyc, sph, qcut, rank, box, h, w, layout))
    if len(keys) > 1:
        job_ranks = None
    keys = [k for k in keys if k.size]
    if not keys:
        return None, None, cols, None
    key = np.concatenate(keys) if len(keys) > 1 else keys[0]
    del keys
    key.sort(kind="stable")  # timsort: merges the pre-sorted runs (keys are unique: order is the same)
    return key, layout, cols, job_ranks


def _flat_keys(live, cols: _Cols, qcut, rank, x0, kx, y0, ky, h, w, period, s0, n_all, layout):
    """(keys, ranks): keys of the pixel-space footprints ``live`` (indices into ``cols``), block
    after block, and the ranks of those Gaussians in that order.

    The Gaussians are grouped by size class (wrapping ones apart) and, within a
    group, ordered by (box origin row y0, column x0, depth rank): for one fixed
    box offset (oy, ox) the pixel of every in-image element is
    (y0 + oy) * w + x0 + ox, which then increases along the Gaussians (two
    in-image columns differ by less than w), so every offset of a size-class
    block yields an already sorted run of keys and the final sort is a merge
    of a few hundred runs (a stable sort, i.e. timsort, merges them ~2-3x
    faster than sorting at random). Gaussians whose columns wrap around the
    period break that order: they form their own groups. One integer sort
    of packed (group, origin, rank) keys orders them all.
    """
    lkx, lky, lx0, ly0 = kx[live], ky[live], x0[live], y0[live]
    nc = len(_SIZE_CLASSES)
    px = np.searchsorted(_SIZE_CLASSES, np.maximum(lkx, 1))
    py = np.searchsorted(_SIZE_CLASSES, np.maximum(lky, 1))
    in_table = px.max() < nc and py.max() < nc
    if period is not None:
        wraps = (lx0 < s0) | (lx0 + lkx - 1 >= s0 + period)
    else:
        wraps = None
    origin = ly0 * (w + 2 * (period or 0) + 2) + lx0
    origin -= origin.min()
    obits = max(1, int(origin.max()).bit_length())
    rbits = max(1, int(n_all).bit_length())
    cbits = int(nc).bit_length()
    lrank = rank[live]
    if in_table and 2 * cbits + 1 + obits + rbits <= 63:
        grp = px * (1 << cbits) + py
        if wraps is not None:
            grp |= wraps.astype(np.int64) << (2 * cbits)
        okey = (grp << (obits + rbits)) | (origin << rbits) | lrank
        perm = np.argsort(okey)
        del okey, grp
    else:  # sizes beyond the table or too many bits: a lexsort does the same
        kcx, kcy = _size_class(np.maximum(lkx, 1)), _size_class(np.maximum(lky, 1))
        wr = np.zeros(live.size, np.int64) if wraps is None else wraps.astype(np.int64)
        perm = np.lexsort((lrank, origin, kcy, kcx, wr))
    del origin
    sel = live[perm]
    jx0, jkx, jy0, jky = lx0[perm], lkx[perm], ly0[perm], lky[perm]
    mx, my = cols.mx[sel], cols.my[sel]
    ca = cols.con_a[sel].astype(np.float32)
    cb = (2.0 * cols.con_b[sel]).astype(np.float32)
    cc = cols.con_c[sel].astype(np.float32)
    qc = qcut[sel].astype(np.float32)
    rkey = lrank[perm].astype(np.uint64) << np.uint64(layout.rank_shift)
    if in_table:
        kcx_all, kcy_all = _SIZE_CLASSES[px[perm]], _SIZE_CLASSES[py[perm]]
    else:
        kcx_all, kcy_all = _size_class(np.maximum(jkx, 1)), _size_class(np.maximum(jky, 1))
    change = (kcx_all[1:] != kcx_all[:-1]) | (kcy_all[1:] != kcy_all[:-1])
    jw = None
    if wraps is not None:
        jw = wraps[perm]
        change |= jw[1:] != jw[:-1]
    cuts = np.concatenate([[0], np.flatnonzero(change) + 1, [sel.size]])
    # every hit lands in one buffer (no per-block arrays, no concatenation); its size bounds the hits
    buf = np.empty(int(np.sum(kcx_all * kcy_all)), dtype=np.uint64)
    pos = 0
    for g0, g1 in zip(cuts[:-1], cuts[1:]):
        kxc, kyc = int(kcx_all[g0]), int(kcy_all[g0])
        step = max(1, _CHUNK_ELEMENTS // (kxc * kyc))
        for a in range(g0, g1, step):
            s = slice(a, min(g1, a + step))
            pos = _class_keys(kxc, kyc, jx0[s], jkx[s], jy0[s], jky[s], mx[s], my[s], ca[s], cb[s], cc[s],
                              qc[s], rkey[s], h, w, period, s0, layout, wrap=jw is not None and bool(jw[g0]),
                              out=buf, pos=pos)
    return buf[:pos], lrank[perm]


def _estimated_hits(cols: _Cols, qcut: np.ndarray, live, kx, ky, sph_box, limit: int) -> int:
    """Upper estimate of the contributions (= memory) the footprints will produce.

    Pixel-space footprints: the ellipse area ``pi qcut sqrt(det)`` plus its
    bounding-box perimeter (pixels cut by the border), at most the clipped
    box; polar (sphere) footprints: their whole box. Counting dense, size-class
    rounded boxes instead over-counted thin or diagonal ellipses 2-4x and
    refused ordinary 2048-wide views near a wall. The estimate is at most the
    plain box count, so that count is returned when it is within ``limit``.
    """
    box = np.maximum(kx[live], 0).astype(np.float64) * np.maximum(ky[live], 0)
    total = 0
    if sph_box is not None:
        _, skx, _, sky = sph_box
        total += int(np.sum(np.maximum(skx, 0).astype(np.float64) * np.maximum(sky, 0)))
    box_total = float(np.sum(box))
    if int(box_total) + total <= limit:
        return int(box_total) + total
    a, b, c = cols.cov_a[live], cols.cov_b[live], cols.cov_c[live]
    q = np.maximum(qcut[live], 0.0)
    ell = np.pi * q * np.sqrt(np.maximum(a * c - b * b, 0.0)) + 2 * np.sqrt(q) * (np.sqrt(a) + np.sqrt(c)) + 1
    return int(np.sum(np.minimum(box, ell))) + total


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

    def pixels(self, key: np.ndarray) -> np.ndarray:
        """(M,) flat pixel index of sorted keys (uint32 or int64)."""
        if self.pix_shift >= 32 and np.little_endian and key.dtype.byteorder in ("<", "="):
            return key.view(np.uint32)[1::2] >> np.uint32(self.pix_shift - 32)
        return (key >> np.uint64(self.pix_shift)).astype(np.int64)

    def ranks(self, key: np.ndarray) -> np.ndarray:
        """(M,) int64 depth rank of the keys."""
        r = key >> np.uint64(self.rank_shift)
        r &= np.uint64((1 << self.rank_bits) - 1)
        return r.view(np.int64)

    def weights(self, key: np.ndarray) -> np.ndarray:
        """(M,) float32 opacity-free weight exp(-q/2) of the keys."""
        if np.little_endian and key.dtype.byteorder in ("<", "="):
            low = key.view(np.uint32)[0::2]
        else:
            low = (key & np.uint64(0xFFFFFFFF)).astype(np.uint32)
        q = low & np.uint32((1 << self.q_bits) - 1)
        q = q.astype(np.float32)
        q *= np.float32(-0.5 / self.q_scale)
        return np.exp(q, out=q)


def _class_keys(kxc, kyc, x0, kx, y0, ky, mx, my, ca, cb, cc, qc, rkey, h, w, period, s0,
                layout: _KeyLayout, wrap: bool = True, out: np.ndarray | None = None, pos: int = 0):
    """Packed sort keys of one dense (kyc, kxc, n) block of pixel-space footprints.

    The Gaussian axis is innermost, so the keys come out offset by offset: each
    offset's keys are sorted when the Gaussians are ordered by (box origin, rank)
    and no column wraps (see :func:`_flat_keys`). ``ca, cb, cc``: float32 conic
    (xx, 2 xy, yy); ``qc`` float32 cut; ``rkey`` uint64 rank already shifted;
    ``wrap``: some boxes may wrap around the column period (else none does).
    Returns the keys, or with ``out`` writes them to ``out[pos:]`` and returns
    the position after them.

    Elements outside the box or the image get an infinite offset, so their q is
    inf or NaN and never a hit: their (possibly wrapped-around) keys are never
    selected. Keys are built with modular uint64 additions, exact for every hit.
    """
    shift = np.uint64(layout.pix_shift)
    ox = np.arange(kxc, dtype=np.int64)[:, None]
    dx = (x0 - mx).astype(np.float32)[None, :] + ox.astype(np.float32)
    dy = (y0 - my).astype(np.float32)[None, :] + np.arange(kyc, dtype=np.float32)[:, None]
    bad_x = ox >= kx[None, :]
    if wrap and period is not None:
        cols = np.mod(x0[None, :] + ox - s0, period) + s0
        bad_x |= (cols < 0) | (cols >= w)
        base = (y0 * w).astype(np.uint64) << shift
        colkey = cols.astype(np.uint64) << shift
    else:
        cols = x0[None, :] + ox
        bad_x |= (cols < 0) | (cols >= w)
        base = (y0 * w + x0).view(np.uint64) << shift
        colkey = None
    base += rkey
    dx[bad_x] = np.inf
    dy[np.arange(kyc)[:, None] >= ky[None, :]] = np.inf  # rows: boxes are clipped to the image
    rowkey = base[None, :] + ((np.arange(kyc, dtype=np.uint64) * np.uint64(w)) << shift)[:, None]
    with np.errstate(invalid="ignore", over="ignore"):
        q = (cb * dy)[:, None, :] * dx[None, :, :]
        q += (cc * dy * dy)[:, None, :]
        q += (ca * dx * dx)[None, :, :]
        hit = q <= qc[None, None, :]
        np.maximum(q, 0.0, out=q)
        q *= np.float32(layout.q_scale)
        qi = q.astype(np.uint32)
    if colkey is None:
        dense = rowkey[:, None, :] + (np.arange(kxc, dtype=np.uint64) << shift)[None, :, None]
    else:
        dense = rowkey[:, None, :] + colkey[None, :, :]
    dense += qi
    if out is None:
        return dense[hit]
    nh = int(np.count_nonzero(hit))
    np.compress(hit.reshape(-1), dense.reshape(-1), out=out[pos:pos + nh])
    return pos + nh


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
