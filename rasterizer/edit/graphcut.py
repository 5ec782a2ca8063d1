"""Binary graph cut on ERP crops (numpy + scipy's max-flow): the carried mask made to follow the image.

:func:`refine_mask` is a classic contrast-sensitive Potts model (Boykov and Jolly, 2001) on one view:
each pixel of a crop around the mask pays ``log(p / (1 - p))`` for leaving the label the carry gave it
(``p`` = ``pull`` where a match decided it, ``fill`` where a superpixel or a push did), and each pair of
4-neighbours with different labels pays ``weight * exp(-|c_p - c_q|^2 / (2 beta^2))`` of their RGB
colours. Isolated pixels the matches carried wrongly flip to their neighbours' label unless a colour
edge separates them. The minimum is exact (:func:`min_cut`) over the pixels within ``band`` of a label
change; the others keep their label (on m3d_bedroom's prompts bands of 2-8 pixels give the same masks as
the whole crop, in half the time).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import breadth_first_order, maximum_flow

#: Integer steps per unit of energy (scipy's max-flow takes int32 capacities).
_SCALE = 1000


def min_cut(source: np.ndarray, sink: np.ndarray, i: np.ndarray, j: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """(n,) bool, True on the source side of a minimum s-t cut.

    source, sink (n,) >= 0: capacity of each node's edge from the source / to the sink (what the node pays
    on the other side); i, j, weight (E,): undirected node pairs and their capacity (>= 0). Capacities are
    rounded to 1 / ``_SCALE``.
    """
    n = source.size
    s, t = n, n + 1
    nodes = np.arange(n)
    rows = np.concatenate([np.full(n, s), nodes, i, j])
    cols = np.concatenate([nodes, np.full(n, t), j, i])
    cap = np.rint(np.concatenate([source, sink, weight, weight]) * _SCALE).astype(np.int32)
    keep = cap > 0
    graph = csr_matrix((cap[keep], (rows[keep], cols[keep])), shape=(n + 2, n + 2))
    graph.sum_duplicates()
    flow = maximum_flow(graph, s, t, method="dinic").flow
    residual = (graph - flow).tocsr()  # reverse edges get the flow back (flow is antisymmetric)
    residual.data = np.maximum(residual.data, 0)
    residual.eliminate_zeros()
    side = np.zeros(n + 2, dtype=bool)
    side[breadth_first_order(residual, s, directed=True, return_predecessors=False)] = True
    return side[:n]


def _crop(mask: np.ndarray, margin: int) -> tuple[int, slice, int]:
    """(shift, rows, width): rolling the ERP by ``shift`` columns puts the mask's columns (plus ``margin``)
    in ``[0, width)`` without crossing the seam (the widest mask-free run of columns is moved to the edge)."""
    h, w = mask.shape
    rows = np.nonzero(mask.any(1))[0]
    occupied = np.nonzero(mask.any(0))[0]
    gaps = np.diff(np.append(occupied, occupied[0] + w))  # to the next occupied column, around the seam
    k = int(np.argmax(gaps))
    first = int(occupied[(k + 1) % occupied.size])
    width = min(w - int(gaps[k]) + 1 + 2 * margin, w)
    return margin - first, slice(max(int(rows[0]) - margin, 0), min(int(rows[-1]) + margin + 1, h)), width


def refine_mask(mask: np.ndarray, matched: np.ndarray, colour: np.ndarray, *, weight: float, beta: float,
                pull: float, fill: float, margin: int, band: int) -> np.ndarray:
    """(H, W) bool: ``mask`` (H, W) bool after the graph cut of the module docstring.

    matched (H, W) bool: pixels whose label came from their own match (confidence ``pull``; the others
    ``fill``, both in (0.5, 1)); colour (H, W, 3) in [0, 1]. Only pixels of a crop ``margin`` pixels
    around the mask and within ``band`` pixels of a label change can change; the longitude wraps at the
    seam when the crop spans the whole ERP. ``weight`` <= 0 returns ``mask``.
    """
    if weight <= 0 or not mask.any():
        return mask
    h, w = mask.shape
    shift, rows, width = _crop(mask, margin)

    def cut(a):
        return np.roll(a, shift, axis=1)[rows, :width]

    m = cut(mask)
    ch, cw = m.shape
    idx = np.arange(ch * cw).reshape(ch, cw)
    pairs = [(idx[:, :-1], idx[:, 1:]), (idx[:-1], idx[1:])]
    if width == w:
        pairs.append((idx[:, -1], idx[:, 0]))  # the crop is the whole ring: close it at the seam
    i = np.concatenate([a.ravel() for a, _ in pairs])
    j = np.concatenate([b.ravel() for _, b in pairs])
    c = cut(colour).reshape(-1, 3)
    pair_w = weight * np.exp(-((c[i] - c[j]) ** 2).sum(-1) / (2.0 * beta**2))
    p = np.where(cut(matched), pull, fill).ravel()
    mf = m.ravel()
    u = np.where(mf, 1.0, -1.0) * (np.log(p) - np.log1p(-p))  # > 0: costs that much to leave the mask
    source, sink = np.maximum(u, 0.0), np.maximum(-u, 0.0)
    change = np.zeros(ch * cw, dtype=bool)
    differ = mf[i] != mf[j]
    change[i[differ]] = change[j[differ]] = True
    free = ndi.maximum_filter(change.reshape(ch, cw), size=2 * band + 1, mode="nearest").ravel()
    if not free.any():
        return mask
    for a, b in ((i, j), (j, i)):  # a free pixel next to a fixed one: the fixed label pulls it
        one = free[a] & ~free[b]
        source += np.bincount(a[one & mf[b]], weights=pair_w[one & mf[b]], minlength=ch * cw)
        sink += np.bincount(a[one & ~mf[b]], weights=pair_w[one & ~mf[b]], minlength=ch * cw)
    node = np.cumsum(free) - 1
    both = free[i] & free[j]
    mf = mf.copy()
    mf[free] = min_cut(source[free], sink[free], node[i[both]], node[j[both]], pair_w[both])
    out = np.roll(mask, shift, axis=1)
    out[rows, :width] = mf.reshape(ch, cw)
    return np.roll(out, -shift, axis=1)
