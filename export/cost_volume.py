"""Cross-view sphere-sweep cost volume over the four Yin/Yang pairings.

For direction d (target view d, source view 1 - d), target grid g_t and
candidate k, the other view's features on *both* its grids are sampled at
the precomputed coordinates (:mod:`rasterizer.sweep`) and blended with the
validity masks as in the paper's eq. 4, ``(F_n M_n + F_e M_e) / (M_n + M_e)``
(0 where both masks are 0, which cannot happen for Yin + Yang: together they
cover the sphere). Masks are binary "inside the source grid's domain" tests
read off the coordinates (|x|, |y| <= 1 with align_corners=False). A
*matcher* then scores the target against the warped stack:

* :class:`WindowMatcher` (default, training-free): ZNCC and soft census over
  windows laid out in the *target* lattice, on the source image warped
  through each depth hypothesis. The window is therefore aware of the warp
  (scale and shear from a 1 m baseline at 0.4 m are large), and only one
  channel (grey) goes through GridSample, which dominates run time.
* :class:`CorrelationMatcher`: channel dot product of per-pixel descriptors
  (MVSplat's correlation; what a learned backbone would plug into).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .aggregation import box_filter
from .features import pad2d, ring_offsets
from .yin_yang_sampling import pad_longitude


def domain_mask(grid: torch.Tensor) -> torch.Tensor:
    """(..., 2) grid_sample coordinates -> (...) float 1 inside [-1, 1]^2, else 0."""
    return (grid.abs().amax(dim=-1) <= 1.0).to(grid.dtype)


def sample_maps(src: torch.Tensor, grid: torch.Tensor, erp_source: bool) -> torch.Tensor:
    """Bilinear samples of (1, C, h, w) ``src`` at (1, Ho, Wo, 2) -> (1, C, Ho, Wo)."""
    if erp_source:
        src = pad_longitude(src)
    return F.grid_sample(src, grid, mode="bilinear", padding_mode="border", align_corners=False)


class CorrelationMatcher(nn.Module):
    """target (C, h, w), warped (C, D, h, w) -> (D, h, w) channel dot product."""

    def forward(self, target: torch.Tensor, warped: torch.Tensor) -> torch.Tensor:
        return (warped * target.unsqueeze(1)).sum(dim=0)


class WindowMatcher(nn.Module):
    """target (1, h, w) grey, warped (1, D, h, w) -> (D, h, w) similarity in [-1, 1].

    ``w * ZNCC + (1 - w) * census``: ZNCC over a (2r+1)^2 box (eps floor on
    the variances so flat windows score ~0, not noise), soft census
    tanh(diff / sigma) on rings of radius ``census_radii`` (8 each),
    similarity = mean over bits of the product of target and warped bits.
    """

    def __init__(self, zncc_radius: int = 2, census_radii=(1, 3), census_sigma: float = 0.03,
                 zncc_eps: float = 0.02, zncc_weight: float = 0.5, wrap: bool = False) -> None:
        super().__init__()
        self.radius = int(zncc_radius)
        self.offsets = [o for r in census_radii for o in ring_offsets(r)]
        self.pad = max(census_radii)
        self.sigma = float(census_sigma)
        self.eps2 = float(zncc_eps) ** 2
        self.weight = float(zncc_weight)
        self.wrap = wrap

    def census_bits(self, img: torch.Tensor) -> list[torch.Tensor]:
        """Soft census bits of (..., h, w) images, one tensor per offset."""
        h, w = img.shape[-2:]
        p = self.pad
        padded = pad2d(img, p, self.wrap)
        return [torch.tanh((padded[..., p + dy : p + dy + h, p + dx : p + dx + w] - img) / self.sigma)
                for dy, dx in self.offsets]

    def forward(self, target: torch.Tensor, warped: torch.Tensor) -> torch.Tensor:
        t = target  # (1, h, w)
        wv = warped[0]  # (D, h, w)
        r = self.radius
        mean_t = box_filter(t.unsqueeze(0), r, self.wrap)[0]
        var_t = box_filter((t * t).unsqueeze(0), r, self.wrap)[0] - mean_t * mean_t
        mean_w = box_filter(wv.unsqueeze(0), r, self.wrap)[0]
        var_w = box_filter((wv * wv).unsqueeze(0), r, self.wrap)[0] - mean_w * mean_w
        cov = box_filter((wv * t).unsqueeze(0), r, self.wrap)[0] - mean_w * mean_t
        zncc = cov / torch.sqrt((var_t.clamp(min=0) + self.eps2) * (var_w.clamp(min=0) + self.eps2))
        census = None
        for bt, bw in zip(self.census_bits(t), self.census_bits(wv)):
            census = bt * bw if census is None else census + bt * bw
        census = census / len(self.offsets)
        return self.weight * zncc + (1.0 - self.weight) * census


class SweepCostVolume(nn.Module):
    """feats (2, G, C, h, w), warp_grids (2, G, G, D, h, w, 2) -> cost (2, G, D, h, w)."""

    def __init__(self, num_grids: int, erp_source: bool, matcher: nn.Module) -> None:
        super().__init__()
        self.num_grids = num_grids
        self.erp_source = erp_source
        self.matcher = matcher

    def warp(self, source: torch.Tensor, grids: torch.Tensor) -> torch.Tensor:
        """Mask-blended (eq. 4) samples of source (G, C, h, w) at grids (G, D, h, w, 2) -> (C, D, h, w)."""
        g_count, d_count, h, w = grids.shape[:4]
        c = source.shape[1]
        num = None
        den = None
        for gs in range(g_count):
            grid = grids[gs]
            sampled = sample_maps(source[gs : gs + 1], grid.reshape(1, d_count * h, w, 2), self.erp_source)
            sampled = sampled.reshape(c, d_count, h, w)
            if self.erp_source or g_count == 1:
                return sampled
            mask = domain_mask(grid)  # (D, h, w)
            num = sampled * mask if num is None else num + sampled * mask
            den = mask if den is None else den + mask
        return torch.where(den > 0, num / den.clamp(min=1.0), torch.zeros_like(num))

    def forward(self, feats: torch.Tensor, warp_grids: torch.Tensor) -> torch.Tensor:
        _, g_count, _, h, w = feats.shape
        d_count = warp_grids.shape[3]
        costs = []
        for d in range(2):
            for gt in range(g_count):
                warped = self.warp(feats[1 - d], warp_grids[d, gt])
                costs.append(self.matcher(feats[d, gt], warped))
        return torch.stack(costs).reshape(2, g_count, d_count, h, w)
