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
from .select import select, select_many

#: Head defaults = the encoder's (export/config.py).
_CFG = EncoderConfig()


#: A 3-vector field as three component planes (x, y, z), each (2, G, H, W). onnxruntime's elementwise
#: kernels run fastest on contiguous planes; on (..., 3) tensors the last-axis reductions, broadcasts and
#: concatenations cost several times the arithmetic itself (docs/design.md, "The encoder").
Vec = tuple[torch.Tensor, torch.Tensor, torch.Tensor]


def _dot(a: Vec, b: Vec) -> torch.Tensor:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross(a: Vec, b: Vec) -> Vec:
    return a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]


def _scaled(v: Vec, k: torch.Tensor) -> Vec:
    return v[0] * k, v[1] * k, v[2] * k


def _divided(v: Vec, k: torch.Tensor) -> Vec:
    return v[0] / k, v[1] / k, v[2] / k


def _steps(p: Vec, facing: Vec, dim: int, max_stretch: float) -> Vec:
    """Surface step along grid axis ``dim`` (3 = columns, 2 = rows) of points p: see the module docstring."""
    n = p[0].shape[dim]
    fwd = tuple(x.narrow(dim, 1, n - 1) - x.narrow(dim, 0, n - 1) for x in p)
    lf = _dot(fwd, fwd)
    pad = torch.zeros_like(lf.narrow(dim, 0, 1))
    far = pad + SURFEL_BORDER_STEP2
    fwd_p = tuple(torch.cat([x, pad], dim) for x in fwd)  # step to the next pixel
    bwd_p = tuple(torch.cat([pad, x], dim) for x in fwd)  # step from the previous one
    lf_p, lb_p = torch.cat([lf, far], dim), torch.cat([far, lf], dim)
    limit = _dot(facing, facing) * (max_stretch * max_stretch)
    ok_f, ok_b = lf_p <= limit, lb_p <= limit
    one = select_many(lf_p <= lb_p, fwd_p, bwd_p)
    step = select_many(ok_f & ok_b, tuple(0.5 * (f + b) for f, b in zip(fwd_p, bwd_p)), one)
    return select_many(ok_f | ok_b, step, facing)


def surfel_frames(a: Vec, b: Vec, facing_a: Vec, facing_b: Vec, scale_factor: float, ray_scale_ratio: float):
    """Steps a, b -> principal axes (u1, u2, n), each a :data:`Vec`, and scales (s1, s2, s3) planes.

    Covariance = scale_factor^2 (a a^T + b b^T) + (ray_scale_ratio * smaller sigma)^2 n n^T;
    nearly parallel steps (sin < 0.05) fall back to the facing steps.
    """
    n = _cross(a, b)
    flat = _dot(n, n) <= 0.0025 * _dot(a, a) * _dot(b, b)
    ab = select_many(flat, facing_a + facing_b, a + b)
    a, b = ab[:3], ab[3:]
    n = _cross(a, b)
    n = _divided(n, torch.sqrt(_dot(n, n)).clamp(min=1e-30))
    la = torch.sqrt(_dot(a, a)).clamp(min=1e-30)
    e1 = _divided(a, la)
    e2 = _cross(n, e1)
    b1, b2 = _dot(b, e1), _dot(b, e2)
    # in-plane covariance [[p, q], [q, s]] in (e1, e2), closed-form eigen-decomposition
    p, q, s = la * la + b1 * b1, b1 * b2, b2 * b2
    half = 0.5 * (p - s)
    d = torch.sqrt(half * half + q * q)
    mean = 0.5 * (p + s)
    cos2 = select(d > 1e-12 * mean, half / d.clamp(min=1e-30), 1.0)
    cos = torch.sqrt((0.5 * (1.0 + cos2)).clamp(min=0.0))
    sin = torch.sqrt((0.5 * (1.0 - cos2)).clamp(min=0.0)) * (1.0 - 2.0 * (q < 0).to(q.dtype))
    u1 = tuple(cos * x + sin * y for x, y in zip(e1, e2))
    u2 = _cross(n, u1)
    s1 = scale_factor * torch.sqrt(mean + d)
    s2 = scale_factor * torch.sqrt((mean - d).clamp(min=0.0))
    return (u1, u2, n), (s1, s2, ray_scale_ratio * torch.minimum(s1, s2))


