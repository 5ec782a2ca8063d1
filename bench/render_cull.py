"""Pre-render culling for one camera: drop Gaussians a render cannot show.

What :func:`rasterizer.render.render` already skips (``rasterizer.splat``):
range below ``near`` (and z below it for a pinhole), non-finite projections,
footprint boxes wholly outside the image or the Yin/Yang grid's columns, and
Gaussians whose opacity is below 1/255 (footprint cut at ``opacity * g >=
1/255``); ``rasterizer.front_to_back`` also skips, chunk by chunk, boxes whose
pixels all reached T < 1e-4. It still projects every Gaussian (Jacobian, 2-D
covariance) for every camera (twice for an ERP via Yin-Yang) and enumerates
and sorts the footprints of Gaussians behind surfaces that are dense but not
yet at T < 1e-4, which cost as much as visible ones although the compositor
gives them little weight.

:func:`cull_for_camera` adds, as an index the caller passes to ``subset``:

* the near test and, for pinhole / Yin / Yang cameras, a frustum / domain
  test of the centre widened by the Gaussian's 3-sigma angular radius;
* occlusion: on a coarse ERP grid of cells around the camera, Gaussians are
  accumulated front to back as optical depth ``tau = sum opacity * (projected
  Gaussian integral) / (cell solid angle)``. Since ``-log T >= sum alpha``
  per pixel, a cell is opaque (T <= exp(-tau_cut)) at the range ``r*`` where
  tau reaches ``tau_cut``. A Gaussian is culled when its range exceeds
  ``(1 + range_margin)`` times the *largest* ``r*`` of the 3x3 cells around
  its own, so partly covered cells at silhouettes never cull what shows
  beside an edge.
"""

from __future__ import annotations

import numpy as np

from rasterizer import geometry as geo
from rasterizer.camera import DEFAULT_NEAR
from rasterizer.gaussians import Gaussians, quat_to_rotmat

#: Optical depth at which a cell counts as opaque: T <= exp(-7) ~ 1e-3.
DEFAULT_TAU_CUT = 7.0


def _angular_radius(gaussians: Gaussians, ranges: np.ndarray) -> np.ndarray:
    """(N,) 3-sigma angular radius (radians) of each Gaussian seen from ``ranges``."""
    smax = gaussians.scales.max(axis=1).astype(np.float64)
    return np.arctan2(3.0 * smax, np.maximum(ranges, 1e-12))


def _in_view(p_cam: np.ndarray, ranges: np.ndarray, radius: np.ndarray, projection: str,
             width: int, height: int, fov_deg: float, near: float) -> np.ndarray:
    """(N,) bool: the widened centre lies inside the camera's image / domain."""
    if projection == "erp":
        return np.ones(p_cam.shape[0], dtype=bool)
    if projection == "perspective":
        fx, fy, cx, cy = geo.pinhole_intrinsics(width, height, fov_deg)
        z = p_cam[:, 2]
        ok = z >= near
        col, row = geo.pinhole_project(p_cam, fx, fy, cx, cy)
        # a sphere of angular radius a around the ray: widen by the worst-case pixel growth
        grow = np.tan(np.minimum(radius, 1.5)) * fx * (1.0 + (np.abs(col - cx) / fx) ** 2 + (np.abs(row - cy) / fy) ** 2)
        ok &= (col >= -0.5 - grow) & (col <= width - 0.5 + grow)
        ok &= (row >= -0.5 - grow) & (row <= height - 0.5 + grow)
        return ok
    lat, lon = geo.lat_lon_from_direction(geo.to_grid_frame(projection, p_cam))
    cl = np.maximum(np.cos(lat), 1e-6)
    return (np.abs(lat) <= geo.YIN_LAT_MAX + radius) & (np.abs(lon) <= geo.YIN_LON_MAX + radius / cl)


