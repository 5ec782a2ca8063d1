"""Phase (b) of rendering: front-to-back alpha compositing of footprints.

Per pixel, in the order of :class:`~rasterizer.splat.Footprints` (nearest
first), exactly the 3DGS / ODGS rules:

* ``alpha_i = min(0.99, opacity_i * g_i)``; contributions with
  ``alpha_i < 1/255`` are skipped (they do not change transmittance);
* ``T_i = prod_{j<i} (1 - alpha_j)`` (exclusive transmittance);
* a contribution is composited only while ``T_i (1 - alpha_i) >= 1e-4``
  (the kernel stops at the first one that would take T below 1e-4);
* ``w_i = alpha_i T_i``; colour = sum w_i c_i (over black), alpha = sum w_i,
  range = sum w_i r_i / alpha (the expected range; 0 where alpha is 0).

Vectorised without a loop over pixels: ``log(1 - alpha)`` is cumulatively
summed in float64 and the sum at each pixel's start is subtracted (a
segmented exclusive cumsum); per-pixel totals come from ``np.add.reduceat``
over the pixel segments.

The per-contribution weights and transmittances (``return_terms=True``) are
what a backward pass (colour/opacity refinement with fixed geometry) needs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .splat import ALPHA_MIN, Footprints

ALPHA_MAX = 0.99
T_MIN = 1e-4


@dataclass(frozen=True)
class CompositeTerms:
    """Per-contribution terms (M,) of one composite, for backward passes.

    alpha: clamped alpha (0 where skipped); transmittance: exclusive T;
    weight: alpha * T (0 where skipped or after termination); starts (P,)
    index of each non-empty pixel's first contribution; pixels (P,) flat
    pixel index of each segment.
    """

    alpha: np.ndarray
    transmittance: np.ndarray
    weight: np.ndarray
    starts: np.ndarray
    pixels: np.ndarray


def accumulate(fp: Footprints, opacities: np.ndarray, colours: np.ndarray, *, return_terms: bool = False):
    """Premultiplied sums: colour (H, W, 3), alpha (H, W), range*alpha (H, W), float32.

    ``opacities`` (N,) and ``colours`` (N, 3) are indexed by ``fp.gaussian``.
    Returns (colour, alpha, range_sum[, CompositeTerms]).
    """
    h, w = fp.height, fp.width
    colour = np.zeros((h * w, 3), dtype=np.float32)
    alpha_img = np.zeros(h * w, dtype=np.float32)
    range_img = np.zeros(h * w, dtype=np.float32)
    m = len(fp)
    if m == 0:
        out = (colour.reshape(h, w, 3), alpha_img.reshape(h, w), range_img.reshape(h, w))
        if return_terms:
            z = np.zeros(0, np.float32)
            return out + (CompositeTerms(z, z, z, np.zeros(0, np.int64), np.zeros(0, np.int64)),)
        return out
    opacities = np.asarray(opacities, dtype=np.float32)
    colours = np.asarray(colours, dtype=np.float32)
    gid = fp.gaussian
    alpha = opacities[gid]
    alpha *= fp.weight
    np.minimum(alpha, np.float32(ALPHA_MAX), out=alpha)
    alpha[alpha < np.float32(ALPHA_MIN)] = 0.0
    log_keep = np.log1p(-alpha)  # float32, <= 0
    csum = np.cumsum(log_keep, dtype=np.float64)  # inclusive, over all pixels
    pix = fp.pixel
    new = np.empty(m, dtype=bool)
    new[0] = True
    np.not_equal(pix[1:], pix[:-1], out=new[1:])
    starts = np.flatnonzero(new)
    del new
    counts = np.diff(np.append(starts, m))
    before = np.zeros(starts.size, dtype=np.float64)
    before[1:] = csum[starts[1:] - 1]
    csum -= np.repeat(before, counts)  # inclusive log T within each pixel
    dead = csum < np.log(T_MIN)
    csum -= log_keep  # exclusive
    trans = np.exp(csum).astype(np.float32)
    del csum
    weight = alpha * trans
    weight[dead] = 0.0
    pixels = pix[starts]
    alpha_img[pixels] = np.add.reduceat(weight, starts)
    range_img[pixels] = np.add.reduceat(weight * fp.ranges[gid], starts)
    for ch in range(3):
        colour[pixels, ch] = np.add.reduceat(weight * np.ascontiguousarray(colours[:, ch])[gid], starts)
    np.clip(alpha_img, 0.0, 1.0, out=alpha_img)
    out = (colour.reshape(h, w, 3), alpha_img.reshape(h, w), range_img.reshape(h, w))
    if return_terms:
        return out + (CompositeTerms(alpha, trans, weight, starts, pixels),)
    return out


def composite(fp: Footprints, opacities: np.ndarray, colours: np.ndarray):
    """Composite footprints: (colour (H, W, 3) over black, alpha (H, W), expected range (H, W)).

    opacities (N,) in [0, 1] and colours (N, 3) (already evaluated for this
    camera) are indexed by ``fp.gaussian``. All outputs float32; range is 0
    where alpha is 0.
    """
    colour, alpha, range_sum = accumulate(fp, opacities, colours)
    return colour, alpha, normalise_range(range_sum, alpha)


def normalise_range(range_sum: np.ndarray, alpha: np.ndarray, floor: float = 1e-6) -> np.ndarray:
    """Expected range ``range_sum / alpha`` where alpha > floor, else 0."""
    out = np.zeros_like(range_sum)
    ok = alpha > floor
    out[ok] = range_sum[ok] / alpha[ok]
    return out