def rotmat_to_quat(axes) -> tuple[torch.Tensor, ...]:
    """Rotations given by their columns (three :data:`Vec`) -> unit (w, x, y, z) planes, w >= 0 (the branch of
    the largest diagonal term, as :func:`rasterizer.gaussians.rotmat_to_quat`)."""
    def m(i, j):
        return axes[j][i]
    m00, m11, m22 = m(0, 0), m(1, 1), m(2, 2)
    trace = m00 + m11 + m22
    d21, d02, d10 = m(2, 1) - m(1, 2), m(0, 2) - m(2, 0), m(1, 0) - m(0, 1)
    s01, s02, s12 = m(0, 1) + m(1, 0), m(0, 2) + m(2, 0), m(1, 2) + m(2, 1)
    cand = [(1 + trace, d21, d02, d10), (d21, 1 + m00 - m11 - m22, s01, s02),
            (d02, s01, 1 - m00 + m11 - m22, s12), (d10, s02, s12, 1 - m00 - m11 + m22)]
    q, best = cand[0], trace
    for c, v in zip(cand[1:], (m00, m11, m22)):
        q = select_many(v > best, c, q)
        best = torch.maximum(best, v)
    norm = torch.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).clamp(min=1e-30)
    q = tuple(x / norm for x in q)
    return select_many(q[0] < 0, tuple(-x for x in q), q)


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
            field = np.stack([s[i] for s in steps]).astype(np.float32)  # (G, H, W, 3)
            if name == "rays":  # the (G, H, W, 3) rays, for the encoder's floor clamp and matches
                self.register_buffer(name, torch.from_numpy(field), persistent=False)
            for c in range(3):  # component planes (G, H, W) for the planar maths
                self.register_buffer(f"{name}_{c}", torch.from_numpy(np.ascontiguousarray(field[..., c])),
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

    def forward(self, rng, conf, colour, c2w, cam_quats):
        rot = c2w[:, :3, :3]  # (2, 3, 3)
        centre = c2w[:, :3, 3]  # (2, 3)
        plane = lambda name: tuple(getattr(self, f"{name}_{c}") for c in range(3))  # noqa: E731
        pts = _scaled(plane("rays"), rng)  # camera frame
        fa, fb = _scaled(plane("east"), rng), _scaled(plane("south"), rng)  # camera-facing pixel steps
        a = _steps(pts, fa, 3, self.max_stretch)
        b = _steps(pts, fb, 2, self.max_stretch)
        axes, scales = surfel_frames(a, b, fa, fb, self.scale_factor, self.ray_scale_ratio)
        c = conf.clamp(0.0, 1.0)
        if self.confident_shrink:
            scales = _scaled(scales, 1.0 - self.confident_shrink * c)
        # camera frame -> world: one flat (N, 3) x (3, 3) GEMM per view
        means = centre.reshape(2, 1, 3) + torch.matmul(torch.stack(pts, -1).reshape(2, -1, 3), rot.transpose(1, 2))
        # camera-frame surfel rotation, turned to the world by the camera quaternion (one MatMul)
        local = torch.stack(rotmat_to_quat(axes), -1)
        quats = torch.matmul(local.reshape(2, -1, 4), quat_left_matrix(cam_quats).transpose(1, 2))
        if self.opacity_gamma == 2.0:
            c = c * c
        elif self.opacity_gamma != 1.0:
            c = torch.pow(c, self.opacity_gamma)
        opac = self.opacity_min + (self.opacity_max - self.opacity_min) * c
        sh_dc = (colour.permute(0, 1, 3, 4, 2) - 0.5) / SH_C0
        return (means.reshape(-1, 3), torch.stack(scales, -1).reshape(-1, 3), quats.reshape(-1, 4),
                opac.reshape(-1), sh_dc.reshape(-1, 3))
