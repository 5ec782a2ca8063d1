"""ERP <-> Yin/Yang image resampling and ERP resizing (numpy only).

Grids and pixel centres are those of :mod:`rasterizer.geometry`
(conventions section 1): an H x W ERP maps to Yin and Yang images of
h x 3h with h = H // 2 by default. Sampling is bilinear at pixel centres.

* Reading an ERP wraps in longitude (column W is column 0) and reflects
  across the poles (row -1 is row 0 at longitude + pi), so Yang samples near
  the poles are exact neighbours, not clamped copies.
* Reading a Yin/Yang image clamps at its border (the blend weight there is 0).
* :func:`yin_yang_to_erp` blends the two in their ~6% overlap with weight
  ``w_yin = smoothstep(m_yin / (m_yin + m_yang))``, where ``m`` is the angular
  margin of the direction inside each grid's domain plus a one-pixel feather.
  The weight is 1 where only Yin sees the direction, 0 where only Yang does,
  and continuous in between, so there is no seam.

Images are (H, W) or (H, W, C) arrays of any float dtype (returned as
float32); the sampling maps are cached per size.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from . import geometry as geo


def _as_hwc(img: np.ndarray) -> tuple[np.ndarray, bool]:
    a = np.asarray(img)
    if a.ndim == 2:
        return a[:, :, None], True
    if a.ndim != 3:
        raise ValueError(f"image must be (H, W) or (H, W, C), got shape {a.shape}")
    return a, False


def _gather(img: np.ndarray, idx: np.ndarray, wts: np.ndarray) -> np.ndarray:
    """Weighted taps: (P, C) from img (H, W, C), idx/wts (P, T) flat indices."""
    chans = np.ascontiguousarray(img.reshape(-1, img.shape[2]).T, dtype=np.float32)  # (C, P_src)
    idx_t = np.ascontiguousarray(idx.T)
    w_t = np.ascontiguousarray(wts.T)
    out = np.empty((idx.shape[0], chans.shape[0]), dtype=np.float32)
    for c, src in enumerate(chans):  # 1-D gathers: far faster than gathering rows
        acc = src[idx_t[0]] * w_t[0]
        for t in range(1, idx_t.shape[0]):
            acc += src[idx_t[t]] * w_t[t]
        out[:, c] = acc
    return out


def _erp_taps(col: np.ndarray, row: np.ndarray, height: int, width: int, nearest: bool = False):
    """Bilinear (or nearest) taps into an ERP at continuous (col, row), wrap + pole reflection."""
    col = np.asarray(col, dtype=np.float64).ravel()
    row = np.asarray(row, dtype=np.float64).ravel()
    if nearest:
        c = np.rint(col).astype(np.int64)[:, None]
        r = np.rint(row).astype(np.int64)[:, None]
        w = np.ones((col.size, 1), dtype=np.float32)
    else:
        c0 = np.floor(col)
        r0 = np.floor(row)
        fc = (col - c0)[:, None]
        fr = (row - r0)[:, None]
        c = c0.astype(np.int64)[:, None] + np.array([0, 1, 0, 1])
        r = r0.astype(np.int64)[:, None] + np.array([0, 0, 1, 1])
        w = np.concatenate([(1 - fc) * (1 - fr), fc * (1 - fr), (1 - fc) * fr, fc * fr], axis=1)
    # reflect across the poles (row -1 - k is row k at longitude + pi)
    north, south = r < 0, r >= height
    r = np.where(north, -1 - r, np.where(south, 2 * height - 1 - r, r))
    c = np.where(north | south, c + width // 2, c)
    r = np.clip(r, 0, height - 1)
    c = np.mod(c, width)
    return r * width + c, w.astype(np.float32)


def _grid_taps(col: np.ndarray, row: np.ndarray, height: int, width: int):
    """Bilinear taps into a Yin/Yang image at continuous (col, row), clamped to the border."""
    col = np.clip(np.asarray(col, dtype=np.float64).ravel(), 0, width - 1)
    row = np.clip(np.asarray(row, dtype=np.float64).ravel(), 0, height - 1)
    c0 = np.minimum(np.floor(col), max(width - 2, 0))
    r0 = np.minimum(np.floor(row), max(height - 2, 0))
    fc = (col - c0)[:, None]
    fr = (row - r0)[:, None]
    c = np.minimum(c0.astype(np.int64)[:, None] + np.array([0, 1, 0, 1]), width - 1)
    r = np.minimum(r0.astype(np.int64)[:, None] + np.array([0, 0, 1, 1]), height - 1)
    w = np.concatenate([(1 - fc) * (1 - fr), fc * (1 - fr), (1 - fc) * fr, fc * fr], axis=1)
    return r * width + c, w.astype(np.float32)


@lru_cache(maxsize=16)
def _to_grid_maps(kind: str, h: int, w: int, height: int, width: int, nearest: bool):
    d = geo.grid_directions(kind, h, w).reshape(-1, 3)
    col, row = geo.project_to_grid("erp", d, height, width)
    idx, wts = _erp_taps(col, row, height, width, nearest)
    idx.setflags(write=False)
    wts.setflags(write=False)
    return idx, wts


def erp_to_yin_yang(erp: np.ndarray, *, height: int | None = None, nearest: bool = False):
    """Sample the Yin and Yang images of an ERP image.

    erp: (H, W[, C]) ERP image. height: Yin/Yang height h (default H // 2);
    both outputs are (h, 3h[, C]) float32. ``nearest=True`` picks the nearest
    ERP pixel instead of bilinear weights (for depth maps, so no range is
    invented across depth edges).
    """
    img, squeeze = _as_hwc(erp)
    big_h, big_w = img.shape[:2]
    h = int(height) if height is not None else big_h // 2
    if h < 1:
        raise ValueError(f"Yin/Yang height must be >= 1, got {h}")
    outs = []
    for kind in ("yin", "yang"):
        idx, wts = _to_grid_maps(kind, h, 3 * h, big_h, big_w, bool(nearest))
        out = _gather(img, idx, wts).reshape(h, 3 * h, img.shape[2])
        outs.append(out[:, :, 0] if squeeze else out)
    return outs[0], outs[1]


#: Blend feather in Yin/Yang pixel pitches (see :func:`blend_weight_yin`).
FEATHER_PIXELS = 1.0


def _margin(kind: str, d: np.ndarray) -> np.ndarray:
    """Angular margin (radians, <0 outside) of directions inside a Yin/Yang domain."""
    return _lat_lon_margin(*geo.lat_lon_from_direction(geo.to_grid_frame(kind, d)))


def _lat_lon_margin(lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
    """:func:`_margin` of grid-frame latitude and longitude."""
    return np.minimum(geo.YIN_LAT_MAX - np.abs(lat), (geo.YIN_LON_MAX - np.abs(lon)) * np.cos(lat))


def blend_weight_yin(d: np.ndarray, feather: float = 0.0) -> np.ndarray:
    """Yin blend weight in [0, 1] of camera-frame directions (..., 3); Yang gets 1 - w.

    ``feather`` (radians) widens both domains for the blend: along the parts
    of the boundary where Yin's and Yang's edges coincide (lon = +-3pi/4 near
    the equator) the overlap has zero width, so without it the merge would
    switch sources between two pixels. Samples up to ``feather`` outside a
    grid read its clamped border pixel.
    """
    return _blend_of_margins(_margin("yin", d), _margin("yang", d), feather)


def _blend_of_margins(margin_yin: np.ndarray, margin_yang: np.ndarray, feather: float) -> np.ndarray:
    """:func:`blend_weight_yin` of the directions' margins inside Yin and Yang (:func:`_margin`)."""
    m_yin = np.maximum(margin_yin + feather, 0.0)
    m_yang = np.maximum(margin_yang + feather, 0.0)
    tot = m_yin + m_yang
    t = np.where(tot > 0, m_yin / np.where(tot > 0, tot, 1.0), 0.5)
    return t * t * (3.0 - 2.0 * t)


def _owned_by_yang(p: np.ndarray, q_yang: np.ndarray):
    """(...) bool: :func:`blend_weight_yin` (no feather) of camera-frame points ``p`` (..., 3) is below 0.5;
    ``q_yang`` is ``p`` in Yang's grid frame (``geometry.to_grid_frame("yang", p)``). Also returns the
    (lat, lon) of ``p`` and of ``q_yang`` that it took.

    Outside the overlap the weight is 0 or 1 without the blend formula: where only Yang's margin is
    positive it is 0 (Yang), elsewhere outside it is 1 or 0.5 (Yin). A margin is positive exactly where
    both of its terms are (cos(lat) > 0), so the cosines and the blend are taken in the overlap only.
    """
    inside = []
    lat_lon = []
    for q in (p, q_yang):
        lat, lon = geo.lat_lon_from_direction(q)
        inside.append((geo.YIN_LAT_MAX - np.abs(lat) > 0) & (geo.YIN_LON_MAX - np.abs(lon) > 0))
        lat_lon.append((lat, lon))
    yang = inside[1] & ~inside[0]
    both = np.flatnonzero(inside[0] & inside[1])
    if both.size:
        margins = [_lat_lon_margin(lat.reshape(-1)[both], lon.reshape(-1)[both]) for lat, lon in lat_lon]
        yang.reshape(-1)[both] = _blend_of_margins(margins[0], margins[1], 0.0) < 0.5
    return yang, lat_lon


def grid_pixel(p: np.ndarray, grids: tuple[str, ...], height: int, width: int) -> np.ndarray:
    """(...) flat index into one view's (G, H, W) grid layout of the nearest pixel of the grid that owns
    the direction of each camera-frame point ``p`` (..., 3): Yin where its blend weight >= 0.5, as the
    renderer's Yin-Yang merge."""
    p = np.asarray(p, dtype=np.float64)
    if tuple(grids) == ("erp",):
        col, row = geo.project_to_grid("erp", p, height, width)
        g = np.zeros(p.shape[:-1], dtype=np.int64)
        col = np.mod(np.rint(col), width)
    else:
        # the blend weight from each grid frame's lat/lon, then the owner's pixel from the same lat/lon:
        # Yang's projection is Yin's of its grid frame (geometry.project_to_grid)
        q_yang = geo.to_grid_frame("yang", p)
        yang, ((lat_yin, lon_yin), (lat_yang, lon_yang)) = _owned_by_yang(p, q_yang)
        g = yang.astype(np.int64)
        col, row = geo.grid_coords_from_lat_lon("yin", np.where(yang, lat_yang, lat_yin), np.where(yang, lon_yang, lon_yin),
                                                height, width)
        col = np.clip(np.rint(col), 0, width - 1)
    row = np.clip(np.rint(row), 0, height - 1)
    return (g * height + row.astype(np.int64)) * width + col.astype(np.int64)


#: ERP merges of up to this many pixels keep their taps cached (about 36 bytes a pixel); larger
#: ones compute them row block by row block as they gather, so their memory is set by the block.
CACHED_TAPS_PIXELS = 2048 * 1024
#: ERP pixels per row block of the taps.
TAP_BLOCK_PIXELS = 1 << 18


def _block_taps(h: int, w: int, height: int, width: int, r0: int, r1: int):
    """Merge taps of ERP rows [r0, r1) into the stacked [Yin; Yang] pixels, zero-weight taps left out.

    About 94% of ERP pixels read only one grid (4 of their 8 bilinear taps have weight 0), so each
    grid's taps are made only where its blend weight is non-zero. Returns two (pixels, idx, wts)
    pieces, flat ERP pixel indices ascending: the pixels with 4 non-zero taps (in their original order)
    and the rest (all 8); idx int32 (the stacked grids hold 2 h w < 2^31 pixels).
    """
    lat, lon = geo.erp_lat_lon(height, width)
    d = geo.direction_from_lat_lon(lat[r0:r1], lon).reshape(-1, 3)
    wy = blend_weight_yin(d, feather=FEATHER_PIXELS * 2 * geo.YIN_LAT_MAX / h).astype(np.float32)
    n = len(d)
    grids = []  # per grid: (pixels it is read at, their taps' idx and weights, where in those rows is a pixel)
    zero = []  # per grid: True where all its 4 weighted taps are 0
    for k, (kind, scale) in enumerate((("yin", wy), ("yang", 1.0 - wy))):
        some = np.flatnonzero(scale != 0)
        col, row = geo.project_to_grid(kind, d[some], h, w)
        i, t = _grid_taps(col, row, h, w)
        t *= scale[some, None]
        where = np.zeros(n, np.int64)
        where[some] = np.arange(some.size)
        none = np.ones(n, bool)
        none[some] = ~np.any(t != 0, axis=1)
        grids.append(((i + k * h * w).astype(np.int32), t, where))
        zero.append(none)
    one = zero[0] | zero[1]
    four = np.flatnonzero(one)
    from_yang = zero[0][four]
    idx4 = np.empty((four.size, 4), np.int32)
    wts4 = np.empty((four.size, 4), np.float32)
    for k, sel in enumerate((~from_yang, from_yang)):
        i, t, where = grids[k]
        rows = where[four[sel]]
        idx4[sel], wts4[sel] = i[rows], t[rows]
    eight = np.flatnonzero(~one)
    (i0, t0, w0), (i1, t1, w1) = grids
    idx8 = np.concatenate([i0[w0[eight]], i1[w1[eight]]], axis=1)
    wts8 = np.concatenate([t0[w0[eight]], t1[w1[eight]]], axis=1)
    offset = r0 * width
    return (four + offset, idx4, wts4), (eight + offset, idx8, wts8)


def _row_blocks(height: int, width: int) -> list[tuple[int, int]]:
    rows = max(1, TAP_BLOCK_PIXELS // width)
    return [(r0, min(height, r0 + rows)) for r0 in range(0, height, rows)]


@lru_cache(maxsize=4)
def _sparse_taps(h: int, w: int, height: int, width: int):
    """The taps of :func:`_block_taps` for the whole ERP, cached: the 4-tap pixels in two halves
    (for two threads), then the 8-tap ones; read-only."""
    blocks = [_block_taps(h, w, height, width, r0, r1) for r0, r1 in _row_blocks(height, width)]
    four, eight = ([np.concatenate([b[k][i] for b in blocks]) for i in range(3)] for k in (0, 1))
    half = four[0].size // 2
    out = (tuple(np.ascontiguousarray(a[:half]) for a in four), tuple(np.ascontiguousarray(a[half:]) for a in four),
           tuple(np.ascontiguousarray(a) for a in eight))
    for part in out:
        for a in part:
            a.setflags(write=False)
    return out


def yin_yang_to_erp(yin: np.ndarray, yang: np.ndarray, height: int, width: int, *, pool=None) -> np.ndarray:
    """Merge Yin and Yang images (h, w[, C]) into an ERP image (height, width[, C]) float32.

    Bilinear sampling of each grid at every ERP pixel centre, blended with
    :func:`blend_weight_yin` (weights sum to 1). To merge rendered images with
    partial coverage, pass premultiplied colour and alpha as channels and
    divide afterwards (what :func:`rasterizer.render.render` does). Taps of
    weight 0 are skipped (about 94% of ERP pixels read one grid only); with a
    ``pool`` (an executor) the pieces of the gather run in its threads. The
    taps of ERPs up to ``CACHED_TAPS_PIXELS`` are cached; larger ERPs make them
    per row block.
    """
    a, squeeze = _as_hwc(yin)
    b, _ = _as_hwc(yang)
    if a.shape != b.shape:
        raise ValueError(f"Yin and Yang images differ in shape: {a.shape} vs {b.shape}")
    h, w, c = a.shape
    both = np.concatenate([a.reshape(-1, c), b.reshape(-1, c)]).astype(np.float32, copy=False)[:, None, :]
    out = np.empty((int(height) * int(width), c), dtype=np.float32)

    def piece(taps):
        pixels, idx, wts = taps
        if pixels.size:
            out[pixels] = _gather(both, idx, wts)

    height, width = int(height), int(width)
    if height * width <= CACHED_TAPS_PIXELS:
        pieces = _sparse_taps(h, w, height, width)
        run = piece
    else:  # taps made and used block by block: nothing of the size of the ERP's taps is held
        pieces = _row_blocks(height, width)

        def run(rows):
            for taps in _block_taps(h, w, height, width, *rows):
                piece(taps)
    if pool is None:
        for item in pieces:
            run(item)
    else:
        list(pool.map(run, pieces))
    out = out.reshape(int(height), int(width), c)
    return out[:, :, 0] if squeeze else out


# ---------------------------------------------------------------------------
# ERP resizing
# ---------------------------------------------------------------------------

@lru_cache(maxsize=32)
def _axis_taps(n_in: int, n_out: int, wrap: bool):
    """Resampling taps (n_out, T) along one axis: area average when shrinking, bilinear otherwise.

    Pixel-centre convention: output pixel j covers [j, j+1) * n_in / n_out of
    the input axis. ``wrap`` makes the axis periodic (ERP longitude);
    otherwise the edge pixel is repeated.
    """
    if n_out < n_in:
        s = n_in / n_out
        t = int(np.ceil(s)) + 1
        lo = np.arange(n_out) * s
        first = np.floor(lo).astype(np.int64)
        k = first[:, None] + np.arange(t)
        left = np.maximum(k, lo[:, None])
        right = np.minimum(k + 1, lo[:, None] + s)
        wts = np.maximum(right - left, 0.0) / s
    else:
        x = (np.arange(n_out) + 0.5) * n_in / n_out - 0.5
        x0 = np.floor(x)
        f = x - x0
        k = x0.astype(np.int64)[:, None] + np.array([0, 1])
        wts = np.stack([1 - f, f], axis=1)
    k = np.mod(k, n_in) if wrap else np.clip(k, 0, n_in - 1)
    return k, wts.astype(np.float32)


def resize_erp(img: np.ndarray, height: int, width: int) -> np.ndarray:
    """Resize an ERP image (H, W[, C]) of any real dtype to (height, width[, C]) float32 (values unscaled).

    Area averaging when shrinking an axis, bilinear when enlarging it;
    longitude wraps, latitude repeats the edge row. Same size: a float32 copy.
    Works in blocks of output rows, each converted to float32 from its own input rows, so a large
    uint8 panorama (5760x2880) never exists as a full-size float copy: the extra memory is the
    output plus about 16 MB.
    """
    a, squeeze = _as_hwc(img)
    if height < 1 or width < 1:
        raise ValueError(f"target size must be positive, got {height}x{width}")
    h, w, c = a.shape
    height, width = int(height), int(width)
    if h != height:
        k_rows, w_rows = _axis_taps(h, height, False)
    else:
        k_rows, w_rows = np.arange(h)[:, None], np.ones((h, 1), np.float32)
    cols = _axis_taps(w, width, True) if w != width else None
    out = np.empty((height, width, c), np.float32)
    step = max(1, (16 << 20) // (k_rows.shape[1] * max(w, width) * c * 4))  # output rows per ~16 MB block
    for o0 in range(0, height, step):
        o1 = min(o0 + step, height)
        block = a[k_rows[o0:o1]].astype(np.float32)  # (rows, taps, W, C): only this block's input rows
        rows = block[:, 0] if h == height else np.einsum("ot,otwc->owc", w_rows[o0:o1], block)
        if cols is not None:
            rows = np.einsum("ot,hotc->hoc", cols[1], rows[:, cols[0]])
        out[o0:o1] = rows
    return out[:, :, 0] if squeeze else out
