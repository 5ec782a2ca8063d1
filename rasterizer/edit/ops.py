"""Gaussians of a selection, and the edits (remove, keep, recolor, translate).

A Gaussian came from one pixel (or, merged by compaction, one block of
``block`` x ``block`` pixels) of one reference's grid
(:class:`rasterizer.compaction.Provenance`); its *source pixel* is the ERP
pixel of that reference looking along the block centre's ray. It belongs to
a selection when its source pixel is in that reference's mask.
"""

from __future__ import annotations

import numpy as np

from .. import geometry as geo
from ..gaussians import Gaussians, rgb_to_sh_dc
from .correspondences import grid_point_directions

EDIT_OPS = ("remove", "keep", "recolor", "translate")


def source_pixels(index: np.ndarray, block: np.ndarray, grids: tuple[str, ...], height: int, width: int,
                  erp_height: int) -> tuple[np.ndarray, np.ndarray]:
    """(view (N,), flat ERP pixel (N,) on a (erp_height, 2 erp_height) ERP) of Gaussians at layout positions
    ``index`` (N,) [view][grid][row][col] of grids height x width, standing for ``block`` (N,) pixel blocks."""
    index = np.asarray(index, dtype=np.int64)
    per_grid = height * width
    vg, pix = np.divmod(index, per_grid)
    view, grid = np.divmod(vg, len(grids))
    row, col = np.divmod(pix, width)
    half = (np.asarray(block, dtype=np.float64) - 1.0) / 2.0
    d = grid_point_directions(grid, col + half, row + half, height, width, erp=tuple(grids) == ("erp",))
    ecol, erow = geo.project_to_grid("erp", d, erp_height, 2 * erp_height)
    ecol = np.mod(np.floor(ecol + 0.5).astype(np.int64), 2 * erp_height)
    erow = np.clip(np.floor(erow + 0.5).astype(np.int64), 0, erp_height - 1)
    return view, erow * (2 * erp_height) + ecol


def gaussian_values(maps: np.ndarray, view: np.ndarray, pixel: np.ndarray) -> np.ndarray:
    """Per-Gaussian value of per-view ERP maps (2, He, We): the map of its view at its source pixel."""
    flat = np.asarray(maps).reshape(2, -1)
    return flat[view, pixel]


def edit_gaussians(g: Gaussians, selected: np.ndarray, op: str, *, color=None, offset=None) -> Gaussians:
    """The Gaussians after ``op`` on the ``selected`` (N,) bool ones.

    remove: drop them; keep: keep only them; recolor: their colour (SH DC) set
    to ``color`` (3,) RGB in [0, 1], higher SH bands zeroed (flat colour);
    translate: their means moved by ``offset`` (3,) world units.
    """
    selected = np.asarray(selected, dtype=bool)
    if selected.shape != (len(g),):
        raise ValueError(f"selection has {selected.shape} entries for {len(g)} Gaussians")
    if op == "remove":
        return g.subset(~selected)
    if op == "keep":
        return g.subset(selected)
    if op == "recolor":
        rgb = np.asarray(color, dtype=np.float32).reshape(3)
        sh = g.sh.copy()
        sh[selected] = 0.0
        sh[selected, 0] = rgb_to_sh_dc(rgb)
        return g.with_(sh=sh)
    if op == "translate":
        means = g.means.copy()
        means[selected] += np.asarray(offset, dtype=np.float32).reshape(3)
        return g.with_(means=means)
    raise ValueError(f"unknown edit op {op!r}; expected one of {EDIT_OPS}")


def palette(count: int) -> np.ndarray:
    """(count, 3) uint8 distinct, deterministic colours: label k always gets the same one (golden-ratio hues)."""
    k = np.arange(count, dtype=np.float64)
    hue = np.mod(k * 0.6180339887498949, 1.0)
    sat = 0.55 + 0.45 * np.mod(k * 0.37, 1.0)
    val = 0.6 + 0.4 * np.mod(k * 0.23 + 0.5, 1.0)
    h6 = hue * 6.0
    c = val * sat
    x = c * (1 - np.abs(np.mod(h6, 2) - 1))
    sector = np.floor(h6).astype(int) % 6
    zero = np.zeros_like(c)
    table = np.stack([np.stack(t, -1) for t in ((c, x, zero), (x, c, zero), (zero, c, x), (zero, x, c), (x, zero, c),
                                                (c, zero, x))])  # (6, count, 3)
    rgb = table[sector, np.arange(count)] + (val - c)[:, None]
    return np.rint(rgb * 255).astype(np.uint8)
