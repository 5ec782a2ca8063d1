"""Front-to-back rendering with early termination, depth chunk after depth chunk.

The Gaussians a camera sees are taken in depth order (the pose's ranks) in
chunks of about :data:`CHUNK_LAYERS` image-sizes of footprint pixels. Each
chunk's contributions are built (:func:`rasterizer.splat.job_keys`), sorted by
(pixel, depth) and composited with every pixel's transmittance carried over
from the chunks before (:func:`rasterizer.composite.composite_segments` with
``log_t``). A pixel whose transmittance has fallen below ``T_MIN`` (1e-4, the
compositing rule's stop) takes no further contribution, so it drops out:

* a Gaussian whose footprint box holds no live pixel is skipped before any of
  its contributions exist (a summed-area table of the live-pixel mask answers
  "any live pixel in this box" in four lookups per box, wrapped columns in two
  pieces);
* the contributions of the Gaussians that remain are dropped at dead pixels
  before the sort when a sample shows that many are there
  (:data:`rasterizer.splat.keys.MASK_MIN_DROP`); otherwise they are sorted and
  composited with weight 0 (a dead pixel takes no contribution), which costs
  less than the filter.

Nothing a pixel would have composited is dropped, so the result is that of
the single global sort up to float rounding of the carried log transmittance.
Peak memory is set by the image size and the chunk (about CHUNK_LAYERS x H x W
contributions, or one Gaussian's box when that is larger; a box is at most one
image), not by the total number of contributions.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import numpy as np

from . import splat
from .composite import T_MIN, composite_segments, segment_starts

#: Footprint pixels (box areas) per depth chunk, in image sizes: smaller chunks let dead
#: pixels cull sooner, each chunk costs fixed numpy calls per size class and one summed-area
#: table. On m3d renders (about 120 layers of boxes, 60 composited per pixel) 8 ran fastest
#: (CPU seconds of a 768 x 256 Yin grid on a loaded 2-core box: 1.56 / 1.18 / 1.12 / 1.25 / 1.23 for 1 / 4 / 8 / 16 / 32).
CHUNK_LAYERS = 8.0
#: Smallest and largest chunk (box pixels): tiny images are not cut into tiny chunks, and a
#: chunk's keys (8 bytes each) and dense blocks stay within about a hundred MB at any size.
MIN_CHUNK = 1 << 15
MAX_CHUNK = 1 << 23
#: Below this many visible Gaussians a second thread costs more than it saves.
MIN_THREAD_GAUSSIANS = 20_000


def chunk_budget(h: int, w: int) -> float:
    """Box pixels per depth chunk of an H x W image (see :data:`CHUNK_LAYERS`)."""
    return float(min(max(MIN_CHUNK, CHUNK_LAYERS * h * w), MAX_CHUNK))


def _pieces(x0, kx, period, start, w):
    """Column ranges (a0, a1, b0, b1), inclusive, clipped to [0, w): a box's columns after wrapping.

    Non-periodic columns (``period`` None) are one piece; wrapping ones are the
    piece up to the end of the period and the piece that wraps to its start.
    An empty piece has end = start - 1.
    """
    if period is None:
        lo, hi = x0, x0 + kx - 1
        b0, b1 = np.zeros_like(x0), np.full_like(x0, -1)
    else:
        lo = np.mod(x0 - start, period) + start
        end = lo + kx - 1
        hi = np.minimum(end, start + period - 1)
        b0, b1 = np.full_like(x0, start), end - period
    out = []
    for c0, c1 in ((lo, hi), (b0, b1)):
        c1 = np.clip(c1, -1, w - 1)
        c0 = np.minimum(np.clip(c0, 0, w), c1 + 1)
        out += [c0, c1]
    return out


def _any_alive(sat: np.ndarray, top, bottom, a0, a1, b0, b1) -> np.ndarray:
    """(n,) bool: some live pixel in a box, from the flat summed-area table ``sat`` ((H+1) (W+1),).

    ``top``, ``bottom``: flat offsets of the box's first row and of the row after its last in
    ``sat``; columns a0 .. a1 - 1 and b0 .. b1 - 1 (a1, b1 exclusive). Flat 1-D takes: a 2-D
    fancy index of the table costs several times more.
    """
    count = np.take(sat, bottom + a1) - np.take(sat, top + a1) - np.take(sat, bottom + a0) + np.take(sat, top + a0)
    count += np.take(sat, bottom + b1) - np.take(sat, top + b1) - np.take(sat, bottom + b0) + np.take(sat, top + b0)
    return count > 0


def _summed_area(alive: np.ndarray, h: int, w: int) -> np.ndarray:
    """Flat ((H+1) (W+1),) int32 summed-area table of the (H*W,) bool mask (row 0 and column 0 zero)."""
    sat = np.zeros((h + 1, w + 1), dtype=np.int32)
    np.cumsum(alive.reshape(h, w), axis=0, dtype=np.int32, out=sat[1:, 1:])
    np.cumsum(sat[1:, 1:], axis=1, out=sat[1:, 1:])
    return sat.reshape(-1)


def _by_rank(rank: np.ndarray, n_all: int) -> np.ndarray:
    """Positions of ``rank`` (distinct integers in [0, n_all)) in increasing rank: an argsort by one
    scatter into n_all slots (linear time)."""
    slot = np.full(n_all, -1, dtype=np.int64)
    slot[rank] = np.arange(rank.size)
    return slot[slot >= 0]


def premultiplied(pose: splat.SharedPose, camera, qcut_all: np.ndarray | None, table,
                  threads: int = 1, columns=None, cut_sigma: float | None = None):
    """(colour*alpha (H, W, 3), alpha (H, W), range*alpha (H, W)) float32 of one camera, front to back.

    ``pose``: the :class:`~rasterizer.splat.SharedPose` of the camera's pose; ``qcut_all`` (N,)
    :func:`~rasterizer.splat.opacity_cuts` or None; ``table`` (N, 8) float32
    :func:`~rasterizer.composite.gaussian_table` rows in depth-rank order (row k = the Gaussian of
    rank k), or a function ``table(index, rank, n)`` of the (n,) indices of the Gaussians the
    camera keeps and their ranks among themselves that returns the (n, 8) table of those ranks
    (:func:`~rasterizer.composite.ranked_table`; no sort of all N Gaussians). alpha is clipped to
    [0, 1]. ``threads`` > 1 splits the rows into that many bands of about equal footprint area,
    composited side by side (numpy releases the GIL in its loops); the bands touch disjoint
    pixels, so the result is the same up to float rounding. ``columns``: the camera's
    :func:`~rasterizer.splat.projection.project_columns` when the caller has them. ``cut_sigma``: footprints
    are cut short there too (:func:`~rasterizer.splat.key_job`).
    """
    h, w = camera.height, camera.width
    npix = h * w
    sums = np.zeros((npix, 5), dtype=np.float32)
    job = splat.key_job(pose, camera, qcut_all, columns, own_ranks=callable(table), cut_sigma=cut_sigma)
    if job is not None:
        if callable(table):
            table = table(job.cols.index, job.rank, job.n_all)
        bands = _row_bands(job, h, threads)
        if len(bands) == 1:
            _composite_chunks(job, table, sums, h, w)
        else:
            with ThreadPoolExecutor(max_workers=len(bands)) as pool:
                done = [pool.submit(_composite_chunks, _band(job, r0, r1), table, sums, h, w) for r0, r1 in bands]
                for f in done:
                    f.result()
    alpha = np.clip(sums[:, 0], 0.0, 1.0)
    return (np.ascontiguousarray(sums[:, 1:4]).reshape(h, w, 3), alpha.reshape(h, w),
            np.ascontiguousarray(sums[:, 4]).reshape(h, w))


def _row_bands(job, h: int, threads: int) -> list[tuple[int, int]]:
    """Row ranges [r0, r1) splitting the footprints' box area into ``threads`` about equal parts."""
    if threads <= 1 or h < 2 * threads:
        return [(0, h)]
    x0, kx, y0, ky = (b[job.live] for b in job.box)
    if job.polar.size:
        sx0, skx, sy0, sky = job.sphere_box
        kx, y0, ky = np.concatenate([kx, skx]), np.concatenate([y0, sy0]), np.concatenate([ky, sky])
    if kx.size < MIN_THREAD_GAUSSIANS:
        return [(0, h)]
    per_row = np.bincount(y0, weights=kx, minlength=h + 1) - np.bincount(y0 + ky, weights=kx, minlength=h + 1)
    cum = np.cumsum(np.cumsum(per_row)[:h])
    cuts = np.searchsorted(cum, cum[-1] * np.arange(1, threads) / threads) + 1
    edges = np.unique(np.clip(np.concatenate([[0], cuts, [h]]), 0, h))
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


