"""Pixel-aligned Gaussians from an image and its range map (one Gaussian per pixel).

Each pixel with range r > 0 of an ERP, Yin or Yang grid becomes a Gaussian
at ``centre + r * ray`` (world frame) whose tangential standard deviations
are ``scale_factor`` times the pixel's angular pitch times r (the longitude
pitch shrinks by cos(lat)), and whose standard deviation along the ray is
``thickness`` times the smaller tangential one (a flat disc facing the
camera). Colour is the pixel's RGB as SH DC, opacity ``opacity``.

This is the structure the OmniSplat encoder predicts, with the true depth:
rendering it at another pose gives the "oracle" image quality ceiling.
"""

from __future__ import annotations

import numpy as np

from . import geometry as geo
from .gaussians import Gaussians, rgb_to_sh_dc, rotmat_to_quat

#: Default tangential sigma in units of the pixel pitch. On m3d_bedroom (GT
#: depth, both references, rendered at the mid-point target) 0.2 / 0.35 / 0.5
#: / 0.8 gave 28.8 / 28.2 / 27.5 / 25.7 dB: small discs plus the 0.3 px^2
#: low-pass close the gaps there, and larger ones only blur (and cost more
#: footprint pixels). Self re-rendering needs ~0.02 to pass 40 dB.
DEFAULT_SCALE_FACTOR = 0.3
#: Default ray-direction sigma relative to the tangential one.
DEFAULT_THICKNESS = 0.1


def _grid_angles(grid: str, height: int, width: int):
    """Per-pixel (lat, lon) in the grid's own frame and the (lat, lon) pitches (radians)."""
    if grid == "erp":
        lat, lon = geo.erp_lat_lon(height, width)
        return lat, lon, np.pi / height, 2 * np.pi / width
    if grid in ("yin", "yang"):
        lat, lon = geo.yin_lat_lon(height, width)
        return lat, lon, 2 * geo.YIN_LAT_MAX / height, 2 * geo.YIN_LON_MAX / width
    raise ValueError(f"grid must be 'erp', 'yin' or 'yang', got {grid!r}")


def gaussians_from_depth(image: np.ndarray, depth: np.ndarray, c2w, grid: str = "erp", *,
                         scale_factor: float = DEFAULT_SCALE_FACTOR, thickness: float = DEFAULT_THICKNESS,
                         opacity: float = 1.0, stride: int = 1) -> Gaussians:
    """One Gaussian per pixel of ``image`` (H, W, 3) in [0, 1] with range ``depth`` (H, W).

    ``grid`` names the layout of both arrays ("erp", "yin" or "yang"; Yang
    images in the landscape Yin-like layout of :mod:`rasterizer.geometry`).
    ``c2w`` is the 4x4 OpenCV pose of the panorama. Pixels with depth <= 0 or
    non-finite are skipped. ``stride`` > 1 keeps every stride-th row and
    column (a sparser set with proportionally larger Gaussians).
    """
    image = np.asarray(image, dtype=np.float32)
    depth = np.asarray(depth, dtype=np.float64)
    if image.ndim != 3 or image.shape[2] != 3 or image.shape[:2] != depth.shape:
        raise ValueError(f"image must be (H, W, 3) and depth (H, W) of the same size; got {image.shape}, {depth.shape}")
    c2w = geo.as_c2w(c2w)
    height, width = depth.shape
    lat, lon, dlat, dlon = _grid_angles(grid, height, width)
    lat, lon = np.broadcast_arrays(lat, lon)
    sl = (slice(None, None, stride), slice(None, None, stride))
    lat, lon, depth, image = lat[sl], lon[sl], depth[sl], image[sl]
    ok = np.isfinite(depth) & (depth > 0)
    lat, lon, r, rgb = lat[ok], lon[ok], depth[ok], image[ok]
    cl, sla, co, so = np.cos(lat), np.sin(lat), np.cos(lon), np.sin(lon)
    ray = np.stack([cl * so, -sla, cl * co], axis=1)
    e_lon = np.stack([co, np.zeros_like(co), -so], axis=1)
    e_down = np.stack([sla * so, cl, sla * co], axis=1)  # -d ray / d lat
    if grid == "yang":
        m = geo.YANG_ROTATION
        ray, e_lon, e_down = ray @ m.T, e_lon @ m.T, e_down @ m.T
    rot_w = c2w[:3, :3]
    # local axes (columns) e_lon, e_down, ray form a proper rotation (e_lon x e_down = ray)
    frame = np.stack([e_lon @ rot_w.T, e_down @ rot_w.T, ray @ rot_w.T], axis=2)
    s_lon = scale_factor * stride * dlon * np.maximum(cl, 1e-6) * r
    s_lat = scale_factor * stride * dlat * r
    s_ray = thickness * np.minimum(s_lon, s_lat)
    means = c2w[:3, 3] + r[:, None] * (ray @ rot_w.T)
    return Gaussians(
        means=means,
        scales=np.stack([s_lon, s_lat, s_ray], axis=1),
        quats=rotmat_to_quat(frame),
        opacities=np.full(r.shape[0], opacity, dtype=np.float32),
        sh=rgb_to_sh_dc(rgb)[:, None, :],
    )
