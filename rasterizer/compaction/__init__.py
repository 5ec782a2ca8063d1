"""Leave out Gaussians a scene does not need (numpy, vectorised).

A two-view reconstruction has one Gaussian per Yin and per Yang pixel of
both views (786,432 at 512x1024). :func:`compact` removes, in this order,
each step switchable in :class:`CompactionOptions`:

1. ``min_opacity`` / ``min_confidence``: Gaussians too transparent (or too
   unconfident) to show. The renderer already skips alpha < 1/255 per pixel,
   so ``min_opacity = 1/255`` only saves their projection and storage.
2. ``merge_smooth``: a 2x2 block of one grid's pixels (with
   ``smooth_levels`` >= 2 also 4x4 of merged 2x2 blocks, ...) whose
   Gaussians are all still there, nearly the same colour and opacity, and
   lie on one plane seen at most ``smooth_max_incidence_deg`` (55) degrees off
   its normal is replaced by one moment-matched Gaussian with the block's
   optical depth (:func:`smooth_merge_blocks`). Flat, evenly coloured walls then need a
   quarter of the Gaussians and about half the render contributions.
3. ``max_count`` / ``max_bytes``: first step 2 goes on past its texture
   test, least textured 2x2 blocks first, until the count fits or no block
   passes its other tests; then the Gaussians with the largest opacity x
   footprint solid angle seen from their own reference are kept.

Steps 1 and 3 only drop Gaussians; step 2 makes new ones. The output
comes in layout order (a merged block at its top-left pixel). An
environment shell after the pixel-aligned Gaussians (``Provenance.shell``,
:mod:`rasterizer.shell`) is kept as it is, except for steps 1 (opacity) and
3 (the cap counts it), and comes last.

The layout (which view, grid, row, column each Gaussian came from) is a
:class:`Provenance`; the encoder's order is [view][grid][row][col].
"""

from .merge import MIN_OVERLAP, opacity_depth, opacity_for_depth, smooth_merge_blocks
from .options import CompactionError, CompactionOptions, ply_bytes_for_count, ply_count_for_bytes
from .provenance import Provenance
from .result import compact, compact_index, compact_result
from .steps import footprint

__all__ = ["MIN_OVERLAP", "CompactionError", "CompactionOptions", "Provenance", "compact", "compact_index",
           "compact_result", "footprint", "opacity_depth", "opacity_for_depth", "ply_bytes_for_count",
           "ply_count_for_bytes", "smooth_merge_blocks"]
