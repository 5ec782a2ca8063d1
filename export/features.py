"""Training-free matching features: the grey image and the window helpers of the matcher.

Why these: the two-view probe (design/two-view-depth-notes.md) found census
next to ZNCC the single most important ingredient (flat areas and epipole
ties stop snapping to the far plane), and gradient features useless. The
feature is therefore the plain grey image (one channel, so GridSample stays
cheap); :class:`export.cost_volume.WindowMatcher` computes ZNCC and soft
census in windows of the target lattice on it, with :func:`pad2d` and the
census rings of :func:`ring_offsets`.
"""

from __future__ import annotations

import torch
from torch import nn

#: Rec. 601 luma weights of the grey image the matcher works on.
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
