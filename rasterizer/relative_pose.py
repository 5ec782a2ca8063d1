"""Relative pose of two panoramas from bearing matches (numpy only).

Frames: OpenCV camera frames (or their levelled versions, :mod:`rasterizer.gravity`); A is the
world and B's pose is ``[R | t]``: a point ``X_B`` in B's frame is ``R X_B + t`` in A's. Two
levelled panoramas differ by a turn about the y axis (gravity), so ``R = yaw_rotation(yaw)``
(3 dof with the direction of ``t``: :func:`upright_ransac`, :func:`refine_upright`); a residual
tilt needs the general 5-dof model (:func:`refine_general`). A match of unit bearings
``(f_a, f_b)`` satisfies ``f_a . (t x R f_b) = 0``; errors are angles (rad) of a bearing from its
epipolar plane.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .geometry import unit_vectors
from .threads import map_threads

#: Default inlier threshold on the epipolar angle (degrees).
INLIER_DEG = 1.0
_EPS = 1e-12


def yaw_rotation(yaw) -> np.ndarray:
    """Rotation(s) about the camera y axis by ``yaw`` rad, (..., 3, 3)."""
    yaw = np.asarray(yaw, dtype=np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    z, o = np.zeros_like(c), np.ones_like(c)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def _unit(v: np.ndarray) -> np.ndarray:
    return unit_vectors(v, _EPS)


def epipolar_error(fa: np.ndarray, fb: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Symmetric angular epipolar error (rad), the larger of A's and B's; broadcasts over leading axes.

    fa, fb: (..., N, 3) unit bearings; R: (..., 3, 3); t: (..., 3).
    """
    return _epipolar_error_turned(fa, _turned(R, fb), t)


def _turned(R: np.ndarray, fb: np.ndarray) -> np.ndarray:
    """B's bearings in A's frame, ``R f_b`` (..., N, 3)."""
    return np.einsum("...ij,...nj->...ni", R, fb)


def _epipolar_error_turned(fa: np.ndarray, g: np.ndarray, t: np.ndarray) -> np.ndarray:
    """:func:`epipolar_error` of B's bearings already turned into A's frame (``g`` = :func:`_turned`)."""
    t = np.asarray(t)[..., None, :]
    normal = np.cross(t, g)  # of the epipolar plane through B's bearing
    triple = np.abs(np.einsum("...ni,...ni->...n", fa, normal))
    den = np.minimum(np.linalg.norm(normal, axis=-1), np.linalg.norm(np.cross(t, fa), axis=-1))
    return np.arcsin(np.clip(triple / np.maximum(den, _EPS), 0.0, 1.0))


