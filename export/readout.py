"""Depth read-out from an aggregated cost volume, and its confidence.

Cost (N, D, h, w) is a similarity (higher = better) over D candidates
uniform in inverse range, ``inv_depths`` ascending (far ... near).
Winner-take-all plus parabolic sub-plane refinement from the two
neighbouring planes (offset clamped to +-0.5 plane; none at the ends)
gives a fractional plane index k; its inverse range is linear between neighbouring
candidates (:func:`index_to_inverse`), and one plane step in inverse range is the candidates' constant
spacing (:func:`plane_step`; :func:`rasterizer.sweep.inverse_depth_candidates`).
Confidence combines the peak margin (best minus the best plane that is not
a neighbour of the winner) with a zero for near-plane picks, which the probe
found to be the outliers that hurt rendering most.
"""

from __future__ import annotations

import torch
from torch import nn

from .select import select


class DepthReadout(nn.Module):
    """cost (N, D, h, w) -> (plane index (N,1,h,w) float, peak confidences (N,1,h,w) in [0,1]).

    Returns one confidence per entry of ``margin_scales`` (same peak margin,
    different saturation): the model uses a steep one to weight the fill and
    a gentler one for the output confidence / opacity.
    """

    def __init__(self, margin_scales=(0.05,)) -> None:
        super().__init__()
        self.margin_scales = tuple(float(m) for m in margin_scales)

    def forward(self, cost: torch.Tensor):
        d_count = cost.shape[1]
        planes = torch.arange(d_count, dtype=cost.dtype, device=cost.device).view(1, d_count, 1, 1)
        idx = torch.argmax(cost, dim=1, keepdim=True)  # (N,1,h,w) int64
        best = torch.gather(cost, 1, idx)
        lo = torch.gather(cost, 1, (idx - 1).clamp(min=0))
        hi = torch.gather(cost, 1, (idx + 1).clamp(max=d_count - 1))
        curv = lo - 2.0 * best + hi
        inner = (idx > 0) & (idx < d_count - 1) & (curv < -1e-6)
        offset = 0.5 * (lo - hi) / select(inner, curv, -1.0)
        offset = select(inner, offset.clamp(-0.5, 0.5), 0.0)
        k = idx.to(cost.dtype) + offset
        far_from_peak = (planes - idx.to(cost.dtype)).abs() > 1.5
        second = select(far_from_peak, cost, -2.0).amax(dim=1, keepdim=True)
        margin = select(idx == d_count - 1, 0.0, (best - second).clamp(min=0.0))
        return (k,) + tuple(1.0 - torch.exp(margin * (-1.0 / m)) for m in self.margin_scales)


def index_to_inverse(k: torch.Tensor, inv_depths: torch.Tensor) -> torch.Tensor:
    """Inverse range (1/scene units) of a fractional plane index k: the candidates at whole k, linear in
    inverse range between neighbours."""
    d_count = inv_depths.shape[0]
    i0 = k.floor().clamp(0, d_count - 2)
    lo = inv_depths[i0.to(torch.int64)]
    hi = inv_depths[(i0 + 1).to(torch.int64)]
    return lo + (k - i0) * (hi - lo)


def plane_step(inv: torch.Tensor, inv_depths: torch.Tensor) -> torch.Tensor:
    """One candidate step in inverse range at inverse range ``inv`` (any shape), same shape: the
    candidates' constant spacing (uniform in inverse range)."""
    return (inv_depths[1] - inv_depths[0]).expand_as(inv)
