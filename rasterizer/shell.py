"""Environment shell: an opaque backdrop behind the pixel-aligned Gaussians of a two-view scene.

The head's surfels are opaque where matching is confident and translucent (opacity down to
``export.config.EncoderConfig.opacity_min``) where it is not, so that at a novel pose the two
references' uncertain surfaces blend instead of one hiding the other in patches. Behind them, each
reference's image is repeated on a shell of camera-facing discs at ``SHELL_FACTOR`` times the
estimated range, one disc per ``block`` x ``block`` pixels of each grid, opacity ``SHELL_OPACITY``:
plain front-to-back compositing then covers every pixel. Seen from its own reference the shell is
that reference's image; from elsewhere it is a backdrop, as a copy of the nearest reference would be.
Measurements behind the constants: docs/experiments.md, "Environment shell".

Layout: the shell's Gaussians come in [view][grid][block row][block column] order; each one stands
for the ``block`` x ``block`` pixels whose top-left pixel is :func:`shell_layout`'s index (the same
provenance convention as compaction's merged blocks, so selections and edits treat it alike).
"""

from __future__ import annotations

import numpy as np

from .depth_gaussians import gaussians_from_depth
from .gaussians import Gaussians, sh_dc_to_rgb

#: Shell range / estimated range.
SHELL_FACTOR = 2.0
#: Pixels per shell disc side (largest of 4, 2, 1 that divides the grid).
SHELL_BLOCK = 4
#: Disc sigma in block pitches (a lattice of sigma 0.7 pitches covers ~99%; larger for oblique views).
SHELL_SCALE = 1.0
SHELL_OPACITY = 0.99


def shell_block(height: int, width: int) -> int:
    """Block side for grids of height x width: the largest of SHELL_BLOCK, ..., 2, 1 dividing both."""
    b = SHELL_BLOCK
    while b > 1 and (height % b or width % b):
        b //= 2
    return b


def shell_layout(views: int, grids: int, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """(index (M,), block (M,)) of the shell's Gaussians: layout position [view][grid][row][col] of each
    block's top-left pixel, and the block side."""
    b = shell_block(height, width)
    vg = np.arange(views * grids)[:, None, None] * (height * width)
    rows = np.arange(0, height, b)[None, :, None] * width
    cols = np.arange(0, width, b)[None, None, :]
    index = (vg + rows + cols).reshape(-1)
    return index, np.full(index.size, b, dtype=np.int64)


def environment_shell(layout: Gaussians, range_maps: np.ndarray, c2w: np.ndarray, grids: tuple[str, ...]) -> Gaussians:
    """The shell (module docstring) of pixel-aligned Gaussians.

    layout: N = V G H W Gaussians in [view][grid][row][col] order (their colours are averaged per
    block); range_maps (V, G, H, W) range from each view's camera, scene units; c2w (V, 4, 4) the
    poses those ranges are measured from; grids: the G grid kinds ("yin", "yang") or ("erp",).
    """
    v_count, g_count, h, w = np.shape(range_maps)
    if len(layout) != v_count * g_count * h * w:
        raise ValueError(f"{len(layout)} Gaussians for a layout of {v_count}x{g_count}x{h}x{w}")
    b = shell_block(h, w)
    rgb = sh_dc_to_rgb(layout.sh[:, 0, :]).reshape(v_count, g_count, h // b, b, w // b, b, 3).mean(axis=(3, 5))
    rng = np.asarray(range_maps, dtype=np.float64).reshape(v_count, g_count, h // b, b, w // b, b).mean(axis=(3, 5))
    rng = np.where(np.isfinite(rng) & (rng > 0), rng, 1.0) * SHELL_FACTOR  # the encoder's ranges are > 0
    parts = [gaussians_from_depth(np.clip(rgb[v, g], 0.0, 1.0), rng[v, g], c2w[v], grid=grids[g],
                                  scale_factor=SHELL_SCALE, opacity=SHELL_OPACITY)
             for v in range(v_count) for g in range(g_count)]
    return Gaussians.concatenate(parts)
