"""Pixel-aligned Gaussians from an image and its range map (one Gaussian per pixel).

Each pixel with range r > 0 of an ERP, Yin or Yang grid becomes a Gaussian
at ``centre + r * ray`` (world frame) whose tangential standard deviations
are ``scale_factor`` times the pixel's angular pitch times r (the longitude
pitch shrinks by cos(lat)), and whose standard deviation along the ray is
``thickness`` times the smaller tangential one (a flat disc facing the
camera). Colour is the pixel's RGB as SH DC, opacity ``opacity``.

With ``surfels=True`` (what the encoder's head builds, the numpy twin of
:class:`export.gaussian_head.GaussianHead`) each Gaussian is instead a
surfel spanning the surface steps to its neighbouring pixels
(:func:`surfel_shapes`): covariance ``scale_factor^2 (a a^T + b b^T)`` plus
``thickness`` of the smaller sigma along the normal, so that opaque
neighbours overlap on the surface at any incidence, and never across a
depth step (there the camera-facing step is used).

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
#: Surfels (the encoder's head): in-plane sigma in units of the neighbour step.
SURFEL_SCALE_FACTOR = 0.7
#: Surfels: a neighbour step longer than this many camera-facing pixel steps is a depth step
#: (or a grazing surface); the surfel then takes the other side's step, or the facing one.
SURFEL_MAX_STRETCH = 4.0
#: Squared step length assigned beyond a grid border (that side never wins).
SURFEL_BORDER_STEP2 = 1e30


def _steps(p: np.ndarray, facing: np.ndarray, axis: int, max_stretch: float) -> np.ndarray:
    """Surface step (H, W, 3) along grid ``axis`` (1 = columns, 0 = rows) of points p (H, W, 3).

    Central difference where both neighbours are within ``max_stretch``
    facing steps, else the shorter one-sided step if it is, else ``facing``.
    """
    fwd = np.diff(p, axis=axis)
    lf = np.einsum("...k,...k->...", fwd, fwd)[..., None]
    shape = list(fwd.shape)
    shape[axis] = 1
    pad, far = np.zeros(shape), np.full(shape[:-1] + [1], SURFEL_BORDER_STEP2)
    fwd_p, lf_p = np.concatenate([fwd, pad], axis), np.concatenate([lf, far], axis)
    bwd_p, lb_p = np.concatenate([pad, fwd], axis), np.concatenate([far, lf], axis)
    limit = np.einsum("...k,...k->...", facing, facing)[..., None] * max_stretch**2
    ok_f, ok_b = lf_p <= limit, lb_p <= limit
    one = np.where(lf_p <= lb_p, fwd_p, bwd_p)
    step = np.where(ok_f & ok_b, 0.5 * (fwd_p + bwd_p), one)
    return np.where(ok_f | ok_b, step, facing)


def surfel_shapes(points: np.ndarray, facing_a: np.ndarray, facing_b: np.ndarray, *,
                  scale_factor: float = SURFEL_SCALE_FACTOR, thickness: float = DEFAULT_THICKNESS,
                  max_stretch: float = SURFEL_MAX_STRETCH) -> tuple[np.ndarray, np.ndarray]:
    """Principal axes (H, W, 3, 3) (columns u1, u2, normal) and scales (H, W, 3) of pixel surfels.

    points: (H, W, 3) 3-D points of a grid's pixels; facing_a / facing_b:
    (H, W, 3) camera-facing steps to the next column / row (pixel pitch x
    range), all in one frame and unit. Steps a, b from :func:`_steps`; nearly
    parallel steps (sin < 0.05) fall back to the facing ones.
    """
    a = _steps(points, facing_a, 1, max_stretch)
    b = _steps(points, facing_b, 0, max_stretch)
    n = np.cross(a, b)
    dot = lambda u, v: np.einsum("...k,...k->...", u, v)[..., None]  # noqa: E731
    flat = dot(n, n) <= 0.0025 * dot(a, a) * dot(b, b)
    a, b = np.where(flat, facing_a, a), np.where(flat, facing_b, b)
    n = np.cross(a, b)
    n = n / np.maximum(np.sqrt(dot(n, n)), 1e-30)
    la = np.maximum(np.sqrt(dot(a, a)), 1e-30)
    e1 = a / la
    e2 = np.cross(n, e1)
    b1, b2 = dot(b, e1), dot(b, e2)
    p, q, s = la * la + b1 * b1, b1 * b2, b2 * b2  # in-plane covariance [[p, q], [q, s]] in (e1, e2)
    half, mean = 0.5 * (p - s), 0.5 * (p + s)
    d = np.sqrt(half * half + q * q)
    cos2 = np.where(d > 1e-12 * mean, half / np.maximum(d, 1e-30), 1.0)
    cos = np.sqrt(np.maximum(0.5 * (1.0 + cos2), 0.0))
    sin = np.sqrt(np.maximum(0.5 * (1.0 - cos2), 0.0)) * np.where(q < 0, -1.0, 1.0)
    u1 = cos * e1 + sin * e2
    u2 = np.cross(n, u1)
    s1 = scale_factor * np.sqrt(mean + d)
    s2 = scale_factor * np.sqrt(np.maximum(mean - d, 0.0))
    scales = np.concatenate([s1, s2, thickness * np.minimum(s1, s2)], axis=-1)
    return np.stack([u1, u2, n], axis=-1), scales


def _grid_angles(grid: str, height: int, width: int):
    """Per-pixel (lat, lon) in the grid's own frame and the (lat, lon) pitches (radians)."""
    if grid == "erp":
        lat, lon = geo.erp_lat_lon(height, width)
        return lat, lon, np.pi / height, 2 * np.pi / width
    if grid in ("yin", "yang"):
        lat, lon = geo.yin_lat_lon(height, width)
        return lat, lon, 2 * geo.YIN_LAT_MAX / height, 2 * geo.YIN_LON_MAX / width
    raise ValueError(f"grid must be 'erp', 'yin' or 'yang', got {grid!r}")


