"""Environment shell: an opaque backdrop behind the pixel-aligned Gaussians of a two-view scene.

The head's surfels are opaque where matching is confident and translucent (opacity down to
``export.config.EncoderConfig.opacity_min``) where it is not, so that at a novel pose the two
references' uncertain surfaces blend instead of one hiding the other in patches. Behind them, each
reference's image is repeated on a sphere of camera-facing discs around that reference, one disc per
``block`` x ``block`` pixels of each grid, opacity ``SHELL_OPACITY``: plain front-to-back compositing
then covers every pixel. Seen from its own reference the shell is that reference's image; from
elsewhere it is a backdrop, like an environment map of the nearest reference.

The sphere's radius is ``SHELL_RADIUS_FACTOR`` times the ``SHELL_RANGE_PERCENTILE`` percentile of the
scene's estimated ranges, so the backdrop lies beyond (almost) every surface: a backdrop must not
hide a surface that only the other reference sees (a disc at twice its own block's range put a near
object's backdrop in front of the walls and floor behind it). Measurements behind the constants:
docs/design.md.

Layout: the shell's Gaussians come in [view][grid][block row][block column] order; each one stands
for the ``block`` x ``block`` pixels whose top-left pixel is :func:`shell_layout`'s index (the same
provenance convention as compaction's merged blocks, so selections and edits treat it alike).
"""

from __future__ import annotations

import numpy as np

from .depth_gaussians import gaussians_from_depth
from .gaussians import Gaussians, sh_dc_to_rgb

#: Shell radius / the scene's SHELL_RANGE_PERCENTILE-th percentile range (both references' range maps).
SHELL_RADIUS_FACTOR = 4.0
SHELL_RANGE_PERCENTILE = 99.0
#: Pixels per shell disc side (largest of 4, 2, 1 that divides the grid).
SHELL_BLOCK = 4
#: Disc sigma in block pitches. Each pixel sees two shells (one per reference), so one lattice need not
#: close on its own: at 0.55 pitches one shell leaves ~10% at a block's corner and the two together cover
#: every pixel of every pose measured; wider discs overlap more of each other and cost render time
#: (docs/design.md, "Rendering").
SHELL_SCALE = 0.55
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


def shell_radius(range_maps: np.ndarray) -> float:
    """Radius of the shell spheres (scene units): SHELL_RADIUS_FACTOR x the SHELL_RANGE_PERCENTILE-th
    percentile of the finite positive ranges (1 if there are none)."""
    r = np.asarray(range_maps, dtype=np.float64).ravel()
    r = r[np.isfinite(r) & (r > 0)]
    return SHELL_RADIUS_FACTOR * (float(np.percentile(r, SHELL_RANGE_PERCENTILE)) if r.size else 1.0)


def _block_mean(x: np.ndarray) -> np.ndarray:
    """``x.mean(axis=(3, 5))`` of (V, G, H/b, b, W/b, b, C) float32 blocks, the same sums in the same
    (row-major) order as numpy's reduction, as b^2 strided array passes (numpy's reduction over two
    inner axes with a last axis of 3 walks the array element by element, several times slower)."""
    acc = x[:, :, :, 0, :, 0].copy()
    for i in range(x.shape[3]):
        for j in range(x.shape[5]):
            if i or j:
                acc += x[:, :, :, i, :, j]
    acc /= x.shape[3] * x.shape[5]
    return acc


def environment_shell(layout: Gaussians, range_maps: np.ndarray, c2w: np.ndarray, grids: tuple[str, ...],
                      radius: float | None = None) -> Gaussians:
    """The shell (module docstring) of pixel-aligned Gaussians.

    layout: N = V G H W Gaussians in [view][grid][row][col] order (their colours are averaged per
    block); range_maps (V, G, H, W) range from each view's camera, scene units; c2w (V, 4, 4) the
    poses those ranges are measured from; grids: the G grid kinds ("yin", "yang") or ("erp",);
    radius: the spheres' radius, scene units (default :func:`shell_radius` of ``range_maps``).
    """
    v_count, g_count, h, w = np.shape(range_maps)
    if len(layout) != v_count * g_count * h * w:
        raise ValueError(f"{len(layout)} Gaussians for a layout of {v_count}x{g_count}x{h}x{w}")
    b = shell_block(h, w)
    rgb = _block_mean(sh_dc_to_rgb(layout.sh[:, 0, :]).reshape(v_count, g_count, h // b, b, w // b, b, 3))
    rng = np.full((h // b, w // b), shell_radius(range_maps) if radius is None else float(radius))
    parts = [gaussians_from_depth(np.clip(rgb[v, g], 0.0, 1.0), rng, c2w[v], grid=grids[g],
                                  scale_factor=SHELL_SCALE, opacity=SHELL_OPACITY)
             for v in range(v_count) for g in range(g_count)]
    return Gaussians.concatenate(parts)
