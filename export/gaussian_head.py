"""One world-space surfel (flat Gaussian) per Yin / Yang (or ERP) pixel of both views.

* mean = camera centre + range * (R_c2w ray);
* shape: the surface steps to the neighbouring pixels. ``a`` (next column)
  and ``b`` (next row) are central differences of the 3-D points of the range
  map; where one side jumps (longer than ``max_stretch`` camera-facing pixel
  steps: a depth discontinuity or a grazing surface) the other side is used,
  and where both do the camera-facing step (pixel pitch x range along the
  image's east / south axes, longitude pitch times cos(lat)). The in-plane
  covariance is ``scale_factor^2 (a a^T + b b^T)`` (neighbours overlap as a
  lattice; seen from the reference it is the pixel footprint, at any
  incidence), the normal ``a x b`` gets ``ray_scale_ratio`` of the smaller
  in-plane sigma. A surfel never stretches across a depth step.
* orientation: the eigenvectors of that covariance (closed-form 2x2
  eigen-decomposition in the plane of a and b), as a (w, x, y, z) quaternion;
* opacity = opacity_min + (opacity_max - opacity_min) * confidence ** opacity_gamma
  with a high floor: the fill's geometric fallback depth is drawn opaque
  instead of translucent, so plain front-to-back compositing covers the scene;
* colour as SH DC of the pixel colour.

Per-pixel constants (rays, east / south steps) are computed in numpy from
:mod:`rasterizer.geometry` at export and stored in the graph; the numpy twin
is :func:`rasterizer.depth_gaussians.surfel_shapes`.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from rasterizer.depth_gaussians import SURFEL_BORDER_STEP2, pixel_steps
from rasterizer.gaussians import SH_C0

from .config import EncoderConfig

#: Head defaults = the encoder's (export/config.py).
_CFG = EncoderConfig()


def _dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a * b).sum(-1, keepdim=True)


def _where(cond: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``torch.where`` of a (..., 1) condition over (..., k) values, the condition repeated k times first:
    onnxruntime's Where broadcasting over a last axis of 3 or 4 costs about twice the Concat and the plain Where."""
    return torch.where(torch.cat([cond] * a.shape[-1], dim=-1), a, b)


def _cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    a0, a1, a2 = a.unbind(-1)
    b0, b1, b2 = b.unbind(-1)
    return torch.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], dim=-1)


def _steps(p: torch.Tensor, facing: torch.Tensor, dim: int, max_stretch: float) -> torch.Tensor:
    """Surface step (..., 3) along grid axis ``dim`` of points p (..., H, W, 3): see the module docstring."""
    n = p.shape[dim]
    fwd = p.narrow(dim, 1, n - 1) - p.narrow(dim, 0, n - 1)
    lf = _dot(fwd, fwd)
    pad = torch.zeros_like(fwd.narrow(dim, 0, 1))
    far = pad[..., :1] + SURFEL_BORDER_STEP2
    fwd_p, lf_p = torch.cat([fwd, pad], dim), torch.cat([lf, far], dim)  # step to the next pixel
    bwd_p, lb_p = torch.cat([pad, fwd], dim), torch.cat([far, lf], dim)  # step from the previous one
    limit = _dot(facing, facing) * (max_stretch * max_stretch)
    ok_f, ok_b = lf_p <= limit, lb_p <= limit
    one = _where(lf_p <= lb_p, fwd_p, bwd_p)
    step = _where(ok_f & ok_b, 0.5 * (fwd_p + bwd_p), one)
    return _where(ok_f | ok_b, step, facing)


def surfel_frames(a: torch.Tensor, b: torch.Tensor, facing_a: torch.Tensor, facing_b: torch.Tensor,
                  scale_factor: float, ray_scale_ratio: float):
    """Steps a, b (..., 3) -> principal axes (..., 3, 3) (columns u1, u2, n) and scales (..., 3).

    Covariance = scale_factor^2 (a a^T + b b^T) + (ray_scale_ratio * smaller sigma)^2 n n^T;
    nearly parallel steps (sin < 0.05) fall back to the facing steps.
    """
    n = _cross(a, b)
    la, lb, ln = _dot(a, a), _dot(b, b), _dot(n, n)
    flat = ln <= 0.0025 * la * lb
    a, b = _where(flat, facing_a, a), _where(flat, facing_b, b)
    n = _cross(a, b)
    n = n / torch.sqrt(_dot(n, n)).clamp(min=1e-30)
    la = torch.sqrt(_dot(a, a)).clamp(min=1e-30)
    e1 = a / la
    e2 = _cross(n, e1)
    b1, b2 = _dot(b, e1), _dot(b, e2)
    # in-plane covariance [[p, q], [q, s]] in (e1, e2), closed-form eigen-decomposition
    p, q, s = la * la + b1 * b1, b1 * b2, b2 * b2
    half = 0.5 * (p - s)
    d = torch.sqrt(half * half + q * q)
    mean = 0.5 * (p + s)
    cos2 = torch.where(d > 1e-12 * mean, half / d.clamp(min=1e-30), torch.ones_like(d))
    cos = torch.sqrt((0.5 * (1.0 + cos2)).clamp(min=0.0))
    sin = torch.sqrt((0.5 * (1.0 - cos2)).clamp(min=0.0)) * torch.where(q < 0, -torch.ones_like(q), torch.ones_like(q))
    u1 = cos * e1 + sin * e2
    u2 = _cross(n, u1)
    s1 = scale_factor * torch.sqrt(mean + d)
    s2 = scale_factor * torch.sqrt((mean - d).clamp(min=0.0))
    scales = torch.cat([s1, s2, ray_scale_ratio * torch.minimum(s1, s2)], dim=-1)
    return torch.stack([u1, u2, n], dim=-1), scales