def _band(job, r0: int, r1: int):
    """``job`` with every box clipped to rows [r0, r1) (boxes outside the band are dropped)."""
    x0, kx, y0, ky = job.box
    b0 = np.maximum(y0, r0)
    kb = np.minimum(y0 + ky, r1) - b0
    live = job.live[kb[job.live] > 0]
    sphere_box, polar = job.sphere_box, job.polar
    if polar.size:
        sx0, skx, sy0, sky = sphere_box
        s0 = np.maximum(sy0, r0)
        sk = np.minimum(sy0 + sky, r1) - s0
        sphere_box = (sx0, skx, s0, sk)
    return replace(job, live=live, box=(x0, kx, b0, kb), sphere_box=sphere_box)


def _composite_chunks(job, table: np.ndarray, sums: np.ndarray, h: int, w: int) -> None:
    """Composite ``job``'s footprints into ``sums`` (H*W, 5) [alpha, r, g, b, range], chunk by chunk."""
    camera, layout = job.camera, job.layout
    x0, kx, y0, ky = (b[job.live] for b in job.box)
    nflat = job.live.size
    pieces = _pieces(x0, kx, camera.column_period, camera.period_start, w)
    rows0, rows1 = y0, y0 + ky - 1
    rank = job.rank[job.live]
    area = kx.astype(np.float64) * ky
    if job.polar.size:
        sx0, skx, sy0, sky = job.sphere_box
        pieces = [np.concatenate([a, b]) for a, b in zip(pieces, _pieces(sx0, skx, w, 0, w))]
        rows0, rows1 = np.concatenate([rows0, sy0]), np.concatenate([rows1, sy0 + sky - 1])
        rank = np.concatenate([rank, job.rank[job.polar]])
        area = np.concatenate([area, skx.astype(np.float64) * sky])
    order = _by_rank(rank, job.n_all)  # front to back
    order = order[area[order] > 0]  # a band's clipped boxes may be empty
    if order.size == 0:
        return
    budget = chunk_budget(h, w)
    cum = np.cumsum(area[order])
    chunk = (cum - area[order]) // budget  # a chunk starts where the one before filled its budget
    cuts = np.concatenate([[0], np.flatnonzero(np.diff(chunk)) + 1, [order.size]])

    top, bottom = rows0 * (w + 1), (rows1 + 1) * (w + 1)  # flat row offsets in the summed-area table
    a0, a1, b0, b1 = pieces[0], pieces[1] + 1, pieces[2], pieces[3] + 1
    log_t = np.zeros(h * w)
    log_tmin = np.log(T_MIN)
    alive = sat = None  # None: every pixel is alive

    def fetch(a, b):
        return layout.ranks(key[a:b]), layout.weights(key[a:b])

    for c0, c1 in zip(cuts[:-1], cuts[1:]):
        sel = order[c0:c1]
        if sat is not None:
            sel = sel[_any_alive(sat, top[sel], bottom[sel], a0[sel], a1[sel], b0[sel], b1[sel])]
            if sel.size == 0:
                continue
        flat = sel < nflat
        key, _ = splat.job_keys(job, job.live[sel[flat]], sel[~flat] - nflat, pixel_mask=alive)
        if key is None:
            continue
        pix = layout.pixels(key)
        starts = segment_starts(pix)
        pixels = pix[starts].astype(np.int64)
        lt = log_t[pixels]
        seg, _ = composite_segments(key.size, starts, fetch, table, log_t=lt)
        seg += np.take(sums, pixels, axis=0)  # a take, an add and a store: faster than sums[pixels] += seg
        sums[pixels] = seg
        log_t[pixels] = lt
        dead = pixels[lt < log_tmin]
        if dead.size:
            if alive is None:
                alive = np.ones(h * w, dtype=bool)
            alive[dead] = False
            if not alive.any():
                return
            sat = _summed_area(alive, h, w)
