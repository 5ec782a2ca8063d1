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
over the pixel segments. The contributions are processed in cache-sized
chunks of whole pixels (:func:`composite_segments`), which the renderer also
calls directly on its sorted footprint keys.

The per-contribution weights and transmittances (``return_terms=True``) are
what a backward pass (colour/opacity refinement with fixed geometry) needs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .splat import ALPHA_MIN, Footprints

ALPHA_MAX = 0.99
T_MIN = 1e-4
#: Largest colour a Gaussian composites with (:func:`rasterizer.sh.sh_to_rgb` clamps there): every
#: contribution a pixel takes weighs at least ALPHA_MIN * T_MIN, so at this colour it alone saturates an
#: 8-bit pixel, while sums, the Yin-Yang merge, resizes and the V/A division of such colours stay far from
#: float32's overflow (3.4e38), which SH coefficients near float32's limit reach.
COLOUR_MAX = float(1.0 / (ALPHA_MIN * T_MIN))


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


#: Contributions per chunk of the compositing maths (whole pixels per chunk): its ~20
#: temporaries then stay in the core's cache instead of streaming through memory.
_CHUNK = 1 << 16


def segment_starts(pixel: np.ndarray) -> np.ndarray:
    """(P,) int64 index of the first contribution of each run of equal ``pixel`` values."""
    m = pixel.shape[0]
    new = np.empty(m, dtype=bool)
    if m:
        new[0] = True
        np.not_equal(pixel[1:], pixel[:-1], out=new[1:])
    return np.flatnonzero(new)


def composite_segments(m: int, starts: np.ndarray, fetch, table: np.ndarray, terms: bool = False,
                       log_t: np.ndarray | None = None):
    """Front-to-back compositing of M contributions in pixel segments, chunk by chunk.

    ``starts`` (P,): first contribution of each pixel; ``fetch(a, b)`` returns
    (index (b-a,) into ``table``, opacity-free weight g (b-a,) float32) of
    contributions a..b-1; ``table`` (N, 8) float32 C-contiguous rows
    [opacity, r, g, b, range, 0, 0, 0] (:func:`gaussian_table`; one 32-byte
    row per contribution is one memory access). Returns the per-pixel sums
    (P, 5) float32 [alpha, r, g, b, range] of ``w_i = alpha_i T_i`` times
    (1, colour, range), and with ``terms`` the full (M,) alpha, T and w.
    The rules are those of the module docstring; the exclusive log-T is a
    float64 cumulative sum restarted at every pixel.

    ``log_t`` (P,) float64, optional, in and out: each pixel's log transmittance
    before these contributions (its earlier contributions were composited by
    a previous call: the front-to-back renderer feeds depth chunk after depth
    chunk), overwritten with the log transmittance after them. A pixel whose
    log T is below ``log(T_MIN)`` takes no further contribution.
    """
    p = starts.size
    sums = np.empty((p, 5), dtype=np.float32)
    if terms:
        alpha_all = np.empty(m, dtype=np.float32)
        trans_all = np.empty(m, dtype=np.float32)
        weight_all = np.empty(m, dtype=np.float32)
    rows32 = table.view(np.complex128).reshape(-1, 2)  # 32-byte rows
    cuts = np.unique(np.searchsorted(starts, np.arange(0, m, _CHUNK), side="left"))
    cuts = np.append(cuts[cuts < p], p)
    ends = np.append(starts[1:], m)
    amax, amin, log_tmin = np.float32(ALPHA_MAX), np.float32(ALPHA_MIN), np.log(T_MIN)
    for sa, sb in zip(cuts[:-1], cuts[1:]):
        a, b = int(starts[sa]), int(ends[sb - 1])
        ls = starts[sa:sb] - a
        idx, g = fetch(a, b)
        rows = np.take(rows32, idx, axis=0).view(np.float32)  # (b-a, 8)
        alpha = rows[:, 0] * g
        np.minimum(alpha, amax, out=alpha)
        alpha *= alpha >= amin  # skipped: exactly 0
        log_keep = np.negative(alpha)
        np.log1p(log_keep, out=log_keep)
        log_keep = log_keep.astype(np.float64)  # <= 0; float64 ufuncs beat mixed-type ones
        # one cumulative sum over the chunk restarts at every pixel: its first term also takes the
        # pixel's starting log T minus what the sum holds there (the pixels before: their start, their total)
        start = np.zeros(ls.size) if log_t is None else log_t[sa:sb].copy()
        step = start.copy()
        if ls.size > 1:
            step[1:] -= start[:-1] + np.add.reduceat(log_keep, ls)[:-1]
        log_keep[ls] += step
        csum = np.cumsum(log_keep)  # inclusive log T of each contribution
        if log_t is not None:
            log_t[sa:sb] = csum[np.append(ls[1:], b - a) - 1]
        alive = csum >= log_tmin
        csum -= log_keep  # exclusive
        csum[ls] = start
        trans = np.exp(csum, out=csum).astype(np.float32)
        weight = alpha * trans
        weight *= alive  # terminated: exactly 0
        out = sums[sa:sb]
        out[:, 0] = np.add.reduceat(weight, ls)
        for ch in range(1, 5):
            out[:, ch] = np.add.reduceat(weight * rows[:, ch], ls)
        if terms:
            alpha_all[a:b], trans_all[a:b], weight_all[a:b] = alpha, trans, weight
    if terms:
        return sums, (alpha_all, trans_all, weight_all)
    return sums, None


