"""Closed-form maths of small symmetric 3x3 matrices (6 components xx, yy, zz, xy, xz, yz), vectorised.

Eigenvalues by the trigonometric roots of the characteristic polynomial (many times faster than
``np.linalg.eigh`` on stacked small matrices), the smallest eigenpair, the plane test of the smooth
merge, and scales / quaternion of covariances with the arithmetic of :mod:`rasterizer.gaussians`.
The eigen maths exists once, on separate component arrays (:func:`eigvals_c`,
:func:`eigvec_c`); :func:`sym3_eigvals` / :func:`smallest_eigenpair` apply it to (m, 6) stacks
(the merged covariance's widening) and :func:`plane_ok_c` to the blocks its eigenvalue tests
keep (the hot path of the 2x2 merge).
"""

from __future__ import annotations

import numpy as np

SYM = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


# Reductions over a length-3 last axis, column by column (numpy's axis reductions are slow on short rows).
def sum3(a: np.ndarray) -> np.ndarray:
    return a[..., 0] + a[..., 1] + a[..., 2]


def max3(a: np.ndarray) -> np.ndarray:
    return np.maximum(np.maximum(a[..., 0], a[..., 1]), a[..., 2])


def min3(a: np.ndarray) -> np.ndarray:
    return np.minimum(np.minimum(a[..., 0], a[..., 1]), a[..., 2])


