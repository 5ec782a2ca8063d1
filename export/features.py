"""Training-free matching features: per-pixel ZNCC patches and soft census.

Why these: the two-view probe (design/two-view-depth-notes.md) found census
next to ZNCC the single most important ingredient (flat areas and epipole
ties stop snapping to the far plane), and gradient features useless. Both
become *per-pixel descriptor vectors* whose dot product is the matching
score, so the cost volume is a plain correlation <F_t, warp(F_s)> as in
MVSplat and a learned backbone can replace this module unchanged:

* ZNCC part: the (2r+1)^2 grey patch around the pixel, mean removed and
  divided by its norm (+ an eps floor so flat patches give small vectors
  and a neutral score). Dot product of two such vectors = ZNCC of the
  patches (taken in each image's own lattice).
* Census part: tanh((I_q - I_p) / sigma) for 8 neighbours on each ring of
  radius r in ``census_radii`` (several scales), divided by sqrt(K): a
  differentiable, illumination-robust census whose dot product is
  1 - 2 * (soft Hamming distance) / K.

Descriptor = [sqrt(w) * zncc, sqrt(1 - w) * census]: the dot product of two
descriptors is w * ZNCC + (1 - w) * census similarity, in [-1, 1].
"""

from __future__ import annotations

import torch
from torch import nn

#: Rec. 601 luma weights of the grey image every matcher works on.
LUMA = (0.299, 0.587, 0.114)


def pad2d(x: torch.Tensor, pad: int, wrap: bool) -> torch.Tensor:
    """Edge-replicate pad of the last two axes; circular in width if ``wrap`` (ERP)."""
    if pad == 0:
        return x
    if wrap:
        x = torch.cat([x[..., -pad:], x, x[..., :pad]], dim=-1)
    else:
        x = torch.cat([x[..., :, :1].expand(*x.shape[:-1], pad), x, x[..., :, -1:].expand(*x.shape[:-1], pad)], dim=-1)
    top = x[..., :1, :].expand(*x.shape[:-2], pad, x.shape[-1])
    bottom = x[..., -1:, :].expand(*x.shape[:-2], pad, x.shape[-1])
    return torch.cat([top, x, bottom], dim=-2)


def shifted(x: torch.Tensor, offsets: list[tuple[int, int]], wrap: bool) -> torch.Tensor:
    """Stack of x shifted by (dy, dx) offsets: (N, 1, h, w) -> (N, len(offsets), h, w)."""
    pad = max(max(abs(dy), abs(dx)) for dy, dx in offsets)
    xp = pad2d(x, pad, wrap)
    h, w = x.shape[-2:]
    return torch.cat([xp[..., pad + dy : pad + dy + h, pad + dx : pad + dx + w] for dy, dx in offsets], dim=1)


def ring_offsets(radius: int) -> list[tuple[int, int]]:
    r = radius
    return [(-r, -r), (-r, 0), (-r, r), (0, -r), (0, r), (r, -r), (r, 0), (r, r)]


class GreyFeatures(nn.Module):
    """(N, 3, h, w) colour -> (N, 1, h, w) luma: the input of the window matcher.

    The window matcher normalises locally itself (ZNCC, census), so the
    feature is the plain grey image; one channel keeps GridSample cheap.
    """

    out_channels = 1

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("luma", torch.tensor(LUMA).view(1, 3, 1, 1), persistent=False)

    def forward(self, rgb: torch.Tensor) -> torch.Tensor:
        return (rgb * self.luma).sum(dim=1, keepdim=True)


class TrainingFreeFeatures(nn.Module):
    """(N, 3, h, w) colour in [0, 1] -> (N, C, h, w) descriptors (module docstring).

    ``wrap=True`` treats the width axis as periodic (ERP longitude).
    """

    def __init__(self, zncc_radius: int = 2, census_radii=(1, 3), census_sigma: float = 0.03,
                 zncc_eps: float = 0.02, zncc_weight: float = 0.5, wrap: bool = False) -> None:
        super().__init__()
        r = zncc_radius
        self.zncc_offsets = [(dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1)]
        self.census_offsets = [o for rad in census_radii for o in ring_offsets(rad)]
        self.census_sigma = float(census_sigma)
        self.zncc_eps = float(zncc_eps)
        self.zncc_weight = float(zncc_weight)
        self.wrap = wrap
        self.out_channels = len(self.zncc_offsets) + len(self.census_offsets)
        self.register_buffer("luma", torch.tensor(LUMA).view(1, 3, 1, 1), persistent=False)

    def forward(self, rgb: torch.Tensor) -> torch.Tensor:
        grey = (rgb * self.luma).sum(dim=1, keepdim=True)
        patch = shifted(grey, self.zncc_offsets, self.wrap)
        patch = patch - patch.mean(dim=1, keepdim=True)
        n = patch.shape[1]
        norm = torch.sqrt((patch * patch).sum(dim=1, keepdim=True) + n * self.zncc_eps**2)
        zncc = patch / norm
        census = torch.tanh((shifted(grey, self.census_offsets, self.wrap) - grey) / self.census_sigma)
        census = census / len(self.census_offsets) ** 0.5
        wz = self.zncc_weight
        return torch.cat([zncc * wz**0.5, census * (1.0 - wz) ** 0.5], dim=1)
