"""Descriptor matching of two panoramas' features (numpy only): nearest neighbours both ways with Lowe's ratio
test, over all pairs (:func:`putative_matches`) or over the pairs whose bearings fit a relative pose
(:func:`guided_matches`). Distances are computed in chunks of rows; the chunks are independent and run on two
threads, so results are those of one pass. One estimate matches the same two descriptor sets six to ten times
(seeds, guided rounds under several poses), so :class:`Distances` keeps each chunk once it is computed.
"""

from __future__ import annotations

import numpy as np

from rasterizer.threads import map_threads

#: Rows of descriptor distances computed at a time.
_DIST_ROWS = 1024


def _row_slices(n: int) -> list[slice]:
    """Chunks of :data:`_DIST_ROWS` descriptor rows covering ``n``."""
    return [slice(s, min(s + _DIST_ROWS, n)) for s in range(0, n, _DIST_ROWS)]


def _distance_rows(rows: np.ndarray, desc_b: np.ndarray) -> np.ndarray:
    """Squared RootSIFT distances (len(rows), len(desc_b)) float32 of unit descriptors."""
    return np.maximum(2.0 - 2.0 * (rows @ desc_b.T), 0.0)


class Distances:
    """Squared RootSIFT distances between descriptor sets ``a`` (Na, 128) and ``b`` (Nb, 128) float32, unit
    rows, computed per chunk of :data:`_DIST_ROWS` rows of ``a`` when first asked for and kept (4 Na Nb bytes at
    most). Chunks are independent, so two threads may ask for different ones at once."""

    def __init__(self, a: np.ndarray, b: np.ndarray):
        self.a, self.b = a, b
        self._chunks: dict[int, np.ndarray] = {}

    def rows(self, sl: slice) -> np.ndarray:
        """(rows, Nb) distances of ``sl``, one of :func:`_row_slices` (len(a))."""
        if sl.start not in self._chunks:
            self._chunks[sl.start] = _distance_rows(self.a[sl], self.b)
        return self._chunks[sl.start]

    def chunks(self):
        """Yield (rows slice, distances) over all of ``a``."""
        for sl in _row_slices(len(self.a)):
            yield sl, self.rows(sl)


def mutual_matches(dist: Distances, ratio: float) -> np.ndarray:
    """(M, 2) index pairs: nearest neighbours both ways passing Lowe's ratio test."""
    na, nb = len(dist.a), len(dist.b)
    best_d, second = np.full(na, np.inf), np.full(na, np.inf)
    best_j = np.zeros(na, int)
    col_best, col_arg = np.full(nb, np.inf), np.zeros(nb, int)
    for sl, d2 in dist.chunks():
        part = np.partition(d2, 1, axis=1)[:, :2] if nb > 1 else np.concatenate([d2, d2 + np.inf], 1)
        best_d[sl], second[sl] = part[:, 0], part[:, 1]
        best_j[sl] = np.argmin(d2, axis=1)
        cm = np.argmin(d2, axis=0)
        cv = d2[cm, np.arange(nb)]
        upd = cv < col_best
        col_best[upd], col_arg[upd] = cv[upd], cm[upd] + sl.start
    keep = np.isfinite(best_d) & (best_d < ratio * ratio * second) & (col_arg[best_j] == np.arange(na))
    return np.stack([np.nonzero(keep)[0], best_j[keep]], 1)


def _stable_order(major: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Stable argsort by (``major`` index, ``dist``): one 64-bit key of the index above the float32 distance's
    bits (a non-negative float32's bits order as its value; + 0 turns -0.0 into 0.0), not a three-key lexsort."""
    bits = (dist.astype(np.float32) + np.float32(0.0)).view(np.uint32)
    return np.argsort((major.astype(np.uint64) << np.uint64(32)) | bits, kind="stable")


def _mutual_among(dist: Distances, ratio: float, candidates) -> np.ndarray:
    """:func:`mutual_matches` restricted to the pairs ``candidates(rows)`` ((r, c) index arrays in row-major
    order, as ``np.nonzero`` gives them, r local to the rows slice) admits: nearest neighbours both ways among
    them, ratio-tested against the second nearest candidate of the row (none: passes). Ties go to the lower
    index, as ``argmin``'s do; the candidates are a few percent of all pairs, so they are sorted instead of
    scanning dense rows."""
    def chunk(sl):  # (rows, columns, squared distances) of one chunk's admitted pairs
        d2 = dist.rows(sl)
        r, c = candidates(sl)
        return r + sl.start, c, d2[r, c]

    parts = map_threads(chunk, _row_slices(len(dist.a)))  # independent chunks: the same pairs, in order
    r, c, d = (np.concatenate([p[i] for p in parts]) if parts else np.zeros(0, int) for i in range(3))
    if r.size == 0:
        return np.zeros((0, 2), int)
    v = d.astype(np.float64)
    # the candidates come by row, then column: a stable sort by (row, distance) orders them as
    # lexsort((c, v, r)) would, and by (column, distance) as lexsort((r, v, c))
    o = _stable_order(r, d)  # by row, then distance, then column
    r1, c1, v1 = r[o], c[o], v[o]
    first = np.flatnonzero(np.r_[True, r1[1:] != r1[:-1]])
    second = np.full(first.size, np.inf)
    has_two = np.diff(np.r_[first, r1.size]) > 1
    second[has_two] = v1[first[has_two] + 1]
    o = _stable_order(c, d)  # by column, then distance, then row
    c2 = c[o]
    col_first = np.flatnonzero(np.r_[True, c2[1:] != c2[:-1]])
    col_arg = np.full(len(dist.b), -1)
    col_arg[c2[col_first]] = r[o][col_first]
    best_row, best_j = r1[first], c1[first]
    keep = (v1[first] < ratio * ratio * second) & (col_arg[best_j] == best_row)
    return np.stack([best_row[keep], best_j[keep]], 1)


def putative_matches(dist: Distances, ratio: float = 0.8) -> np.ndarray:
    """(M, 2) index pairs: nearest neighbours both ways passing Lowe's ratio test."""
    if len(dist.a) < 2 or len(dist.b) < 2:
        return np.zeros((0, 2), int)
    return mutual_matches(dist, ratio)


def guided_matches(fa, fb, dist: Distances, R, t, *, max_deg: float, ratio: float = 0.9) -> np.ndarray:
    """Pairs whose bearings fit the pose (epipolar angle < ``max_deg``, in front of both cameras),
    nearest in descriptor among those candidates, ratio-tested and mutual; (M, 2)."""
    sin_thr = np.sin(np.radians(max_deg))
    g = fb @ R.T
    n = np.cross(t, g)
    n_hat = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    cross_a = np.linalg.norm(np.cross(t, fa), axis=-1)
    at, gt = fa @ t, g @ t

    def fits_pose(sl):  # (r, c) of the rows' pairs that fit
        # the first test leaves a few percent of the pairs: the others are evaluated at those only
        near = fa[sl] @ n_hat.T
        np.abs(near, out=near)
        r, c = np.nonzero(near < sin_thr)
        a = fa[sl][r]
        sin_b = np.abs(np.einsum("ij,ij->i", a, n[c])) / np.maximum(cross_a[sl][r], 1e-12)
        k = np.einsum("ij,ij->i", a, g[c])
        den = np.maximum(1 - k * k, 1e-9)
        a_t, g_t = at[sl][r], gt[c]
        ok = (sin_b < sin_thr) & ((a_t - k * g_t) / den > 0) & ((k * a_t - g_t) / den > 0)
        return r[ok], c[ok]

    return _mutual_among(dist, ratio, fits_pose)
