"""Cross-view correspondences of every Gaussian-grid pixel: the encoder's matching as an output.

A pixel of view d with estimated range r sits at p = R (r ray) + t in the
other camera (``rel_rt``); where p falls in the other view's grids is its
match (the sweep's own warp, evaluated at the picked depth), and the other
view's range there says whether the two depth maps agree: the left-right
check of :meth:`export.model.OmniSplatEncoder.lr_consistency` at full
resolution, on the final (filled) range maps, with the same tolerance
(``lr_tol_planes`` plane steps of inverse range).

Output ``matches`` (2, G, H, W, 5) float32, per [view][grid][row][col]:

* 0 ``grid``: index of the other view's grid holding the match (0 Yin / ERP, 1 Yang);
* 1 ``col``, 2 ``row``: pixel coordinates in that grid, pixel centres at integers
  (ERP columns wrapped into [-0.5, W - 0.5));
* 3 ``score``: the pixel's matching confidence in [0, 1] (the ``confidence`` output);
* 4 ``status``: 0 consistent, 1 occluded (the other view sees something
  nearer along that ray), 2 inconsistent (it sees something farther: a
  left-right failure of this pixel's depth).

:data:`rasterizer.edit.correspondences` reads these channels (names declared there).
"""

from __future__ import annotations

import torch
from torch import nn

from rasterizer.sweep import ERP_PAD

from .fine_sweep import norm3, sample_other_view, source_points


class Matches(nn.Module):
    """range, confidence (2, G, H, W), rays (G, H, W, 3), rel_rt (2, 3, 4), tol (scalar, 1/m,
    or a function of the other view's expected inverse range (2, G, H, W)) -> (2, G, H, W, 5)."""

    def __init__(self, grids, erp_width: int = 0) -> None:
        super().__init__()
        self.grids = tuple(grids)
        self.erp_width = int(erp_width)

    def forward(self, rng, conf, rays, rel_rt, tol):
        g_count, h, w = rays.shape[:3]
        pts = source_points(rng.reshape(2, g_count, 1, h, w), rays, rel_rt)  # (x, y, z), each (2, G, 1, h, w)
        inv = 1.0 / rng.reshape(2 * g_count, 1, h, w)
        seen, in_yin, gx, gy = sample_other_view(inv, pts, self.grids, self.erp_width)
        seen = seen.reshape(2, g_count, h, w)
        expected = 1.0 / norm3(*pts).clamp(min=1e-6).reshape(2, g_count, h, w)
        diff = seen - expected
        tol = tol(expected) if callable(tol) else tol
        status = (diff > tol).to(rng.dtype) + 2.0 * (diff < -tol).to(rng.dtype)
        gx, gy = gx.reshape(2, g_count, h, w), gy.reshape(2, g_count, h, w)
        if self.grids == ("erp",):
            col = (gx + 1.0) * (0.5 * (self.erp_width + 2 * ERP_PAD)) - 0.5 - ERP_PAD
        else:
            col = (gx + 1.0) * (0.5 * w) - 0.5
        row = (gy + 1.0) * (0.5 * h) - 0.5
        grid = 1.0 - in_yin.reshape(2, g_count, h, w).to(rng.dtype)
        return torch.stack([grid, col, row, conf, status], dim=-1)