def images_from_sums(sums: np.ndarray, pixels: np.ndarray, h: int, w: int):
    """(colour (H, W, 3), alpha (H, W), range_sum (H, W)) float32 images of per-pixel sums."""
    colour = np.zeros((h * w, 3), dtype=np.float32)
    alpha_img = np.zeros(h * w, dtype=np.float32)
    range_img = np.zeros(h * w, dtype=np.float32)
    if pixels.size:
        alpha_img[pixels] = sums[:, 0]
        colour[pixels] = sums[:, 1:4]
        range_img[pixels] = sums[:, 4]
        np.clip(alpha_img, 0.0, 1.0, out=alpha_img)
    return colour.reshape(h, w, 3), alpha_img.reshape(h, w), range_img.reshape(h, w)


def gaussian_table(opacities: np.ndarray, colours: np.ndarray, ranges: np.ndarray,
                   order: np.ndarray | None = None) -> np.ndarray:
    """(N, 8) float32 C-contiguous rows [opacity, r, g, b, range, 0, 0, 0] for :func:`composite_segments`.

    ``order`` (N,) int, optional: row k is then Gaussian ``order[k]`` (the depth-rank order of a
    render), gathered as one 32-byte element per row (a fancy index of (N, 8) rows takes twice as long).
    """
    table = np.zeros((ranges.shape[0], 8), dtype=np.float32)
    table[:, 0] = opacities
    table[:, 1:4] = colours
    table[:, 4] = ranges
    if order is None:
        return table
    return np.take(table.view(np.complex128).reshape(-1, 2), order, axis=0).view(np.float32)


def ranked_table(opacities: np.ndarray, colours: np.ndarray, ranges: np.ndarray, rank: np.ndarray,
                 n: int) -> np.ndarray:
    """(n, 8) float32 :func:`gaussian_table` in depth-rank order, filled only at the rows ``rank`` (m,)
    of the m Gaussians given by their (m,) columns (the others stay 0): a camera that keeps few
    Gaussians evaluates colours for those only."""
    table = np.zeros((n, 8), dtype=np.float32)
    rows = gaussian_table(opacities, colours, ranges)
    table.view(np.complex128).reshape(-1, 2)[rank] = rows.view(np.complex128).reshape(-1, 2)
    return table


def accumulate(fp: Footprints, opacities: np.ndarray, colours: np.ndarray, *, return_terms: bool = False):
    """Premultiplied sums: colour (H, W, 3), alpha (H, W), range*alpha (H, W), float32.

    ``opacities`` (N,) and ``colours`` (N, 3) are indexed by ``fp.gaussian``.
    Returns (colour, alpha, range_sum[, CompositeTerms]).
    """
    h, w = fp.height, fp.width
    m = len(fp)
    if m == 0:
        out = images_from_sums(np.zeros((0, 5), np.float32), np.zeros(0, np.int64), h, w)
        if return_terms:
            z = np.zeros(0, np.float32)
            return out + (CompositeTerms(z, z, z, np.zeros(0, np.int64), np.zeros(0, np.int64)),)
        return out
    table = gaussian_table(np.asarray(opacities, dtype=np.float32), np.asarray(colours, dtype=np.float32),
                           fp.ranges)
    gid, g = fp.gaussian, fp.weight
    pix = fp.pixel
    starts = segment_starts(pix)
    sums, terms = composite_segments(m, starts, lambda a, b: (gid[a:b], g[a:b]), table, terms=return_terms)
    pixels = pix[starts]
    out = images_from_sums(sums, pixels, h, w)
    if return_terms:
        alpha, trans, weight = terms
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
