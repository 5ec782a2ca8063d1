"""ERP -> Yin / Yang images inside the graph, with constant sampling grids.

The grids come from :mod:`rasterizer.geometry` (pixel centres, the one
convention), are converted to ``grid_sample`` coordinates with
``align_corners=False`` (pixel c of an n-pixel axis sits at (2c + 1)/n - 1)
and become graph constants. The ERP is padded circularly by
:data:`rasterizer.sweep.ERP_PAD` columns first, so samples near the seam
(lon = +-pi, the back of the Yang grid) interpolate across it; rows use
border padding (the poles).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from rasterizer.geometry import grid_directions, project_to_grid
from rasterizer.sweep import ERP_PAD, normalised_coords


def erp_sampling_grid(kind: str, height: int, width: int, erp_height: int) -> np.ndarray:
    """(h, w, 2) ``grid_sample`` coordinates into a circularly padded ERP."""
    col, row = project_to_grid("erp", grid_directions(kind, height, width), erp_height, 2 * erp_height)
    return normalised_coords("erp", col, row, erp_height, 2 * erp_height)


def pad_longitude(x: torch.Tensor, pad: int = ERP_PAD) -> torch.Tensor:
    """Circularly pad the last (longitude) axis of an ERP tensor by ``pad`` each side."""
    return torch.cat([x[..., -pad:], x, x[..., :pad]], dim=-1)


class YinYangSampler(nn.Module):
    """(N, C, H, W) ERP -> (N, 2, C, H/2, 3H/2) stacked [Yin, Yang] images.

    Bilinear; the Yin/Yang pitch equals the ERP's equatorial pitch, so no
    low-pass is needed at full resolution.
    """

    def __init__(self, erp_height: int, grid_height: int, grid_width: int) -> None:
        super().__init__()
        grids = np.stack([erp_sampling_grid(k, grid_height, grid_width, erp_height) for k in ("yin", "yang")])
        self.register_buffer("grid", torch.from_numpy(grids), persistent=False)  # (2, h, w, 2)

    def forward(self, erp: torch.Tensor) -> torch.Tensor:
        n, c = erp.shape[:2]
        padded = pad_longitude(erp)
        out = []
        for g in range(2):
            grid = self.grid[g : g + 1].expand(n, -1, -1, -1)
            out.append(F.grid_sample(padded, grid, mode="bilinear", padding_mode="border", align_corners=False))
        return torch.stack(out, dim=1)
