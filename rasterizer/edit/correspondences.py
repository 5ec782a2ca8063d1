"""The encoder's cross-view matches (``matches`` output, :mod:`export.matches`) on ERP images.

``matches`` (2, G, H, W, 5) float32 per [view][grid][row][col]: channels
:data:`CHANNELS`. :func:`pack` / :func:`unpack` store them in 6 bytes per
pixel instead of 20; :func:`erp_matches` turns one view's Yin/Yang matches
into, for every pixel of an ERP of that view, the ERP pixel of the other
view it matches; :func:`carry` moves a per-pixel map through them.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from .. import geometry as geo
from ..yin_yang import grid_pixel

#: Channels of the ``matches`` output, in order.
CHANNELS = ("grid", "col", "row", "score", "status")
#: ``status`` values: consistent, occluded in the other view, left-right failure (the encoder's), and
#: PHOTO: the two pixels differ in colour (set by :func:`photo_checked`, never by the encoder).
OK, OCCLUDED, INCONSISTENT, PHOTO = 0, 1, 2, 3
#: Fixed-point steps per pixel of the packed coordinates.
_SUBPIXEL = 32


def pack(matches: np.ndarray) -> dict[str, np.ndarray]:
    """(2, G, H, W, 5) float32 -> {"code": uint8 grid * 4 + status, "col", "row": uint16 (1/32 px,
    offset 0.5 so -0.5 is 0), "score": uint8 (1/255)}; 6 bytes per pixel."""
    m = np.asarray(matches, dtype=np.float32)
    if m.ndim != 5 or m.shape[-1] != len(CHANNELS):
        raise ValueError(f"matches must be (2, G, H, W, {len(CHANNELS)}), got {m.shape}")
    code = (np.rint(m[..., 0]).astype(np.uint8) * 4 + np.rint(m[..., 4]).astype(np.uint8)).astype(np.uint8)
    lim = np.float32(np.iinfo(np.uint16).max)

    def fixed(v):
        return np.clip(np.rint((v + 0.5) * _SUBPIXEL), 0, lim).astype(np.uint16)

    score = np.rint(np.clip(m[..., 3], 0, 1) * 255).astype(np.uint8)
    return {"code": code, "col": fixed(m[..., 1]), "row": fixed(m[..., 2]), "score": score}


def unpack(packed: dict[str, np.ndarray]) -> np.ndarray:
    """Inverse of :func:`pack` (coordinates to 1/32 pixel, score to 1/255)."""
    code = packed["code"]
    out = np.empty(code.shape + (len(CHANNELS),), dtype=np.float32)
    out[..., 0] = code // 4
    out[..., 1] = packed["col"].astype(np.float32) / _SUBPIXEL - 0.5
    out[..., 2] = packed["row"].astype(np.float32) / _SUBPIXEL - 0.5
    out[..., 3] = packed["score"].astype(np.float32) / 255.0
    out[..., 4] = code % 4
    return out


def grid_point_directions(grid: np.ndarray, col: np.ndarray, row: np.ndarray, height: int, width: int,
                          erp: bool = False) -> np.ndarray:
    """Camera-frame unit rays (..., 3) at continuous (col, row) of a Yin (grid 0) / Yang (1) or ERP grid."""
    if erp:
        lon = (col + 0.5) / width * 2 * np.pi - np.pi
        lat = np.pi / 2 - (row + 0.5) / height * np.pi
        return geo.direction_from_lat_lon(lat, lon)
    lat = geo.YIN_LAT_MAX - (row + 0.5) * (2 * geo.YIN_LAT_MAX) / height
    lon = -geo.YIN_LON_MAX + (col + 0.5) * (2 * geo.YIN_LON_MAX) / width
    d = geo.direction_from_lat_lon(lat, lon)
    yang = np.asarray(grid) > 0.5
    return np.where(yang[..., None], d @ geo.YANG_ROTATION.T, d)


@lru_cache(maxsize=8)
def erp_to_grid_pixel(grids: tuple[str, ...], height: int, width: int, erp_height: int) -> np.ndarray:
    """(He, 2 He) flat index into one view's (G, H, W) grid layout: the nearest pixel of the grid that
    owns each ERP pixel's direction (Yin where its blend weight >= 0.5, as the renderer's merge). Read-only."""
    out = grid_pixel(geo.grid_directions("erp", erp_height, 2 * erp_height), grids, height, width)
    out.flags.writeable = False
    return out


@dataclass(frozen=True)
class ErpMatches:
    """Per ERP pixel of one view: the matched ERP pixel (col, row, continuous) in the other view,
    the match score and status (:data:`OK`, :data:`OCCLUDED`, :data:`INCONSISTENT`, :data:`PHOTO`); each (He, We)."""

    col: np.ndarray
    row: np.ndarray
    score: np.ndarray
    status: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        """(He, We) bool: the match passed the left-right / occlusion check (and the colour check, if run)."""
        return self.status == OK

    @property
    def weak(self) -> np.ndarray:
        """(He, We) bool: a left-right failure whose two pixels agree in colour (after :func:`photo_checked`):
        the other view's range there disagrees, but this view's match may still be right."""
        return self.status == INCONSISTENT


def erp_matches(matches: np.ndarray, view: int, grids: tuple[str, ...], erp_height: int) -> ErpMatches:
    """``matches`` (2, G, H, W, 5) -> :class:`ErpMatches` of ``view`` on a (erp_height, 2 erp_height) ERP."""
    m = np.asarray(matches)[view]
    g_count, h, w = m.shape[:3]
    pick = m.reshape(g_count * h * w, -1)[erp_to_grid_pixel(tuple(grids), h, w, int(erp_height))]
    d = grid_point_directions(pick[..., 0], pick[..., 1], pick[..., 2], h, w, erp=tuple(grids) == ("erp",))
    col, row = geo.project_to_grid("erp", d, erp_height, 2 * erp_height)
    return ErpMatches(col.astype(np.float32), row.astype(np.float32), pick[..., 3],
                      np.rint(pick[..., 4]).astype(np.uint8))


def photo_checked(match: ErpMatches, colour: np.ndarray, other_colour: np.ndarray, tol: float) -> ErpMatches:
    """``match`` with the consistent and the left-right-failed matches whose colours (H, W, 3) differ by
    more than ``tol`` (RGB distance) from the colour they land on in ``other_colour`` marked :data:`PHOTO`
    (occluded ones stay occluded). What is left :data:`INCONSISTENT` is then :attr:`ErpMatches.weak`."""
    seen, _ = carry(other_colour, match)
    off = (np.linalg.norm(seen - colour, axis=-1) > tol) & ((match.status == OK) | (match.status == INCONSISTENT))
    status = np.where(off, np.uint8(PHOTO), match.status).astype(np.uint8)
    return ErpMatches(match.col, match.row, match.score, status)


def carry(values: np.ndarray, match: ErpMatches) -> tuple[np.ndarray, np.ndarray]:
    """Pull a per-pixel map of the other view (He, We[, C]) to this view through ``match``.

    Nearest pixel (longitude wrapped, rows clamped). Returns (values (He, We[, C]),
    valid (He, We) bool: the match passed the left-right and occlusion check).
    """
    he, we = values.shape[:2]
    c = np.mod(np.rint(match.col).astype(np.int64), we)
    r = np.clip(np.rint(match.row).astype(np.int64), 0, he - 1)
    return values[r, c], match.valid
