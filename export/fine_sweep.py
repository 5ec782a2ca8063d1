"""Second, finer sweep around the coarse depth (a cascade stage, CasMVSNet-style).

The coarse sweep resolves inverse range to one plane step on a grid
``downscale`` times smaller than the Gaussians. This stage re-matches at a
finer grid with a few hypotheses per pixel, spaced a fraction of a coarse
step around the coarse estimate (so the hypotheses follow the coarse
surface instead of fronto-parallel planes). Hypotheses are per pixel, so
their source locations are projected inside the graph:

* p = R (r d) + t in the source camera (``rel_rt`` input, no inverse);
* lat = asin(-y / |p|), lon = asin(x / |(x, z)|) within 45 degrees of the
  +z axis and +-acos(z / |(x, z)|) elsewhere: no Atan / atan2 in the
  graph, and each arc function is used only where it is well conditioned;
* ``grid_sample`` coordinates as in :func:`rasterizer.sweep.normalised_coords`
  (Yin/Yang: x = lon / lon_max, y = -lat / lat_max, outside the domain
  where |x| or |y| > 1: that is the validity mask).

Matching, aggregation and the peak read-out reuse the coarse stage's
modules; the read-out's margin becomes the fine confidence.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from rasterizer.geometry import YIN_LAT_MAX, YIN_LON_MAX
from rasterizer.sweep import ERP_PAD

from .cost_volume import sample_maps, slab_size, stacked_source
from .select import select, select_many


def _lon(x: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """atan2(x, z) in [-pi, pi] without Atan, each arc function only where it is well conditioned:
    asin(x / rho) within 45 degrees of +z, +-pi - asin(x / rho) within 45 degrees of -z, else
    +-acos(z / rho) (|z / rho| < cos 45 deg there)."""
    rho = torch.sqrt(x * x + z * z).clamp(min=1e-12)
    s = torch.asin((x / rho).clamp(-1.0, 1.0))
    c = torch.acos((z / rho).clamp(-1.0, 1.0))
    pos = x >= 0
    side, back = select_many(pos, (c, math.pi - s), (-c, -math.pi - s))
    return select(x.abs() <= z, s, select(x.abs() <= -z, back, side))


def project_normalised(p: torch.Tensor, kind: str, width: int = 0) -> torch.Tensor:
    """Camera-frame points (..., 3) -> ``grid_sample`` (x, y) of the grid ``kind`` (..., 2).

    ``width`` is the ERP width (the x coordinate addresses the source padded
    by :data:`rasterizer.sweep.ERP_PAD` columns, as the coarse warp grids do).
    """
    return torch.stack(project_xyz(*p.unbind(-1), kind, width), dim=-1)


def project_xyz(x: torch.Tensor, y: torch.Tensor, z: torch.Tensor, kind: str, width: int = 0):
    """:func:`project_normalised` of points given as their three coordinate tensors -> (gx, gy), each of
    their shape. Per-coordinate tensors keep the graph free of (..., 3) tensors, whose last-axis
    splits and concatenations cost onnxruntime more than the arithmetic."""
    if kind == "yang":
        x, y, z = y, x, -z
    norm = torch.sqrt(x * x + y * y + z * z).clamp(min=1e-12)
    lat = torch.asin((-y / norm).clamp(-1.0, 1.0))
    lon = _lon(x, z)
    if kind == "erp":
        col = (lon + math.pi) * (width / (2 * math.pi)) - 0.5
        gx = (2.0 * (col + ERP_PAD) + 1.0) / (width + 2 * ERP_PAD) - 1.0
        gy = -lat * (2.0 / math.pi)
    else:
        gx = lon * (1.0 / YIN_LON_MAX)
        gy = -lat * (1.0 / YIN_LAT_MAX)
    return gx, gy


def sample_other_view(maps: torch.Tensor, pts, grids, erp_width: int = 0):
    """The other view's (2G, 1, h, w) ``maps`` at source-camera points ``pts`` = (x, y, z), each (2, G, J, h, w).

    Returns (samples (2, 1, G J h, w), in_yin (2, G, J, h, w) bool: the point
    was sampled in the Yin grid (always True for ERP), gx, gy (2, G, J, h, w) its ``grid_sample``
    coordinates in that grid). Yin/Yang sources: each point is sampled once, in the Yin map if its
    direction lies in the Yin domain, else in the Yang map (the two cover the sphere), from one
    image with Yang stacked under Yin (a replicated edge row each, so bilinear taps never mix
    them). This is the mask blend of eq. 4 with the Yang mask zeroed where Yin is valid: half the
    GridSample work of sampling both and averaging the overlap.
    """
    x, y, z = pts
    _, g_count, j_count, h, w = x.shape
    views = maps.reshape(2, g_count, 1, h, w)
    source = torch.stack([views[1], views[0]])  # [d] = view 1 - d, (2, G_s, 1, h, w)
    if tuple(grids) == ("erp",):
        gx, gy = project_xyz(x, y, z, "erp", erp_width)
        grid = torch.stack([gx, gy], dim=-1).reshape(2, g_count * j_count * h, w, 2)
        return sample_maps(source[:, 0], grid, True), torch.ones_like(gx, dtype=torch.bool), gx, gy
    norm = torch.sqrt(x * x + y * y + z * z)
    in_yin = (y.abs() <= math.sin(YIN_LAT_MAX) * norm) & (z >= -x.abs())
    # Yang points in the Yang frame (y, x, -z), where its layout is Yin's
    gx, gy = project_xyz(*select_many(in_yin, (x, y, z), (y, x, -z)), "yin")
    gs = ((gy + 1.0) * h + (~in_yin).to(gy.dtype) * float(2 * h + 4)) / (2 * h + 2) - 1.0  # rows + h + 2
    grid = torch.stack([gx, gs], dim=-1).reshape(2, g_count * j_count * h, w, 2)
    return sample_maps(stacked_source(source, False), grid, False), in_yin, gx, gy


def source_points(rng: torch.Tensor, rays: torch.Tensor, rel_rt: torch.Tensor):
    """Ranges (2, G, J, h, w) along the target rays (G, h, w, 3) -> p = R (r d) + t in the other camera
    (``rel_rt`` (2, 3, 4)) as (x, y, z), each (2, G, J, h, w): the rotated rays once, then one multiply-add
    per coordinate, R d r + t."""
    _, g_count, _, h, w = rng.shape
    rot, t = rel_rt[:, :, :3], rel_rt[:, :, 3]  # (2, 3, 3), (2, 3)
    u = torch.matmul(rays.reshape(1, g_count * h * w, 3), rot.transpose(1, 2)).reshape(2, g_count, 1, h, w, 3)
    return tuple(u[..., k] * rng + t[:, k].reshape(2, 1, 1, 1, 1) for k in range(3))


def norm3(x: torch.Tensor, y: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """|p| of points given as their coordinates."""
    return torch.sqrt(x * x + y * y + z * z)


class FineSweep(nn.Module):
    """inv (2G, 1, h, w) coarse inverse range on the fine grid, grey (2G, 1, h, w),
    rays (G, h, w, 3), rel_rt (2, 3, 4), step (scalar or (2G, 1, h, w): one fine hypothesis apart)
    -> refined inverse range and one confidence per margin scale of ``readout``, each (2G, 1, h, w).

    Hypotheses inv + (j - J // 2) * step, j = 0 .. J - 1, clamped to
    [inv_min, inv_max]. A peak at either end of the hypotheses (the coarse
    estimate was off by more than the span) keeps the coarse value and
    confidence 0.
    """

    def __init__(self, grids, num_hypotheses: int, matcher: nn.Module, aggregation: nn.Module,
                 readout: nn.Module, erp_width: int = 0) -> None:
        super().__init__()
        self.grids = tuple(grids)
        self.num = int(num_hypotheses)
        self.matcher = matcher
        self.aggregation = aggregation
        self.readout = readout
        self.erp_width = int(erp_width)
        offsets = torch.arange(self.num, dtype=torch.float32) - (self.num // 2)
        self.register_buffer("offsets", offsets.view(1, 1, self.num, 1, 1), persistent=False)

    def points(self, inv_h: torch.Tensor, rays: torch.Tensor, rel_rt: torch.Tensor):
        """(2G, 1, J, h, w) inverse ranges -> points in the source camera as (x, y, z), each (2, G, J, h, w)."""
        return source_points(1.0 / inv_h.reshape(2, len(self.grids), *inv_h.shape[2:]), rays, rel_rt)

    def sample(self, maps: torch.Tensor, pts) -> torch.Tensor:
        """The other view's (2G, 1, h, w) ``maps`` at source-camera points (x, y, z), each (2, G, J, h, w)
        -> (2G, 1, J, h, w). See :func:`sample_other_view`."""
        _, g_count, j_count, h, w = pts[0].shape
        return sample_other_view(maps, pts, self.grids, self.erp_width)[0].reshape(2 * g_count, 1, j_count, h, w)

    def lr_consistency(self, inv: torch.Tensor, rays: torch.Tensor, rel_rt: torch.Tensor, tol) -> torch.Tensor:
        """1 where the other view's inverse range at a pixel's 3D point matches that point's (within ``tol``:
        a scalar, or a function of that point's inverse range from the other camera)."""
        pts = self.points(inv.unsqueeze(2), rays, rel_rt)  # (2, G, 1, h, w) each
        expected = 1.0 / norm3(*pts).clamp(min=1e-6)
        seen = self.sample(inv, pts)
        expected = expected.reshape(seen.shape)
        tol = tol(expected) if callable(tol) else tol
        return ((seen - expected).abs() <= tol).to(inv.dtype).squeeze(2)

    def forward(self, inv, grey, rays, rel_rt, step, inv_min, inv_max):
        step = torch.as_tensor(step, dtype=inv.dtype)
        step_h = step.unsqueeze(2) if step.dim() == 4 else step
        inv_h = (inv.unsqueeze(2) + self.offsets * step_h).clamp(min=inv_min, max=inv_max)  # (2G, 1, J, h, w)
        # hypotheses in slabs that fit the cache (export.cost_volume.slab_size); each scores on its own
        n, _, _, h, w = inv_h.shape
        terms = self.matcher.target_terms(grey)  # once for every slab
        cost = []
        for part in torch.split(inv_h, slab_size(self.num, n * h * w * 4), dim=2):
            warped = self.sample(grey, self.points(part, rays, rel_rt))
            cost.append(self.aggregation(self.matcher.score(terms, warped), grey))
        cost = torch.cat(cost, 1)  # (2G, J, h, w)
        k, *confs = self.readout(cost)
        inner = ((k > 0.5) & (k < self.num - 1.5)).to(k.dtype)
        refined = inv + (k - self.num // 2) * step
        return (inner * refined + (1.0 - inner) * inv,) + tuple(c * inner for c in confs)