def rotmat_to_quat(r: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotations -> (..., 4) unit (w, x, y, z), w >= 0 (the branch of the largest diagonal term,
    as :func:`rasterizer.gaussians.rotmat_to_quat`)."""
    m00, m11, m22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
    trace = m00 + m11 + m22
    d21, d02, d10 = r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]
    s01, s02, s12 = r[..., 0, 1] + r[..., 1, 0], r[..., 0, 2] + r[..., 2, 0], r[..., 1, 2] + r[..., 2, 1]
    cand = [torch.stack(c, -1) for c in ((1 + trace, d21, d02, d10), (d21, 1 + m00 - m11 - m22, s01, s02),
                                         (d02, s01, 1 - m00 + m11 - m22, s12), (d10, s02, s12, 1 - m00 - m11 + m22))]
    q, best = cand[0], trace
    for c, v in zip(cand[1:], (m00, m11, m22)):
        gt = (v > best).unsqueeze(-1)
        q = _where(gt, c, q)
        best = torch.maximum(best, v)
    q = q / torch.sqrt((q * q).sum(-1, keepdim=True)).clamp(min=1e-30)
    return _where(q[..., :1] < 0, -q, q)


def quat_left_matrix(q: torch.Tensor) -> torch.Tensor:
    """(..., 4) (w, x, y, z) -> (..., 4, 4) L with q * p = L @ p (Hamilton product)."""
    w, x, y, z = q.unbind(-1)
    rows = [torch.stack(r, dim=-1) for r in ((w, -x, -y, -z), (x, w, -z, y), (y, z, w, -x), (z, -y, x, w))]
    return torch.stack(rows, dim=-2)


class GaussianHead(nn.Module):
    """range, confidence (2, G, H, W), colour (2, G, 3, H, W), c2w (2,4,4), cam_quats (2,4)
    -> means, scales, quats, opacities, sh_dc, each (N, k) with N = 2 G H W in
    [view][grid][row][col] order; ``cam_quats`` (w, x, y, z) are the rotations of ``c2w``.

    Footprint sigma: ``scale_factor`` neighbour steps at confidence 0, narrowing linearly to
    ``scale_factor_confident`` at confidence 1 (None: ``scale_factor`` everywhere)."""

    def __init__(self, grids, height: int, width: int, scale_factor: float = _CFG.scale_factor,
                 ray_scale_ratio: float = _CFG.ray_scale_ratio, opacity_min: float = _CFG.opacity_min,
                 opacity_max: float = _CFG.opacity_max, opacity_gamma: float = _CFG.opacity_gamma,
                 max_stretch: float = _CFG.max_stretch, scale_factor_confident: float | None = None) -> None:
        super().__init__()
        steps = [pixel_steps(k, height, width) for k in grids]
        for i, name in enumerate(("rays", "east", "south")):
            self.register_buffer(name, torch.from_numpy(np.stack([s[i] for s in steps]).astype(np.float32)),
                                 persistent=False)
        self.scale_factor = float(scale_factor)
        # footprint fraction dropped at confidence 1 (linear in confidence; None: one footprint for all)
        narrow = self.scale_factor if scale_factor_confident is None else float(scale_factor_confident)
        self.confident_shrink = 1.0 - narrow / self.scale_factor
        self.ray_scale_ratio = float(ray_scale_ratio)
        self.opacity_min = float(opacity_min)
        self.opacity_max = float(opacity_max)
        self.opacity_gamma = float(opacity_gamma)
        self.max_stretch = float(max_stretch)

    def forward(self, rng, conf, colour, c2w, cam_quats, opaque=None):
        """``opaque`` (2, G, H, W) in [0, 1], optional: moves each opacity that far to ``opacity_max``."""
        rot = c2w[:, :3, :3]  # (2, 3, 3)
        centre = c2w[:, :3, 3]  # (2, 3)
        r = rng.unsqueeze(-1)  # (2, G, H, W, 1)
        pts = r * self.rays  # camera frame
        fa, fb = r * self.east, r * self.south  # camera-facing pixel steps
        a = _steps(pts, fa, 3, self.max_stretch)
        b = _steps(pts, fb, 2, self.max_stretch)
        axes, scales = surfel_frames(a, b, fa, fb, self.scale_factor, self.ray_scale_ratio)
        c = conf.clamp(0.0, 1.0)
        if self.confident_shrink:  # opaque layout surfels get the confident footprint: sharp, the shell behind
            fp = c if opaque is None else torch.maximum(c, opaque)
            scales = scales * (1.0 - self.confident_shrink * fp).unsqueeze(-1)
        means = centre.reshape(2, 1, 1, 1, 3) + torch.matmul(pts.reshape(2, -1, 3), rot.transpose(1, 2)).reshape(pts.shape)
        # camera-frame surfel rotation, turned to the world by the camera quaternion (one MatMul)
        local = rotmat_to_quat(axes)
        quats = torch.matmul(local.reshape(2, -1, 4), quat_left_matrix(cam_quats).transpose(1, 2)).reshape(local.shape)
        if self.opacity_gamma == 2.0:
            c = c * c
        elif self.opacity_gamma != 1.0:
            c = torch.pow(c, self.opacity_gamma)
        opac = self.opacity_min + (self.opacity_max - self.opacity_min) * c
        if opaque is not None:
            opac = opac + opaque * (self.opacity_max - opac)
        sh_dc = (colour.permute(0, 1, 3, 4, 2) - 0.5) / SH_C0
        return (means.reshape(-1, 3), scales.reshape(-1, 3), quats.reshape(-1, 4),
                opac.reshape(-1), sh_dc.reshape(-1, 3))
