"""Backward of front-to-back compositing (:mod:`rasterizer.composite`) for fixed footprints.

Forward, per pixel p and its contributions k (front to back, see
:func:`rasterizer.composite.accumulate`)::

    alpha_k = min(0.99, o_{g_k} g_k)   (0 when < 1/255),   T_k = prod_{j<k} (1 - alpha_j)
    w_k = alpha_k T_k,   C_p = sum_k w_k c_{g_k},   A_p = sum_k w_k

With ``s_k = G_p . c_{g_k} + H_p`` (G = dL/dC, H = dL/dA) the exact gradient is::

    dL/dalpha_k = T_k s_k - (sum_{i>k} w_i s_i) / (1 - alpha_k)

The suffix sum is a segmented reverse cumsum (one float64 cumsum over all
contributions, minus each segment's total); ``dalpha/do = g`` where the clamp
at 0.99 is inactive. Skipped (alpha < 1/255) and terminated (T < 1e-4)
contributions have zero gradient: the skip/termination sets are treated as
constants, like the CUDA kernels do. No loop over pixels or Gaussians.

:class:`BlendOperator` is the sparse linear map colours (N, 3) -> image
(P, 3) for fixed opacities (rows = pixels, optionally divided by A_p), used
by the conjugate-gradient colour solve and for the colour gradient.
"""

from __future__ import annotations

import numpy as np

from ..composite import ALPHA_MAX, CompositeTerms
from ..splat import Footprints


def segment_ends(starts: np.ndarray, m: int) -> np.ndarray:
    """(P,) one-past-the-last index of each segment given its starts (ascending) and the total M."""
    return np.append(starts[1:], m).astype(np.int64)


def suffix_sums(values: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Exclusive reverse cumsum within segments: out_k = sum of values after k in k's segment (float64)."""
    m = values.shape[0]
    if m == 0:
        return np.zeros(0, np.float64)
    cs = np.cumsum(values, dtype=np.float64)
    ends = segment_ends(starts, m)
    total = cs[ends - 1]  # inclusive cumsum at each segment's last entry
    return np.repeat(total, ends - starts) - cs


def opacity_gradient(fp: Footprints, terms: CompositeTerms, opacities: np.ndarray, colours: np.ndarray,
                     grad_colour: np.ndarray, grad_alpha: np.ndarray | None = None) -> np.ndarray:
    """dL/d opacity (N,) float64 from per-pixel dL/dC (H*W, 3) and dL/dA (H*W,) of one composite.

    ``terms`` must come from ``accumulate(fp, opacities, colours, return_terms=True)``.
    """
    n = opacities.shape[0]
    m = len(fp)
    if m == 0:
        return np.zeros(n, np.float64)
    pix, gid = fp.pixel, fp.gaussian
    s = np.einsum("mc,mc->m", np.asarray(grad_colour, np.float32)[pix], np.asarray(colours, np.float32)[gid])
    if grad_alpha is not None:
        s += np.asarray(grad_alpha, np.float32)[pix]
    live = terms.weight > 0
    after = suffix_sums(terms.weight * s, terms.starts)
    dalpha = terms.transmittance * s - after / (1.0 - terms.alpha)
    unclamped = live & (np.asarray(opacities, np.float32)[gid] * fp.weight < np.float32(ALPHA_MAX))
    return np.bincount(gid, weights=np.where(unclamped, dalpha * fp.weight, 0.0), minlength=n)


class BlendOperator:
    """Sparse blend matrix B (H*W, N) of one composite: image = B @ colours.

    ``normalise=True`` divides each row by the pixel's alpha A_p (the colour
    the ERP renderer shows, C/A), rows with A_p < ``floor`` are zero.
    """

    def __init__(self, fp: Footprints, terms: CompositeTerms, n: int, *, normalise: bool = True,
                 floor: float = 1.0 / 255.0) -> None:
        p = fp.height * fp.width
        m = len(fp)
        data = terms.weight.astype(np.float64)
        self.alpha = np.zeros(p, np.float64)
        if m:
            self.alpha[terms.pixels] = np.add.reduceat(data, terms.starts)
        if normalise and m:
            a = self.alpha[fp.pixel]
            data = np.where(a >= floor, data / np.maximum(a, floor), 0.0)
        counts = np.bincount(fp.pixel, minlength=p) if m else np.zeros(p, np.int64)
        indptr = np.zeros(p + 1, np.int64)
        np.cumsum(counts, out=indptr[1:])
        import scipy.sparse as sp  # only +opt needs it; importing rasterizer stays light

        self.matrix = sp.csr_matrix((data, fp.gaussian.astype(np.int32), indptr), shape=(p, n))
        self.normalised = normalise
        self.covered = self.alpha >= floor

    def __matmul__(self, colours: np.ndarray) -> np.ndarray:
        """Image (H*W, 3) float64 of colours (N, 3)."""
        return self.matrix @ colours

    def rmatvec(self, image: np.ndarray) -> np.ndarray:
        """B^T image: (N, 3) float64 from a per-pixel array (H*W, 3)."""
        return self.matrix.T @ image
