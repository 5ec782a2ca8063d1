"""View-dependent colour of Gaussians from real spherical harmonics (3DGS convention).

``rgb = max(0, 0.5 + sum_k C_k Y_k(d) sh_k)`` with ``d`` the unit direction
from the camera centre to the Gaussian (world frame), degree 0..3, the
constants and sign pattern of the INRIA 3DGS code; clamped above at
:data:`rasterizer.composite.COLOUR_MAX`.
"""

from __future__ import annotations

import numpy as np

from .composite import COLOUR_MAX

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def sh_basis(dirs: np.ndarray, k: int) -> np.ndarray:
    """Real SH basis values (N, k) for unit directions (N, 3), k in 1, 4, 9, 16."""
    dirs = np.asarray(dirs, dtype=np.float32)
    x, y, z = dirs[:, 0], dirs[:, 1], dirs[:, 2]
    out = np.empty((dirs.shape[0], k), dtype=np.float32)
    out[:, 0] = SH_C0
    if k > 1:
        out[:, 1] = -SH_C1 * y
        out[:, 2] = SH_C1 * z
        out[:, 3] = -SH_C1 * x
    if k > 4:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out[:, 4] = SH_C2[0] * xy
        out[:, 5] = SH_C2[1] * yz
        out[:, 6] = SH_C2[2] * (2.0 * zz - xx - yy)
        out[:, 7] = SH_C2[3] * xz
        out[:, 8] = SH_C2[4] * (xx - yy)
    if k > 9:
        out[:, 9] = SH_C3[0] * y * (3 * xx - yy)
        out[:, 10] = SH_C3[1] * xy * z
        out[:, 11] = SH_C3[2] * y * (4 * zz - xx - yy)
        out[:, 12] = SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy)
        out[:, 13] = SH_C3[4] * x * (4 * zz - xx - yy)
        out[:, 14] = SH_C3[5] * z * (xx - yy)
        out[:, 15] = SH_C3[6] * x * (xx - 3 * yy)
    return out


def sh_to_rgb(sh: np.ndarray, means: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Colours (N, 3) float32 in [0, COLOUR_MAX] of SH coefficients (N, K, 3) seen from ``centre`` (3,).

    Evaluated in float32; the rows whose sum overflows it (coefficients near float32's limit, finite each)
    again in float64, so that a colour is never Inf or NaN (which the compositing's zero weights would
    turn into NaN pixels), then clamped to COLOUR_MAX."""
    sh = np.asarray(sh, dtype=np.float32)
    k = sh.shape[1]
    if k == 1:
        rgb = np.float32(SH_C0) * sh[:, 0, :] + np.float32(0.5)
    else:
        d = np.asarray(means, dtype=np.float64) - np.asarray(centre, dtype=np.float64)
        n = np.linalg.norm(d, axis=1, keepdims=True)
        d = np.where(n > 0, d / np.maximum(n, 1e-30), 0.0)
        basis = sh_basis(d, k)
        with np.errstate(over="ignore", invalid="ignore"):
            rgb = np.einsum("nk,nkc->nc", basis, sh) + np.float32(0.5)
        bad = np.flatnonzero(~np.isfinite(rgb).all(axis=1))
        if bad.size:
            exact = np.einsum("nk,nkc->nc", basis[bad].astype(np.float64), sh[bad].astype(np.float64)) + 0.5
            rgb[bad] = np.clip(exact, 0.0, COLOUR_MAX)
    return np.clip(rgb, 0.0, COLOUR_MAX).astype(np.float32, copy=False)