def occluded(gaussians: Gaussians, c2w: np.ndarray, p_cam: np.ndarray, ranges: np.ndarray, candidates: np.ndarray, *,
             cells: tuple[int, int] | None = None, tau_cut: float = DEFAULT_TAU_CUT,
             range_margin: float = 0.05) -> np.ndarray:
    """(N,) bool: Gaussians (among ``candidates``) hidden behind opaque cells (module docstring).

    ``cells`` (rows, cols) of the ERP cell grid; default: about 8 Gaussians
    per cell (sqrt(N / 64) rows, at most 128), so cells are not
    empty between neighbouring centres.
    """
    n = p_cam.shape[0]
    out = np.zeros(n, dtype=bool)
    idx = np.flatnonzero(candidates)
    if idx.size == 0:
        return out
    if cells is None:
        hc = int(np.clip(np.sqrt(idx.size / 64.0), 2, 128))
        cells = (hc, 2 * hc)
    hc, wc = cells
    lat, lon = geo.lat_lon_from_direction(p_cam[idx])
    cr = np.clip(np.floor((np.pi / 2 - lat) / np.pi * hc), 0, hc - 1).astype(np.int64)
    cc = np.mod(np.floor((lon + np.pi) / (2 * np.pi) * wc), wc).astype(np.int64)
    cell = cr * wc + cc
    r = ranges[idx]
    # projected integral of opacity * Gaussian: 2 pi s1 s2 |cos| / r^2 (solid angle), s1, s2 the disc axes
    rot = quat_to_rotmat(gaussians.quats[idx])
    s = gaussians.scales[idx].astype(np.float64)
    order_s = np.argsort(s, axis=1)
    normal = np.take_along_axis(rot, order_s[:, None, :1], axis=2)[:, :, 0]  # axis of the smallest scale
    normal = normal @ np.asarray(c2w)[:3, :3]  # world -> camera frame (row vectors)
    ray = p_cam[idx] / np.maximum(r, 1e-12)[:, None]
    s_sorted = np.take_along_axis(s, order_s, axis=1)
    mass = gaussians.opacities[idx].astype(np.float64) * 2 * np.pi * s_sorted[:, 1] * s_sorted[:, 2] / r ** 2
    mass *= np.abs(np.einsum("ij,ij->i", normal, ray))
    cell_lat = np.pi / 2 - (np.arange(hc) + 0.5) / hc * np.pi
    omega = (2 * np.pi / wc) * (np.pi / hc) * np.cos(cell_lat)
    tau = mass / omega[cr]
    order = np.lexsort((r, cell))
    cell_s, tau_s, r_s = cell[order], tau[order], r[order]
    csum = np.cumsum(tau_s)
    first = np.ones(order.size, dtype=bool)
    first[1:] = cell_s[1:] != cell_s[:-1]
    starts = np.flatnonzero(first)
    seg = np.cumsum(first) - 1
    base = np.concatenate([[0.0], csum[starts[1:] - 1]]) if starts.size > 1 else np.zeros(1)
    incl = csum - base[seg]
    opaque_at = np.full(hc * wc, np.inf)
    hit = incl >= tau_cut
    # first opaque entry per cell: ranges ascend within a cell, so take the min range among hits
    np.minimum.at(opaque_at, cell_s[hit], r_s[hit])
    grid = opaque_at.reshape(hc, wc)
    pad = np.concatenate([grid[:1], grid, grid[-1:]], axis=0)
    pad = np.concatenate([pad[:, -1:], pad, pad[:, :1]], axis=1)
    worst = np.max(np.stack([pad[dy:dy + hc, dx:dx + wc] for dy in range(3) for dx in range(3)]), axis=0)
    out[idx] = r > (1.0 + range_margin) * worst.reshape(-1)[cell]
    return out


def cull_for_camera(gaussians: Gaussians, c2w, projection: str = "erp", *, width: int, height: int | None = None,
                    fov_deg: float = 90.0, near: float = DEFAULT_NEAR, occlusion: bool = True,
                    cells: tuple[int, int] | None = None, tau_cut: float = DEFAULT_TAU_CUT,
                    range_margin: float = 0.05) -> np.ndarray:
    """Ascending indices of the Gaussians a render of this camera may show.

    Same camera arguments as :func:`rasterizer.render.render`; ``occlusion``
    switches the opaque-cell test off. Render ``gaussians.subset(index)``.
    """
    c2w = geo.as_c2w(c2w)
    width = int(width)
    if height is None:
        height = {"erp": width // 2, "yin": width // 3, "yang": width // 3}.get(projection, width)
    p_cam = geo.world_to_camera(gaussians.means.astype(np.float64), c2w)
    ranges = np.linalg.norm(p_cam, axis=1)
    keep = ranges >= near
    keep &= _in_view(p_cam, ranges, _angular_radius(gaussians, ranges), projection, width, int(height),
                     fov_deg, near)
    if occlusion:
        # occluders are every Gaussian in front (also outside the view), candidates only those kept
        hidden = occluded(gaussians, c2w, p_cam, ranges, ranges >= near, cells=cells, tau_cut=tau_cut,
                          range_margin=range_margin)
        keep &= ~hidden
    return np.flatnonzero(keep)