def pixel_steps(grid: str, height: int, width: int):
    """Camera-frame rays and camera-facing pixel steps of a grid, each (H, W, 3) float64.

    east = d ray / d column (longitude pitch x cos(lat) along the local east
    axis), south = d ray / d row (latitude pitch along the local south axis);
    times the range they are the 3-D steps to the neighbouring pixels of a
    surface facing the camera. Yang grids are rotated by YANG_ROTATION.
    """
    lat, lon, dlat, dlon = _grid_angles(grid, height, width)
    lat, lon = np.broadcast_arrays(lat, lon)
    cl, sla, co, so = np.cos(lat), np.sin(lat), np.cos(lon), np.sin(lon)
    ray = np.stack([cl * so, -sla, cl * co], axis=-1)
    east = np.stack([co, np.zeros_like(co), -so], axis=-1) * (dlon * np.maximum(cl, 1e-6))[..., None]
    south = np.stack([sla * so, cl, sla * co], axis=-1) * dlat  # -d ray / d lat
    if grid == "yang":
        m = geo.YANG_ROTATION
        ray, east, south = ray @ m.T, east @ m.T, south @ m.T
    return ray, east, south


def gaussians_from_depth(image: np.ndarray, depth: np.ndarray, c2w, grid: str = "erp", *,
                         scale_factor: float | None = None, thickness: float = DEFAULT_THICKNESS,
                         opacity: float = 1.0, stride: int = 1, surfels: bool = False,
                         max_stretch: float = SURFEL_MAX_STRETCH) -> Gaussians:
    """One Gaussian per pixel of ``image`` (H, W, 3) in [0, 1] with range ``depth`` (H, W).

    ``grid`` names the layout of both arrays ("erp", "yin" or "yang"; Yang
    images in the landscape Yin-like layout of :mod:`rasterizer.geometry`).
    ``c2w`` is the 4x4 OpenCV pose of the panorama. Pixels with depth <= 0 or
    non-finite are skipped. ``stride`` > 1 keeps every stride-th row and
    column (a sparser set with proportionally larger Gaussians). ``surfels``:
    oriented surfels (:func:`surfel_shapes`, ``max_stretch``) instead of
    camera-facing discs; ``scale_factor`` then counts neighbour steps.
    Default ``scale_factor``: SURFEL_SCALE_FACTOR for surfels, else DEFAULT_SCALE_FACTOR.
    """
    if scale_factor is None:
        scale_factor = SURFEL_SCALE_FACTOR if surfels else DEFAULT_SCALE_FACTOR
    image = np.asarray(image, dtype=np.float32)
    depth = np.asarray(depth, dtype=np.float64)
    if image.ndim != 3 or image.shape[2] != 3 or image.shape[:2] != depth.shape:
        raise ValueError(f"image must be (H, W, 3) and depth (H, W) of the same size; got {image.shape}, {depth.shape}")
    c2w = geo.as_c2w(c2w)
    height, width = depth.shape
    depth_g = depth
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
    means = c2w[:3, 3] + r[:, None] * (ray @ rot_w.T)
    if surfels:
        ray_g, east, south = pixel_steps(grid, height, width)
        r_g = np.where(np.isfinite(depth_g) & (depth_g > 0), depth_g, 0.0)[..., None]
        axes, scales = surfel_shapes((r_g * ray_g)[sl], (r_g * east * stride)[sl], (r_g * south * stride)[sl],
                                     scale_factor=scale_factor, thickness=thickness, max_stretch=max_stretch)
        frame, scales = rot_w @ axes[ok], scales[ok]
    else:
        # local axes (columns) e_lon, e_down, ray form a proper rotation (e_lon x e_down = ray)
        frame = np.stack([e_lon @ rot_w.T, e_down @ rot_w.T, ray @ rot_w.T], axis=2)
        s_lon = scale_factor * stride * dlon * np.maximum(cl, 1e-6) * r
        s_lat = scale_factor * stride * dlat * r
        scales = np.stack([s_lon, s_lat, thickness * np.minimum(s_lon, s_lat)], axis=1)
    return Gaussians(
        means=means,
        scales=scales,
        quats=rotmat_to_quat(frame),
        opacities=np.full(r.shape[0], opacity, dtype=np.float32),
        sh=rgb_to_sh_dc(rgb)[:, None, :],
    )