def outer6(d: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(n, 6) w d d^T of vectors d (n, 3)."""
    return np.stack([w * d[:, i] * d[:, j] for i, j in SYM], axis=1)


def sym_full(s6: np.ndarray) -> np.ndarray:
    """(n, 3, 3) symmetric matrices from their 6 components."""
    out = np.empty((s6.shape[0], 3, 3))
    for k, (i, j) in enumerate(SYM):
        out[:, i, j] = s6[:, k]
        out[:, j, i] = s6[:, k]
    return out


def sym3_eigvals(s6: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Eigenvalues (ascending) of symmetric 3x3 matrices given as 6 components, and the spread p.

    Closed form (trigonometric roots of the characteristic polynomial),
    many times faster than ``np.linalg.eigh`` on small stacked matrices.
    """
    return eigvals_c(*(s6[:, k] for k in range(6)))


def smallest_eigenpair(s6: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Smallest eigenvalue, its unit eigenvector and ok-flag of symmetric PSD 3x3 matrices (6 components).

    ok is False where the smallest eigenvalue is (numerically) repeated, so
    the eigenvector, a plane normal here, is not defined.
    """
    lam, mid, _, p = sym3_eigvals(s6)
    vec, nb = eigvec_c(lam, *(s6[:, k] for k in range(6)))
    ok = (p > 0) & (mid - lam > 1e-9 * p) & (nb > 0)
    return np.maximum(lam, 0.0), np.stack(vec, axis=1), ok


def eigvec_c(lam, xx, yy, zz, xy, xz, yz):
    """Unit eigenvector (three component arrays) of eigenvalue ``lam`` and its unnormalised length nb.

    The longest cross product of two rows of A - lambda I (the first of equal lengths); where
    nb = 0 the eigenvector is not defined and the components are the (zero) cross product.
    """
    r0 = (xx - lam, xy, xz)
    r1 = (xy, yy - lam, yz)
    r2 = (xz, yz, zz - lam)

    def cross(a, b):
        return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])

    cands = (cross(r0, r1), cross(r0, r2), cross(r1, r2))
    norms = [c[0] * c[0] + c[1] * c[1] + c[2] * c[2] for c in cands]
    # argmax, first of equal maxima
    best1 = norms[1] > norms[0]
    nmax = np.where(best1, norms[1], norms[0])
    best2 = norms[2] > nmax
    nb2 = np.where(best2, norms[2], nmax)
    vec = [np.where(best2, cands[2][k], np.where(best1, cands[1][k], cands[0][k])) for k in range(3)]
    nb = np.sqrt(nb2)
    nbs = np.where(nb > 0, nb, 1.0)
    return (vec[0] / nbs, vec[1] / nbs, vec[2] / nbs), nb


def rows4(a: np.ndarray) -> np.ndarray:
    """a[0] + a[1] + a[2] + a[3] in that order (the same rounding as summing four member arrays one by one)."""
    return a[0] + a[1] + a[2] + a[3]


def eigvals_c(xx, yy, zz, xy, xz, yz):
    """:func:`sym3_eigvals` on the six components as separate arrays."""
    q = (xx + yy + zz) / 3.0
    p2 = (xx - q) ** 2 + (yy - q) ** 2 + (zz - q) ** 2 + 2.0 * (xy * xy + xz * xz + yz * yz)
    p = np.sqrt(p2 / 6.0)
    inv = np.where(p > 0, 1.0 / np.where(p > 0, p, 1.0), 0.0)
    bxx, byy, bzz = (xx - q) * inv, (yy - q) * inv, (zz - q) * inv
    bxy, bxz, byz = xy * inv, xz * inv, yz * inv
    det = bxx * (byy * bzz - byz * byz) - bxy * (bxy * bzz - byz * bxz) + bxz * (bxy * byz - byy * bxz)
    phi = np.arccos(np.clip(det / 2.0, -1.0, 1.0)) / 3.0
    lo = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    hi = q + 2.0 * p * np.cos(phi)
    return lo, 3.0 * q - lo - hi, hi, p


def plane_ok_c(wsafe, mux, muy, muz, m2, plane_tol: float, cos_incidence: float) -> np.ndarray:
    """Blocks whose (weighted) centres lie on a plane seen at most at the incidence limit.

    Residual = rms distance from the best plane (smallest eigenvalue of the
    scatter m2 / wsafe), relative to the range of the block's centre (mux,
    muy, muz); incidence = angle between that plane's normal and the ray to
    the centre. The incidence limit also rejects depth steps: a block whose
    pixels jump in range fits a plane almost parallel to the rays.

    m2: six (m,) component arrays of the scatter. The cheap tests (spread, repeated eigenvalue, residual)
    run first; the normal (cross products of rows of A - lambda I, the longest one) only for the blocks
    that pass them.
    """
    xx, yy, zz, xy, xz, yz = (c / wsafe for c in m2)
    lam, mid, _, p = eigvals_c(xx, yy, zz, xy, xz, yz)
    rng = np.sqrt(mux * mux + muy * muy + muz * muz)
    ok = (p > 0) & (mid - lam > 1e-9 * p) & (rng > 0) & (np.maximum(lam, 0.0) <= (plane_tol * rng) ** 2)
    i = np.flatnonzero(ok)
    lam, xx, yy, zz, xy, xz, yz = (a[i] for a in (lam, xx, yy, zz, xy, xz, yz))
    (vx, vy, vz), nb = eigvec_c(lam, xx, yy, zz, xy, xz, yz)
    mux, muy, muz, rng = mux[i], muy[i], muz[i], rng[i]
    dot = vx * mux + vy * muy + vz * muz
    cos_inc = np.abs(dot) / rng
    ok[i] = (nb > 0) & (cos_inc >= cos_incidence)
    return ok


def sym3_eigh(s6: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (m, 3), ascending, and unit eigenvectors (m, 3, 3) as columns of symmetric 3x3
    matrices given as 6 components: ``np.linalg.eigh``'s result in closed form, several times faster on
    stacked small matrices (eigenvectors of a repeated eigenvalue, and the signs, may differ: any
    orthonormal choice spans the same eigenspaces).

    The eigenvalue farther from the middle one (:func:`eigvals_c`) has a well-separated eigenvector,
    the longest cross product of two rows of A - lambda I (:func:`eigvec_c`; the x axis where A is a
    multiple of I); the other two are the 2x2 problem in the plane orthogonal to it, solved by one
    Jacobi rotation, which stays exact when they coincide. Eigenvalues are the Rayleigh quotients of
    the eigenvectors (accurate to rounding of A's norm, where the trigonometric roots lose half the
    digits of a nearly repeated pair).
    """
    xx, yy, zz, xy, xz, yz = (s6[:, k] for k in range(6))
    lo, mid, hi, _ = eigvals_c(xx, yy, zz, xy, xz, yz)
    top = hi - mid >= mid - lo  # the largest eigenvalue is the isolated one (else the smallest)
    (ax, ay, az), nb = eigvec_c(np.where(top, hi, lo), xx, yy, zz, xy, xz, yz)
    ax = np.where(nb > 0, ax, 1.0)
    # (u, v): an orthonormal basis of the plane orthogonal to a, (u, v, a) right-handed
    big = np.abs(ax) > np.abs(ay)
    ux, uy, uz = np.where(big, -az, 0.0), np.where(big, 0.0, az), np.where(big, ax, -ay)
    un = np.sqrt(ux * ux + uy * uy + uz * uz)
    ux, uy, uz = ux / un, uy / un, uz / un
    vx, vy, vz = ay * uz - az * uy, az * ux - ax * uz, ax * uy - ay * ux

    def times(x, y, z):  # A (x, y, z)
        return xx * x + xy * y + xz * z, xy * x + yy * y + yz * z, xz * x + yz * y + zz * z

    aux, auy, auz = times(ux, uy, uz)
    avx, avy, avz = times(vx, vy, vz)
    m00 = ux * aux + uy * auy + uz * auz
    m01 = vx * aux + vy * auy + vz * auz
    m11 = vx * avx + vy * avy + vz * avz
    theta = 0.5 * np.arctan2(2.0 * m01, m00 - m11)  # rotates (u, v) onto the 2x2 problem's eigenvectors
    c, s = np.cos(theta), np.sin(theta)
    b = (c * ux + s * vx, c * uy + s * vy, c * uz + s * vz)  # the larger of the two
    d = (c * vx - s * ux, c * vy - s * uy, c * vz - s * uz)
    half, rad = 0.5 * (m00 + m11), np.hypot(0.5 * (m00 - m11), m01)
    aax, aay, aaz = times(ax, ay, az)
    lam_a = ax * aax + ay * aay + az * aaz
    evals = np.empty((s6.shape[0], 3))
    vecs = np.empty((s6.shape[0], 3, 3))
    for k, (when_top, when_low) in enumerate(((half - rad, lam_a), (half + rad, half - rad), (lam_a, half + rad))):
        evals[:, k] = np.where(top, when_top, when_low)
    cols = (((d, (ax, ay, az)), (b, d), ((ax, ay, az), b)))
    for k, (when_top, when_low) in enumerate(cols):
        for i in range(3):
            vecs[:, i, k] = np.where(top, when_top[i], when_low[i])
    return evals, vecs


def scale_rotation6(cov6: np.ndarray, min_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`rasterizer.gaussians.scale_rotation_from_covariance` of covariances given as 6 components.

    The eigen-decomposition in closed form (:func:`sym3_eigh`): the same scales and covariances to
    rounding, the quaternions of another (equally valid) choice of eigenvector signs; the reflection
    test uses the triple product of the orthonormal eigenvectors instead of an LU determinant (same sign).
    """
    evals, r = sym3_eigh(cov6)
    det = (r[:, 0, 0] * (r[:, 1, 1] * r[:, 2, 2] - r[:, 1, 2] * r[:, 2, 1])
           - r[:, 0, 1] * (r[:, 1, 0] * r[:, 2, 2] - r[:, 1, 2] * r[:, 2, 0])
           + r[:, 0, 2] * (r[:, 1, 0] * r[:, 2, 1] - r[:, 1, 1] * r[:, 2, 0]))
    r[:, :, 2] *= np.where(det < 0, -1.0, 1.0)[:, None]
    return np.sqrt(np.maximum(evals, min_scale**2)), rotmat_to_quat(r)


def rotmat_to_quat(r: np.ndarray) -> np.ndarray:
    """:func:`rasterizer.gaussians.rotmat_to_quat` (the same arithmetic), component by component."""
    m00, m11, m22 = r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]
    trace = m00 + m11 + m22
    d21, d02, d10 = r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] - r[:, 0, 1]
    s01, s02, s12 = r[:, 0, 1] + r[:, 1, 0], r[:, 0, 2] + r[:, 2, 0], r[:, 1, 2] + r[:, 2, 1]
    cand = ((1 + trace, d21, d02, d10),
            (d21, 1 + m00 - m11 - m22, s01, s02),
            (d02, s01, 1 - m00 + m11 - m22, s12),
            (d10, s02, s12, 1 - m00 - m11 + m22))
    # argmax over (trace, m00, m11, m22), the first of equal maxima
    which = np.zeros(trace.shape, dtype=np.intp)
    cur = trace
    for k, d in ((1, m00), (2, m11), (3, m22)):
        gt = d > cur
        which[gt] = k
        cur = np.where(gt, d, cur)
    q = [np.choose(which, [c[k] for c in cand]) for k in range(4)]
    norm = np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    sign = np.where(q[0] / norm < 0, -1.0, 1.0)
    out = np.empty(trace.shape + (4,))
    for k in range(4):
        out[:, k] = q[k] / norm * sign
    return out
