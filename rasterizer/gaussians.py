"""The Gaussians container and covariance <-> scale/rotation conversions.

One set of 3D Gaussians in world space, stored as activated float32 arrays:

==========  ==========  ===================================================
field       shape       meaning
==========  ==========  ===================================================
means       (N, 3)      centres, world frame (metres)
scales      (N, 3)      standard deviations along the local axes, > 0
quats       (N, 4)      unit rotation quaternions (w, x, y, z), local->world
opacities   (N,)        alpha in [0, 1]
sh          (N, K, 3)   SH coefficients, K = (degree + 1)^2; sh[:, 0] is DC,
                        colour = 0.5 + 0.28209479177387814 * DC
==========  ==========  ===================================================

The PLY file stores the pre-activation form (log-scale, logit opacity); see
:mod:`rasterizer.ply`.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np

from .sh import SH_C0


class GaussiansError(ValueError):
    """Gaussian arrays of the wrong shape, or with NaN/Inf."""


#: A position step (SPZ's fixed point; float32's spacing far from the origin) may be at most this fraction of
#: the Gaussians' :func:`typical_size`: every splat then lies within 1/16 of that size of where it is, per axis.
#: Measured on the m3d and ZInD dev scenes moved from the origin (1024-wide ERP renders from a reference, SPZ
#: against the unrounded Gaussians), the PSNR lost to the position step, against SPZ at the origin (57.2 and
#: 56.9 dB):
#:
#: ==================  ==========  ===========
#: step / median size  m3d         ZInD
#: ==================  ==========  ===========
#: 0.06-0.08           0.6 dB      1.4 dB
#: 0.12-0.16           1.4 dB      2.1 dB
#: 0.23-0.31           3.7 dB      4.4 dB
#: 0.47-0.63           8.0 dB      8.7 dB
#: 1.9-2.5             20.6 dB     18.9 dB
#: ==================  ==========  ===========
#:
#: 1/8 keeps the loss within about 2 dB of SPZ at the origin on both (no visible change); beyond 1/4 the error
#: more than doubles, and from about one size on, splats visibly move.
MAX_STEP_PER_SIZE = 1 / 8


def step_share(step: float, size: float) -> str:
    """A position step against a :func:`typical_size` in words, for a refusal's message: "0.12 of", or "more than"
    where the size is 0 (a point cloud of zero scales, against which every step is too coarse)."""
    return f"{step / size:.2g} of" if size > 0 else "more than"


def typical_size(scales: np.ndarray) -> float:
    """The median over (N, 3) ``scales`` (N >= 1) of each Gaussian's middle scale, in scene units: the sigma of a flat
    splat's narrower visible axis (its thinnest shows only edge on), what a position error is seen against."""
    a, b, c = scales[:, 0], scales[:, 1], scales[:, 2]
    middle = np.maximum(np.minimum(a, b), np.minimum(np.maximum(a, b), c))  # column-wise: 10x faster than axis=1
    return float(np.partition(middle, len(middle) // 2)[len(middle) // 2])  # the (upper) median, without a sort


def rgb_to_sh_dc(rgb: np.ndarray) -> np.ndarray:
    """SH DC coefficient that renders as colour ``rgb``."""
    return (np.asarray(rgb, dtype=np.float32) - 0.5) / np.float32(SH_C0)


def sh_dc_to_rgb(dc: np.ndarray) -> np.ndarray:
    """Colour of an SH DC coefficient (no clamping)."""
    return np.float32(0.5) + np.float32(SH_C0) * np.asarray(dc, dtype=np.float32)


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) of quaternions (N, 4) in (w, x, y, z) order.

    The quaternions are normalised first; a zero quaternion gives the identity.
    """
    q = np.asarray(q, dtype=np.float64)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    q = np.where(n > 1e-12, q / np.maximum(n, 1e-12), np.array([1.0, 0.0, 0.0, 0.0]))
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


def rotmat_to_quat(rot: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z) with w >= 0 of rotation matrices (N, 3, 3).

    Uses the largest-diagonal branch for each matrix, so it is stable for
    every rotation (including 180-degree turns).
    """
    r = np.asarray(rot, dtype=np.float64)
    m00, m11, m22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
    trace = m00 + m11 + m22
    cand = np.stack(
        [
            np.stack([1 + trace, r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]], -1),
            np.stack([r[..., 2, 1] - r[..., 1, 2], 1 + m00 - m11 - m22, r[..., 0, 1] + r[..., 1, 0], r[..., 0, 2] + r[..., 2, 0]], -1),  # noqa: E501
            np.stack([r[..., 0, 2] - r[..., 2, 0], r[..., 0, 1] + r[..., 1, 0], 1 - m00 + m11 - m22, r[..., 1, 2] + r[..., 2, 1]], -1),  # noqa: E501
            np.stack([r[..., 1, 0] - r[..., 0, 1], r[..., 0, 2] + r[..., 2, 0], r[..., 1, 2] + r[..., 2, 1], 1 - m00 - m11 + m22], -1),  # noqa: E501
        ],
        axis=-2,
    )
    which = np.argmax(np.stack([trace, m00, m11, m22], -1), axis=-1)
    q = np.take_along_axis(cand, which[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def covariance_from_scale_rotation(scales: np.ndarray, quats: np.ndarray) -> np.ndarray:
    """World covariances R diag(s^2) R^T, (N, 3, 3) float64."""
    rot = quat_to_rotmat(quats)
    s2 = np.asarray(scales, dtype=np.float64) ** 2
    return np.einsum("nij,nj,nkj->nik", rot, s2, rot)


def scale_rotation_from_covariance(cov: np.ndarray, min_scale: float = 1e-12) -> tuple[np.ndarray, np.ndarray]:
    """Scales (N, 3) and quaternions (N, 4) of symmetric PSD covariances (N, 3, 3).

    Eigen-decomposition; negative round-off eigenvalues and rank-deficient
    covariances are floored at ``min_scale**2`` so log-scales stay finite.
    Reflections are turned into proper rotations by flipping one axis.
    """
    cov = np.asarray(cov, dtype=np.float64)
    cov = 0.5 * (cov + np.swapaxes(cov, -1, -2))
    evals, evecs = np.linalg.eigh(cov)
    det = np.linalg.det(evecs)
    evecs[..., :, 2] *= np.where(det < 0, -1.0, 1.0)[..., None]
    scales = np.sqrt(np.maximum(evals, min_scale**2))
    return scales, rotmat_to_quat(evecs)


@dataclass(frozen=True)
class Gaussians:
    """A set of world-space 3D Gaussians (see the module docstring for fields)."""

    means: np.ndarray
    scales: np.ndarray
    quats: np.ndarray
    opacities: np.ndarray
    sh: np.ndarray

    def __post_init__(self) -> None:
        n = np.shape(self.means)[0] if np.ndim(self.means) == 2 else -1
        expected = {
            "means": (n, 3),
            "scales": (n, 3),
            "quats": (n, 4),
            "opacities": (n,),
        }
        for name, shape in expected.items():
            arr = np.ascontiguousarray(getattr(self, name), dtype=np.float32)
            if arr.shape != shape or n < 0:
                raise GaussiansError(f"{name} must have shape {shape}, got {arr.shape}")
            object.__setattr__(self, name, arr)
        sh = np.ascontiguousarray(self.sh, dtype=np.float32)
        if sh.ndim == 2 and sh.shape == (n, 3):
            sh = sh[:, None, :]
        k = sh.shape[1] if sh.ndim == 3 else 0
        if sh.ndim != 3 or sh.shape[0] != n or sh.shape[2] != 3 or k not in (1, 4, 9, 16):
            raise GaussiansError(f"sh must have shape (N, K, 3) with K in 1, 4, 9, 16; got {sh.shape}")
        object.__setattr__(self, "sh", sh)

    # -- construction -----------------------------------------------------
    @classmethod
    def empty(cls, sh_degree: int = 0) -> "Gaussians":
        k = (sh_degree + 1) ** 2
        return cls(np.zeros((0, 3)), np.ones((0, 3)), np.tile([1.0, 0, 0, 0], (0, 1)), np.zeros(0), np.zeros((0, k, 3)))

    # -- views --------------------------------------------------------------
    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return int(round(np.sqrt(self.sh.shape[1]))) - 1

    @property
    def rgb(self) -> np.ndarray:
        """View-independent colour (SH DC only), (N, 3), not clamped."""
        return sh_dc_to_rgb(self.sh[:, 0, :])

    def covariances(self) -> np.ndarray:
        """World covariances (N, 3, 3) float64."""
        return covariance_from_scale_rotation(self.scales, self.quats)

    def subset(self, index) -> "Gaussians":
        """The Gaussians selected by a boolean mask or integer index array."""
        return Gaussians(*(getattr(self, f.name)[index] for f in fields(self)))

    def with_(self, **changes) -> "Gaussians":
        """A copy with some fields replaced (validated again)."""
        return replace(self, **changes)

    @staticmethod
    def concatenate(parts: "list[Gaussians]") -> "Gaussians":
        """All ``parts`` in order; SH bands a part lacks are zero. Each field is written once into its output."""
        if not parts:
            return Gaussians.empty()
        k = max(p.sh.shape[1] for p in parts)
        n = sum(len(p) for p in parts)
        out = {name: np.empty((n, *getattr(parts[0], name).shape[1:]), np.float32)
               for name in ("means", "scales", "quats", "opacities")}
        sh = np.empty((n, k, 3), np.float32)
        start = 0
        for p in parts:  # a loop over the parts (a few), not over Gaussians
            rows = slice(start, start + len(p))
            for name, arr in out.items():
                arr[rows] = getattr(p, name)
            kp = p.sh.shape[1]
            sh[rows, :kp] = p.sh
            sh[rows, kp:] = 0.0
            start = rows.stop
        return Gaussians(out["means"], out["scales"], out["quats"], out["opacities"], sh)

    def check_finite(self) -> None:
        """Raise :class:`GaussiansError` naming the first field with NaN/Inf or bad range."""
        for f in fields(self):
            arr = getattr(self, f.name)
            if not np.all(np.isfinite(arr)):
                raise GaussiansError(f"{f.name} contains NaN or Inf")
        if np.any(self.scales < 0):
            raise GaussiansError("scales must be non-negative")
        if np.any((self.opacities < 0) | (self.opacities > 1)):
            raise GaussiansError("opacities must lie in [0, 1]")