def triangulate(fa: np.ndarray, fb: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Midpoint ranges ``(lam_a, lam_b)`` (..., N) with ``lam_a f_a ~ lam_b R f_b + t``; NaN-free (0 if parallel)."""
    return _triangulate_turned(fa, _turned(R, fb), t)


def _triangulate_turned(fa: np.ndarray, g: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`triangulate` of B's bearings already turned into A's frame (``g`` = :func:`_turned`)."""
    t = np.asarray(t)[..., None, :]
    k = np.einsum("...ni,...ni->...n", fa, g)
    at, gt = np.sum(fa * t, -1), np.sum(g * t, -1)
    den = np.maximum(1.0 - k * k, 1e-9)
    return (at - k * gt) / den, (k * at - gt) / den


def rotation_only_fraction(fa: np.ndarray, fb: np.ndarray, *, threshold_deg: float = 0.5, yaw_step_deg: float = 0.5) -> float:
    """Largest fraction of matches a pure yaw (no translation) explains within ``threshold_deg``: ~1 means no parallax.

    ``f_a . R(yaw) f_b = cos(yaw) (x_a x_b + z_a z_b) + sin(yaw) (x_a z_b - z_a x_b) + y_a y_b``: three numbers per
    match, then one (yaws, N) pass, instead of turning every bearing by every yaw."""
    if not len(fa):
        return 0.0
    yaws = np.radians(np.arange(0.0, 360.0, yaw_step_deg))
    cos_thr = np.cos(np.radians(threshold_deg))
    along = fa[:, 0] * fb[:, 0] + fa[:, 2] * fb[:, 2]
    across = fa[:, 0] * fb[:, 2] - fa[:, 2] * fb[:, 0]
    dots = np.cos(yaws)[:, None] * along + np.sin(yaws)[:, None] * across
    dots += fa[:, 1] * fb[:, 1]
    return float(np.max(np.mean(dots > cos_thr, axis=1)))


@dataclass
class Hypothesis:
    """One relative pose: yaw (rad), unit ``t``, inlier mask (N,), MSAC cost."""

    yaw: float
    t: np.ndarray
    inliers: np.ndarray
    cost: float

    @property
    def R(self) -> np.ndarray:
        return yaw_rotation(self.yaw)

    @property
    def num_inliers(self) -> int:
        return int(self.inliers.sum())


@dataclass
class RansacResult:
    best: Hypothesis
    rival: Hypothesis | None  # best hypothesis far from ``best`` (another mode), if any
    num_hypotheses: int
    extras: dict = field(default_factory=dict)


def _minimal_hypotheses(fa: np.ndarray, fb: np.ndarray, triples: np.ndarray, yaw_step_deg: float):
    """Roots in yaw of det[m1, m2, m3] = 0 (m_k = R f_b,k x f_a,k) per sample triple -> (yaws (H,), t (H, 3))."""
    yaws = np.radians(np.arange(-180.0, 180.0 + yaw_step_deg, yaw_step_deg))
    a, b = fa[triples], fb[triples]  # (S, 3, 3)
    g = np.einsum("yij,skj->yski", yaw_rotation(yaws), b)  # (Y, S, 3, 3)
    m = np.cross(g, a[None])
    det = np.linalg.det(m)  # (Y, S)
    y0, s0 = np.nonzero(np.sign(det[:-1]) * np.sign(det[1:]) < 0)
    d0, d1 = det[y0, s0], det[y0 + 1, s0]
    yaw = yaws[y0] + (yaws[y0 + 1] - yaws[y0]) * d0 / (d0 - d1)
    mm = np.cross(np.einsum("hij,hkj->hki", yaw_rotation(yaw), b[s0]), a[s0])
    t = np.cross(mm[:, 0], mm[:, 1])
    t_alt = np.cross(mm[:, 0], mm[:, 2])
    t = np.where(np.linalg.norm(t, axis=-1, keepdims=True) > np.linalg.norm(t_alt, axis=-1, keepdims=True), t, t_alt)
    ok = np.linalg.norm(t, axis=-1) > 1e-9
    return yaw[ok], _unit(t[ok])


def _score(fa, fb, yaws, ts, thr):
    """MSAC cost (H,), inliers (H, N) and ``t`` with the sign most inliers see in front of both cameras."""
    g = _turned(yaw_rotation(yaws), fb[None])  # (H, N, 3), shared by the error and the ranges
    err = _epipolar_error_turned(fa[None], g, ts)
    inl = err < thr
    la, lb = _triangulate_turned(fa[None], g, ts)
    front = (la > 0) & (lb > 0)
    back = (la < 0) & (lb < 0)
    flip = np.sum(back & inl, 1) > np.sum(front & inl, 1)
    ts = np.where(flip[:, None], -ts, ts)
    inl &= np.where(flip[:, None], back, front)
    cost = np.sum(np.where(inl, err * err, thr * thr), axis=1)
    return cost, inl, ts


def upright_ransac(fa: np.ndarray, fb: np.ndarray, *, threshold_deg: float = INLIER_DEG, samples: int = 400,
                   yaw_step_deg: float = 1.0, rival_yaw_deg: float = 15.0, rival_t_deg: float = 25.0,
                   seed: int = 0) -> RansacResult:
    """Upright 3-point RANSAC on matched bearings fa, fb (N, 3); cheirality picks the sign of ``t``.

    ``rival`` is the best hypothesis whose yaw differs by more than ``rival_yaw_deg`` or whose
    translation direction differs by more than ``rival_t_deg`` (a second mode, e.g. a 180-deg flip).
    """
    n = len(fa)
    if n < 3:
        raise ValueError("need at least 3 matches")
    rng = np.random.default_rng(seed)
    triples = np.stack([rng.choice(n, 3, replace=False) for _ in range(samples)])
    yaws, ts = _minimal_hypotheses(fa, fb, triples, yaw_step_deg)
    if not len(yaws):
        raise ValueError("no pose hypothesis (degenerate matches)")
    thr = np.radians(threshold_deg)
    starts = range(0, len(yaws), 256)  # independent blocks of hypotheses, scored two at a time
    parts = map_threads(lambda i: _score(fa, fb, yaws[i:i + 256], ts[i:i + 256], thr), starts)
    cost, inl, tt = (np.concatenate(x) for x in zip(*parts))
    order = np.argsort(cost)
    b = order[0]
    best = Hypothesis(float(yaws[b]), tt[b], inl[b], float(cost[b]))
    dyaw = np.degrees(np.abs(np.angle(np.exp(1j * (yaws - yaws[b])))))
    dt = np.degrees(np.arccos(np.clip(tt @ tt[b], -1, 1)))
    far = (dyaw > rival_yaw_deg) | (dt > rival_t_deg)
    rival = None
    if far.any():
        r = order[far[order]][0]
        rival = Hypothesis(float(yaws[r]), tt[r], inl[r], float(cost[r]))
    return RansacResult(best, rival, len(yaws))


def _params_to_pose(p: np.ndarray, yaw0: float, t0: np.ndarray, basis: np.ndarray):
    return yaw0 + p[0], _unit(t0 + basis @ p[1:])


def _robust_gauss_newton(residual, apply, rot, t: np.ndarray, dim: int, s: float, iterations: int):
    """Cauchy-weighted (scale ``s`` rad) Gauss-Newton with forward-difference Jacobians.

    ``rot`` is the rotation's parameter (a yaw, or a 3 x 3 matrix) and ``t`` the unit translation; ``apply(p, rot,
    t, basis)`` moves them by the step ``p`` (dim,) whose last two entries move ``t`` in ``basis`` (3, 2), the
    tangent plane of the sphere at ``t``; ``residual(rot, t)`` gives the (N,) epipolar residuals. Returns (rot, t).
    """
    for _ in range(iterations):
        helper = np.array([1.0, 0, 0]) if abs(t[0]) < 0.9 else np.array([0, 1.0, 0])
        e1 = _unit(np.cross(t, helper))
        basis = np.stack([e1, np.cross(t, e1)], 1)
        r = residual(rot, t)
        w = 1.0 / (1.0 + (r / s) ** 2)
        J = np.empty((len(r), dim))
        h = 1e-6
        for k in range(dim):
            dp = np.zeros(dim)
            dp[k] = h
            J[:, k] = (residual(*apply(dp, rot, t, basis)) - r) / h
        A = J.T @ (w[:, None] * J) + 1e-9 * np.eye(dim)
        step = -np.linalg.solve(A, J.T @ (w * r))
        rot, t = apply(step, rot, t, basis)
        if np.abs(step).max() < 1e-9:
            break
    return rot, t


def refine_upright(fa: np.ndarray, fb: np.ndarray, yaw: float, t: np.ndarray, *, R0: np.ndarray | None = None,
                   scale_deg: float = INLIER_DEG, iterations: int = 15) -> tuple[float, np.ndarray]:
    """Robust (Cauchy, scale ``scale_deg``) Gauss-Newton on yaw and the direction of ``t``.

    The rotation is ``R0 @ yaw_rotation(yaw)`` (``R0`` = I by default); returns (yaw, unit t).
    """
    R0 = np.eye(3) if R0 is None else np.asarray(R0, dtype=np.float64)
    t = _unit(np.asarray(t, dtype=np.float64))
    s = np.radians(scale_deg)

    def residual(yaw_, t_):
        g = (R0 @ yaw_rotation(yaw_) @ fb.T).T
        n = np.cross(t_, g)
        return np.einsum("ni,ni->n", fa, n) / np.maximum(np.linalg.norm(n, axis=-1), _EPS)

    yaw, t = _robust_gauss_newton(residual, _params_to_pose, yaw, t, 3, s, iterations)
    return float(yaw), t


def rotation_exp(w: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of the rotation vector ``w`` (3,) rad (Rodrigues)."""
    w = np.asarray(w, dtype=np.float64)
    a = float(np.linalg.norm(w))
    k = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if a < 1e-12:
        return np.eye(3) + k
    return np.eye(3) + np.sin(a) / a * k + (1 - np.cos(a)) / (a * a) * (k @ k)


def refine_general(fa: np.ndarray, fb: np.ndarray, R: np.ndarray, t: np.ndarray, *, scale_deg: float = INLIER_DEG,
                   iterations: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """Robust (Cauchy, scale ``scale_deg``) Gauss-Newton on the full rotation (3 dof, ``R exp([w]x)``) and
    the direction of ``t`` (2 dof) from matched unit bearings fa, fb (N, 3); returns (R, unit t)."""
    R = np.asarray(R, dtype=np.float64)
    t = _unit(np.asarray(t, dtype=np.float64))
    s = np.radians(scale_deg)

    def residual(R_, t_):
        n = np.cross(t_, fb @ R_.T)
        return np.einsum("ni,ni->n", fa, n) / np.maximum(np.linalg.norm(n, axis=-1), _EPS)

    def apply(p, R_, t_, basis):
        return R_ @ rotation_exp(p[:3]), _unit(t_ + basis @ p[3:])

    return _robust_gauss_newton(residual, apply, R, t, 5, s, iterations)


def tilt_between(R: np.ndarray) -> float:
    """Angle (deg) by which the rotation ``R`` (3, 3) moves the y axis: the tilt that a yaw cannot explain."""
    return float(np.degrees(np.arccos(np.clip(R[1, 1], -1.0, 1.0))))


def floor_scale(points: np.ndarray, camera_height: float, parallax: np.ndarray | None = None, *,
                min_parallax_deg: float = 3.0, min_share: float = 0.03, min_points: int = 8,
                thickness: float = 0.03, min_spread: float = 0.15, min_peak: float = 0.3,
                bearing_noise_deg: float = INLIER_DEG / 2) -> tuple[float, dict]:
    """Metres per unit from triangulated points (N, 3) in a levelled frame of A (y down along gravity) and
    A's height above the floor.

    The floor is the lowest horizontal slab (``2 * thickness`` thick in log depth) that holds at least
    ``min_points``, ``min_share`` of the points more than 20 deg below the horizon and ``min_peak`` of
    the fullest slab's points (a few strays or a floor's reflections are not a floor), and spreads
    horizontally in both directions (standard deviation along the narrower principal axis of its points'
    x, z at least ``min_spread`` times its depth; a wall's band of points is a line): the lowest large
    horizontal plane, not the densest one (a bed or a table top can be the densest). Points seen with
    less than ``min_parallax_deg`` of ``parallax`` (N,) rad (near the epipoles, badly triangulated)
    are ignored. With ``parallax`` the slab is at least as thick as the median relative depth error of
    the points below, ``bearing_noise_deg`` / sin(parallax): a floor seen with little parallax scatters
    in depth, and a slab thinner than its scatter splits it below the counts above. Raises
    ``ValueError`` when no slab qualifies.
    """
    p = np.asarray(points, dtype=np.float64)
    rng_ = np.linalg.norm(p, axis=-1)
    below = (p[:, 1] > np.sin(np.radians(20)) * rng_) & np.isfinite(rng_)
    if parallax is not None:
        below &= np.asarray(parallax) >= np.radians(min_parallax_deg)
    q = p[below]
    if parallax is not None and len(q):
        sigma = np.radians(bearing_noise_deg) / np.sin(np.asarray(parallax)[below])
        thickness = max(thickness, float(np.median(sigma)))
    if len(q) < max(min_points, 5):
        raise ValueError(f"only {len(q)} well triangulated points below the camera: cannot find the floor")
    order = np.argsort(-q[:, 1])  # deepest first
    q = q[order]
    logy = np.log(q[:, 1])
    # slab starting at each point (going up): the points within ``2 * thickness`` in log depth above it
    ends = np.searchsorted(-logy, -(logy - 2 * thickness), side="right")
    counts = ends - np.arange(len(q))
    need = max(min_points, int(np.ceil(min_share * len(q))), int(np.ceil(min_peak * counts.max())))
    for i in np.nonzero(counts >= need)[0]:
        slab = q[i:ends[i]]
        y = float(np.exp(np.median(np.log(slab[:, 1]))))
        spread = np.sqrt(max(np.linalg.eigvalsh(np.cov(slab[:, [0, 2]].T))[0], 0.0))
        if spread >= min_spread * y:
            return camera_height / y, {"floor_points": int(len(slab)), "floor_depth_units": y,
                                       "points_below_floor": int(i)}
    raise ValueError(f"no horizontal plane below the camera holds {need} of the {len(q)} triangulated points "
                     "there and spreads wide: the floor is not seen in both views")
