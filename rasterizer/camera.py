"""Render cameras: one pose plus one pixel grid (ERP, Yin, Yang or pinhole).

A :class:`Camera` projects world points to continuous pixel coordinates
(col, row) with the pixel-centre convention of :mod:`rasterizer.geometry`
(centre of pixel (r, c) at coordinate (c, r)) and gives the analytic 2x3
Jacobian of that projection with respect to the *world* point, which is what
EWA splatting needs. All maths is float64 and elementwise on (N,) columns.

Column wrap: ERP columns are periodic with period W. Yin/Yang columns are
periodic too (a full turn of longitude is 4w/3 columns, an integer when
w = 3h), but only the first w columns of a period are image pixels. Pinhole
columns do not wrap.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from . import geometry as geo

Projection = Literal["erp", "yin", "yang", "perspective"]
PROJECTIONS = ("erp", "yin", "yang", "perspective")

#: Default near limit on range (world units): closer Gaussians are culled.
DEFAULT_NEAR = 1e-2


def camera_directions(kind: str, height: int, width: int, fov_deg: float = 90.0) -> np.ndarray:
    """Camera-frame unit ray of every pixel centre of a render, (H, W, 3): an ERP/Yin/Yang grid or a pinhole
    with horizontal field of view ``fov_deg``."""
    if kind == "perspective":
        return geo.pinhole_directions(width, height, fov_deg)
    return geo.grid_directions(kind, height, width)


def sample_erp(image: np.ndarray, col: np.ndarray, row: np.ndarray) -> np.ndarray:
    """Bilinear lookup of an ERP image (H, W, C) at continuous pixel coordinates (pixel centre c at c).

    Longitude wraps around the seam; latitude is clamped at the poles. Returns float32 (..., C).
    """
    h, w = image.shape[:2]
    c0 = np.floor(col)
    r0 = np.floor(row)
    fc = (col - c0)[..., None]
    fr = (row - r0)[..., None]
    c0 = c0.astype(np.int64)
    r0 = r0.astype(np.int64)
    c_a, c_b = c0 % w, (c0 + 1) % w
    r_a, r_b = np.clip(r0, 0, h - 1), np.clip(r0 + 1, 0, h - 1)
    top = image[r_a, c_a] * (1 - fc) + image[r_a, c_b] * fc
    bot = image[r_b, c_a] * (1 - fc) + image[r_b, c_b] * fc
    return (top * (1 - fr) + bot * fr).astype(np.float32)


@dataclass(frozen=True)
class Camera:
    """A posed camera with a pixel grid.

    kind: "erp" | "yin" | "yang" | "perspective"; width x height pixels;
    c2w: 4x4 OpenCV camera-to-world (float64); fov_deg: horizontal field of
    view of the pinhole camera (ignored otherwise); near: Gaussians with range
    below it (and pinhole Gaussians with z below it) are culled.
    """

    kind: str
    width: int
    height: int
    c2w: np.ndarray
    fov_deg: float = 90.0
    near: float = DEFAULT_NEAR

    def __post_init__(self) -> None:
        if self.kind not in PROJECTIONS:
            raise ValueError(f"projection must be one of {PROJECTIONS}, got {self.kind!r}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        if not (np.isfinite(self.near) and self.near > 0):
            raise ValueError(f"near must be a positive finite number, got {self.near}")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        object.__setattr__(self, "c2w", geo.as_c2w(self.c2w))
        if self.kind == "perspective":
            geo.pinhole_intrinsics(self.width, self.height, self.fov_deg)  # validates fov

    # -- frames ---------------------------------------------------------------
    @property
    def centre(self) -> np.ndarray:
        """Camera centre in world coordinates, (3,)."""
        return self.c2w[:3, 3]

    @property
    def world_to_camera_rotation(self) -> np.ndarray:
        """R_cw (3, 3): camera-frame vector = R_cw @ world vector."""
        return self.c2w[:3, :3].T

    def to_camera(self, points: np.ndarray) -> np.ndarray:
        """Camera-frame coordinates (N, 3) float64 of world points (N, 3).

        Same as :func:`rasterizer.geometry.world_to_camera`, written on columns
        (no BLAS call, which oversubscribes a shared 2-core box).
        """
        pts = np.asarray(points, dtype=np.float64)
        rot, t = self.c2w[:3, :3], self.c2w[:3, 3]
        d = [pts[:, j] - t[j] for j in range(3)]
        out = np.empty((pts.shape[0], 3))
        for k in range(3):
            out[:, k] = d[0] * rot[0, k] + d[1] * rot[1, k] + d[2] * rot[2, k]
        return out

    # -- projection -----------------------------------------------------------
    def project(self, p_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Continuous (col, row) of camera-frame points (N, 3)."""
        if self.kind == "perspective":
            fx, fy, cx, cy = geo.pinhole_intrinsics(self.width, self.height, self.fov_deg)
            return geo.pinhole_project(p_cam, fx, fy, cx, cy)
        return geo.project_to_grid(self.kind, p_cam, self.height, self.width)

    def jacobian(self, p_cam: np.ndarray) -> np.ndarray:
        """d(col, row)/d(world point), (N, 2, 3): the camera-frame Jacobian times R_cw."""
        if self.kind == "perspective":
            fx, fy, _, _ = geo.pinhole_intrinsics(self.width, self.height, self.fov_deg)
            jac = geo.pinhole_jacobian(p_cam, fx, fy)
        else:
            jac = geo.grid_jacobian(self.kind, p_cam, self.height, self.width)
        return self.jacobian_from_camera(jac)

    def jacobian_from_camera(self, jac: np.ndarray) -> np.ndarray:
        """Chain rule: camera-frame Jacobians (N, 2, 3) -> world-frame ones (times R_cw), elementwise."""
        rcw = self.world_to_camera_rotation
        out = np.empty(jac.shape)
        for i in range(2):
            j0, j1, j2 = jac[:, i, 0], jac[:, i, 1], jac[:, i, 2]
            for k in range(3):
                out[:, i, k] = j0 * rcw[0, k] + j1 * rcw[1, k] + j2 * rcw[2, k]
        return out

    # -- column wrap ----------------------------------------------------------
    @property
    def column_period(self) -> int | None:
        """Columns per full turn of longitude, or None when columns do not wrap."""
        if self.kind == "erp":
            return self.width
        if self.kind in ("yin", "yang") and (4 * self.width) % 3 == 0:
            return 4 * self.width // 3
        return None

    @property
    def period_start(self) -> int:
        """First integer column of the period that contains the image columns."""
        if self.kind in ("yin", "yang"):
            # lon = -pi sits at column -w/6 - 0.5
            return int(np.ceil(-self.width / 6.0 - 0.5))
        return 0
