"""Packed sort keys ``pixel | depth rank | q`` and the dense pixel-space blocks that emit them.

Each (pixel, Gaussian) contribution is one uint64 key: the flat pixel index
in the high bits, the Gaussian's depth rank below it and the quantised
Mahalanobis radius^2 q in the low bits (:class:`KeyLayout`), so one integer
sort orders contributions by pixel, then by depth. :func:`class_keys` builds
the keys of one size class of footprints as a dense (KY, KX, n) block.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .projection import Q_MAX


@dataclass(frozen=True)
class KeyLayout:
    pix_bits: int
    rank_bits: int
    q_bits: int
    rank_shift: int

    @property
    def pix_shift(self) -> int:
        return self.rank_shift + self.rank_bits

    @property
    def q_scale(self) -> float:
        """q -> integer factor; q <= Q_MAX maps below 2^q_bits - 1 even after rounding."""
        return float((1 << self.q_bits) - 2) / Q_MAX

    def pixels(self, key: np.ndarray) -> np.ndarray:
        """(M,) flat pixel index of sorted keys (uint32 or int64)."""
        if self.pix_shift >= 32 and np.little_endian and key.dtype.byteorder in ("<", "="):
            return key.view(np.uint32)[1::2] >> np.uint32(self.pix_shift - 32)
        return (key >> np.uint64(self.pix_shift)).astype(np.int64)

    def ranks(self, key: np.ndarray) -> np.ndarray:
        """(M,) int64 depth rank of the keys."""
        r = key >> np.uint64(self.rank_shift)
        r &= np.uint64((1 << self.rank_bits) - 1)
        return r.view(np.int64)

    def weights(self, key: np.ndarray) -> np.ndarray:
        """(M,) float32 opacity-free weight exp(-q/2) of the keys."""
        if np.little_endian and key.dtype.byteorder in ("<", "="):
            low = key.view(np.uint32)[0::2]
        else:
            low = (key & np.uint64(0xFFFFFFFF)).astype(np.uint32)
        q = low & np.uint32((1 << self.q_bits) - 1)
        q = q.astype(np.float32)
        q *= np.float32(-0.5 / self.q_scale)
        return np.exp(q, out=q)


def class_keys(kxc, kyc, x0, kx, y0, ky, mx, my, ca, cb, cc, qc, rkey, h, w, period, s0,
                layout: KeyLayout, wrap: bool = True, out: np.ndarray | None = None, pos: int = 0):
    """Packed sort keys of one dense (kyc, kxc, n) block of pixel-space footprints.

    The Gaussian axis is innermost, so the keys come out offset by offset: each
    offset's keys are sorted when the Gaussians are ordered by (box origin, rank)
    and no column wraps (see :func:`_flat_keys`). ``ca, cb, cc``: float32 conic
    (xx, 2 xy, yy); ``qc`` float32 cut; ``rkey`` uint64 rank already shifted;
    ``wrap``: some boxes may wrap around the column period (else none does).
    Returns the keys, or with ``out`` writes them to ``out[pos:]`` and returns
    the position after them.

    Elements outside the box or the image get an infinite offset, so their q is
    inf or NaN and never a hit: their (possibly wrapped-around) keys are never
    selected. Keys are built with modular uint64 additions, exact for every hit.
    """
    shift = np.uint64(layout.pix_shift)
    ox = np.arange(kxc, dtype=np.int64)[:, None]
    dx = (x0 - mx).astype(np.float32)[None, :] + ox.astype(np.float32)
    dy = (y0 - my).astype(np.float32)[None, :] + np.arange(kyc, dtype=np.float32)[:, None]
    bad_x = ox >= kx[None, :]
    if wrap and period is not None:
        cols = np.mod(x0[None, :] + ox - s0, period) + s0
        bad_x |= (cols < 0) | (cols >= w)
        base = (y0 * w).astype(np.uint64) << shift
        colkey = cols.astype(np.uint64) << shift
    else:
        cols = x0[None, :] + ox
        bad_x |= (cols < 0) | (cols >= w)
        base = (y0 * w + x0).view(np.uint64) << shift
        colkey = None
    base += rkey
    dx[bad_x] = np.inf
    dy[np.arange(kyc)[:, None] >= ky[None, :]] = np.inf  # rows: boxes are clipped to the image
    rowkey = base[None, :] + ((np.arange(kyc, dtype=np.uint64) * np.uint64(w)) << shift)[:, None]
    with np.errstate(invalid="ignore", over="ignore"):
        q = (cb * dy)[:, None, :] * dx[None, :, :]
        q += (cc * dy * dy)[:, None, :]
        q += (ca * dx * dx)[None, :, :]
        hit = q <= qc[None, None, :]
        np.maximum(q, 0.0, out=q)
        q *= np.float32(layout.q_scale)
        qi = q.astype(np.uint32)
    if colkey is None:
        dense = rowkey[:, None, :] + (np.arange(kxc, dtype=np.uint64) << shift)[None, :, None]
    else:
        dense = rowkey[:, None, :] + colkey[None, :, :]
    dense += qi
    if out is None:
        return dense[hit]
    # the hits' positions, then a take straight into ``out``: np.compress (and a take in its default
    # "raise" mode) with ``out`` first copies into a temporary; every position is in range
    where = np.flatnonzero(hit)
    np.take(dense.reshape(-1), where, out=out[pos:pos + where.size], mode="wrap")
    return pos + where.size
