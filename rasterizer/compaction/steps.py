"""The count cap's mask, and the footprint and range of a Gaussian it ranks by."""

from __future__ import annotations

import numpy as np

from ..gaussians import Gaussians
from .provenance import Provenance


def footprint(gaussians: Gaussians) -> np.ndarray:
    """(N,) tangential size: geometric mean of the two largest scales (world units)."""
    s = gaussians.scales
    a, b, c = s[:, 0], s[:, 1], s[:, 2]
    hi = np.maximum(np.maximum(a, b), c)
    mid = np.maximum(np.minimum(a, b), np.minimum(np.maximum(a, b), c))  # the median (a selection, exact)
    return np.sqrt(mid.astype(np.float64) * hi)


def _ranges_from_own_camera(gaussians: Gaussians, view: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    cam = c2w[:, :3, 3]
    m = gaussians.means
    d = [m[:, k] - np.take(cam[:, k], view) for k in range(3)]  # float64
    return np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])  # np.linalg.norm's order


def _view_of(prov: Provenance, n: int) -> np.ndarray:
    """(n,) reference view of each Gaussian (``prov.decode(n)[0]``, one division)."""
    return prov.flat_index(n) // (len(prov.grids) * prov.height * prov.width)


def cap_keep_mask(gaussians: Gaussians, prov: Provenance, alive: np.ndarray, count: int) -> np.ndarray:
    """(N,) bool: the ``count`` alive Gaussians with the largest opacity x footprint solid angle.

    Solid angle = footprint^2 / range^2 from the Gaussian's own reference
    (world area alone would drop the nearest, largest-on-screen ones first).
    """
    idx = np.flatnonzero(alive)
    if count >= idx.size:
        return alive.copy()
    view = _view_of(prov, len(gaussians))
    rng = np.maximum(_ranges_from_own_camera(gaussians, view, prov.c2w), 1e-9)
    score = gaussians.opacities.astype(np.float64) * (footprint(gaussians) / rng) ** 2
    keep = np.zeros(len(gaussians), dtype=bool)
    if count > 0:
        top = idx[np.argpartition(-score[idx], count - 1)[:count]]
        keep[top] = True
    return keep
