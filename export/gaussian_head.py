"""One world-space Gaussian per Yin / Yang (or ERP) pixel of both views.

* mean = camera centre + range * (R_c2w ray);
* scales: the pixel's angular footprint times range and ``scale_factor``
  along the image's longitude and latitude axes (longitude pitch times
  cos(lat)), and ``ray_scale_ratio`` of the smaller one along the ray (a
  flat disc facing the camera);
* orientation: local axes (east, south, ray) of the pixel, rotated to the
  world by the camera quaternion (w, x, y, z);
* opacity = opacity_min + (opacity_max - opacity_min) * confidence ** opacity_gamma
  (a steep curve with a low floor: confident pixels dominate the blend,
  unconfident ones - epipoles, rejected and filled pixels - still fill holes
  no confident pixel covers);
* colour as SH DC of the pixel colour.

Per-pixel constants (rays, local quaternions, footprints) are computed in
numpy from :mod:`rasterizer.geometry` at export and stored in the graph.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from rasterizer.gaussians import SH_C0, rotmat_to_quat
from rasterizer.geometry import YANG_ROTATION, erp_lat_lon, yin_lat_lon


def pixel_frames(kind: str, height: int, width: int):
    """Camera-frame rays (h, w, 3), local (w, x, y, z) quats (h, w, 4), footprints (h, w, 2) rad."""
    if kind == "erp":
        lat, lon = erp_lat_lon(height, width)
        dlon, dlat = 2 * np.pi / width, np.pi / height
    else:
        lat, lon = yin_lat_lon(height, width)
        dlon, dlat = 1.5 * np.pi / width, 0.5 * np.pi / height
    lat, lon = np.broadcast_arrays(lat, lon)
    cl, sl, co, so = np.cos(lat), np.sin(lat), np.cos(lon), np.sin(lon)
    ray = np.stack([cl * so, -sl, cl * co], -1)
    east = np.stack([co, np.zeros_like(co), -so], -1)
    south = np.stack([sl * so, cl, sl * co], -1)  # -d ray / d lat: image "down"
    frame = np.stack([east, south, ray], -1)  # columns: local x, y, z
    if kind == "yang":
        frame = YANG_ROTATION @ frame
        ray = ray @ YANG_ROTATION.T
    quats = rotmat_to_quat(frame.reshape(-1, 3, 3)).reshape(height, width, 4)
    foot = np.stack([np.maximum(cl, 1e-3) * dlon, np.full_like(cl, dlat)], -1)
    return ray.astype(np.float32), quats.astype(np.float32), foot.astype(np.float32)


def quat_left_matrix(q: torch.Tensor) -> torch.Tensor:
    """(..., 4) (w, x, y, z) -> (..., 4, 4) L with q * p = L @ p (Hamilton product)."""
    w, x, y, z = q.unbind(-1)
    rows = [torch.stack(r, dim=-1) for r in ((w, -x, -y, -z), (x, w, -z, y), (y, z, w, -x), (z, -y, x, w))]
    return torch.stack(rows, dim=-2)


class GaussianHead(nn.Module):
    """range, confidence (2, G, H, W), colour (2, G, 3, H, W), c2w (2,4,4), cam_quats (2,4)
    -> means, scales, quats, opacities, sh_dc, each (N, k) with N = 2 G H W in
    [view][grid][row][col] order."""

    def __init__(self, grids, height: int, width: int, scale_factor: float = 0.5,
                 ray_scale_ratio: float = 0.1, opacity_min: float = 0.15, opacity_max: float = 0.98,
                 opacity_gamma: float = 2.0) -> None:
        super().__init__()
        frames = [pixel_frames(k, height, width) for k in grids]
        self.register_buffer("rays", torch.from_numpy(np.stack([f[0] for f in frames])), persistent=False)
        self.register_buffer("local_quats", torch.from_numpy(np.stack([f[1] for f in frames])), persistent=False)
        self.register_buffer("footprint", torch.from_numpy(np.stack([f[2] for f in frames])), persistent=False)
        self.scale_factor = float(scale_factor)
        self.ray_scale_ratio = float(ray_scale_ratio)
        self.opacity_min = float(opacity_min)
        self.opacity_max = float(opacity_max)
        self.opacity_gamma = float(opacity_gamma)

    def forward(self, rng, conf, colour, c2w, cam_quats):
        rot = c2w[:, :3, :3]  # (2, 3, 3)
        centre = c2w[:, :3, 3]  # (2, 3)
        g, h, w = self.rays.shape[:3]
        rays_w = torch.matmul(self.rays.reshape(1, g * h * w, 3), rot.transpose(1, 2)).reshape(2, g, h, w, 3)
        means = centre[:, None, None, None, :] + rng.unsqueeze(-1) * rays_w
        foot = self.footprint.unsqueeze(0) * (self.scale_factor * rng).unsqueeze(-1)  # (2, G, H, W, 2)
        along = foot.amin(dim=-1, keepdim=True) * self.ray_scale_ratio
        scales = torch.cat([foot, along], dim=-1)
        # camera rotation times local frame as one MatMul (2, GHW, 4): per-pixel constants stay one
        # (G, H, W, 4) tensor instead of 16 folded broadcast products
        quats = torch.matmul(self.local_quats.reshape(1, g * h * w, 4), quat_left_matrix(cam_quats).transpose(1, 2))
        c = conf.clamp(0.0, 1.0)
        if self.opacity_gamma == 2.0:
            c = c * c
        elif self.opacity_gamma != 1.0:
            c = torch.pow(c, self.opacity_gamma)
        opac = self.opacity_min + (self.opacity_max - self.opacity_min) * c
        sh_dc = (colour.permute(0, 1, 3, 4, 2) - 0.5) / SH_C0
        return (means.reshape(-1, 3), scales.reshape(-1, 3), quats.reshape(-1, 4),
                opac.reshape(-1), sh_dc.reshape(-1, 3))
