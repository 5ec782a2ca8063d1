"""Cross-view sphere-sweep cost volume on the Yin/Yang (or ERP) grids.

For direction d (target view d, source view 1 - d), target grid g_t and
candidate k, the other view's features are sampled at the precomputed
coordinates (:mod:`rasterizer.sweep`) in one image with its Yang grid stacked
under its Yin grid: each point is read once, in Yin where Yin's domain holds
it, else in Yang (the paper's eq. 4 mask blend with Yin taking the overlap;
the module table of :mod:`rasterizer.sweep`). :class:`WindowMatcher`
(training-free) then scores the target against the warped stack: ZNCC and
soft census over windows laid out in the *target* lattice, on the source
image warped through each depth hypothesis. The window is therefore aware of
the warp (scale and shear from a 1 m baseline at 0.4 m are large), and only
one channel (grey) goes through GridSample, which dominates run time.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .aggregation import box_filter
from .features import pad2d, ring_offsets
from .yin_yang_sampling import pad_longitude


def stacked_source(maps: torch.Tensor, erp_source: bool) -> torch.Tensor:
    """A view's grids (N, G, C, h, w) -> the one image its points are sampled in (N, C, h', w'):
    the ERP itself, or Yin over Yang with each one's edge row repeated between them, (N, C, 2h + 2, w)
    (:mod:`rasterizer.sweep`)."""
    if erp_source:
        return maps[:, 0]
    yin, yang = maps[:, 0], maps[:, 1]
    return torch.cat([yin, yin[:, :, -1:], yang[:, :, :1], yang], dim=2)


def sample_maps(src: torch.Tensor, grid: torch.Tensor, erp_source: bool) -> torch.Tensor:
    """Bilinear samples of (N, C, h, w) ``src`` at (N, Ho, Wo, 2) -> (N, C, Ho, Wo)."""
    if erp_source:
        src = pad_longitude(src)
    return F.grid_sample(src, grid, mode="bilinear", padding_mode="border", align_corners=False)


class WindowMatcher(nn.Module):
    """target (N, 1, h, w) grey, warped (N, 1, D, h, w) -> (N, D, h, w) similarity in [-1, 1].

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
        """Soft census bits of (..., h, w) images, one tensor per offset.

        tanh((I_q - I_p) / sigma) with the image divided by sigma once, not per offset.
        """
        h, w = img.shape[-2:]
        p = self.pad
        img = img * (1.0 / self.sigma)
        padded = pad2d(img, p, self.wrap)
        return [torch.tanh(padded[..., p + dy : p + dy + h, p + dx : p + dx + w] - img) for dy, dx in self.offsets]

    def target_terms(self, target: torch.Tensor) -> tuple:
        """What the score needs of the target alone (N, 1, h, w): centred grey, its window mean and
        variance, its census bits. A sweep scoring its candidates in slabs computes them once."""
        # centred on mid-grey: the same ZNCC, but the E[xy] - E[x]E[y] moments cancel less (with the
        # small eps floor, rounding there shows as ORT-vs-torch differences in flat windows)
        t = target - 0.5  # (N, 1, h, w), broadcasts over the planes
        mean_t = box_filter(t, self.radius, self.wrap)
        var_t = box_filter(t * t, self.radius, self.wrap) - mean_t * mean_t
        return t, mean_t, var_t, self.census_bits(t)

    def score(self, terms: tuple, warped: torch.Tensor) -> torch.Tensor:
        """The similarity of the target given by :meth:`target_terms` and the warped stack."""
        t, mean_t, var_t, bits_t = terms
        wv = warped[:, 0] - 0.5  # (N, D, h, w)
        r = self.radius
        mean_w = box_filter(wv, r, self.wrap)
        var_w = box_filter(wv * wv, r, self.wrap) - mean_w * mean_w
        cov = box_filter(wv * t, r, self.wrap) - mean_w * mean_t
        zncc = cov / torch.sqrt((var_t.clamp(min=0) + self.eps2) * (var_w.clamp(min=0) + self.eps2))
        census = None
        for bt, bw in zip(bits_t, self.census_bits(wv)):
            census = bt * bw if census is None else census + bt * bw
        census = census / len(self.offsets)
        return self.weight * zncc + (1.0 - self.weight) * census

    def forward(self, target: torch.Tensor, warped: torch.Tensor) -> torch.Tensor:
        return self.score(self.target_terms(target), warped)


#: Bytes of one slab of a cost volume: the matcher's and the aggregation's dozens of elementwise passes run about a
#: third faster on a volume that fits the CPU cache (onnxruntime, 2 threads; the coarse (4, 64, 64, 192) float32
#: volume is 12.6 MB).
SLAB_BYTES = 4 << 20


def slab_size(count: int, plane_bytes: int) -> int:
    """Planes per slab: ``count`` planes of ``plane_bytes`` each in the fewest equal slabs of <= SLAB_BYTES."""
    slabs = max(1, -(-count * plane_bytes // SLAB_BYTES))
    return -(-count // slabs)


class SweepCostVolume(nn.Module):
    """feats (2, G, C, h, w), warp_grids (2, G, D, h, w, 2), guide (2G, 1, h, w) -> cost (2, G, D, h, w).

    All 2 G (direction, target grid) warps run as one batched GridSample of the
    stacked sources and the matcher runs once on the (2 G) stacked targets, so
    the graph has one node per step instead of one per pairing. Candidates go
    through warp, match and ``aggregation`` (guided by ``guide``; None: none)
    in slabs of :func:`slab_size` planes: every candidate's score is its own,
    so the slabs give the values of one pass.
    """

    def __init__(self, num_grids: int, erp_source: bool, matcher: nn.Module,
                 aggregation: nn.Module | None = None) -> None:
        super().__init__()
        self.num_grids = num_grids
        self.erp_source = erp_source
        self.matcher = matcher
        self.aggregation = aggregation

    def warp(self, feats: torch.Tensor, warp_grids: torch.Tensor) -> torch.Tensor:
        """Source samples for every (direction, target grid) -> (2, G, C, D, h, w); direction d samples
        view 1 - d in its stacked source (:func:`stacked_source`)."""
        _, g_count, c, h, w = feats.shape
        d_count = warp_grids.shape[2]
        source = stacked_source(torch.stack([feats[1], feats[0]]), self.erp_source)  # [d] = view 1 - d
        hs, ws = source.shape[-2:]
        source = source.unsqueeze(1).expand(2, g_count, c, hs, ws).reshape(2 * g_count, c, hs, ws)
        sampled = sample_maps(source, warp_grids.reshape(2 * g_count, d_count * h, w, 2), self.erp_source)
        return sampled.reshape(2, g_count, c, d_count, h, w)

    def forward(self, feats: torch.Tensor, warp_grids: torch.Tensor, guide: torch.Tensor | None = None) -> torch.Tensor:
        _, g_count, c, h, w = feats.shape
        d_count = warp_grids.shape[2]
        terms = self.matcher.target_terms(feats.reshape(2 * g_count, c, h, w))  # once for every slab
        cost = []
        for slab in torch.split(warp_grids, slab_size(d_count, 2 * g_count * c * h * w * 4), dim=2):
            n = slab.shape[2]
            part = self.matcher.score(terms, self.warp(feats, slab).reshape(2 * g_count, c, n, h, w))
            cost.append(part if self.aggregation is None else self.aggregation(part, guide))
        return torch.cat(cost, 1).reshape(2, g_count, d_count, h, w)
