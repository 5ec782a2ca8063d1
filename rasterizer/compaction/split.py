"""Detail at the upload's pitch: textured pixels become 2x2 surfels where the upload is finer than the grid.

The encoder samples each panorama at its grid's pitch (a 512x1024 model: about 2.8 px per degree), while
360 cameras deliver 2-6K panoramas. The geometry stays at the grid's pitch; the appearance comes from the
upload as an ERP at twice it (:func:`fine_erp`). A surfel kept as it is (not merged, not in the rig cap)
splits into four where the upload carries texture at its place: the smooth merge's texture test one level
finer (:func:`~rasterizer.compaction.merge.block_texture_contrast` on the 2x2 blocks of the fine ERP, whose
blocks have the grid's pitch: more than :data:`~rasterizer.compaction.merge.TEXTURE_TOL` x the image's
contrast beyond the bilinear prediction from the block means, which is what unsplit surfels draw), read at
the block its ray falls in. The four children

- lie where the rays of the four fine pixels of the surfel's grid pixel meet the surfel's plane (through its
  mean, normal to its thinnest axis); a ray that meets it more than :data:`MAX_CHILD_SIGMAS` standard
  deviations from the mean (grazing incidence) takes the surfel's range instead;
- have half its scales, its rotation and view-dependent band, and opacity 1 - sqrt(1 - its opacity): two
  children on one point composite to its alpha. At the upload's pitch the children overlap as the surfels
  do at the grid's, where its own opacity would be right; a render at the grid's pitch spreads each child
  over about its parent's footprint (the renderer's low-pass), where four would compound it. The middle
  way measured best at both widths (docs/design.md, "Detail at the upload's pitch");
- take its colour plus the difference of the fine ERP at the child's ray from the mean of the four, clipped to
  [0, 1], so the colour fit's and the view-colour fit's work is kept and only the finer detail is added.

Each view splits by its own upload: where one upload is finer than the grid and the other is not, only the
finer one's view splits. Children replace their parent in place: the output stays in layout order and each child
keeps its parent's layout position (selections find them through it). A count cap (``max_count`` / ``max_bytes``)
is never exceeded: the most textured pixels (texture / contrast) split first, as far as it allows.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from .. import geometry as geo
from ..camera import sample_erp
from ..gaussians import Gaussians, quat_to_rotmat, rgb_to_sh_dc, sh_dc_to_rgb
from ..threads import map_threads
from ..yin_yang import resize_erp
from .merge import TEXTURE_TOL, block_texture_contrast
from .result import CompactionResult

#: An upload splits pixels when its ERP is at least this many times as wide as the grid's ERP. Measured
#: on m3d_bedroom (docs/design.md, "Detail at the upload's pitch"): at the grid's own width the children
#: carry only interpolation and every view lost 0.14-0.27 dB; at 1.5x (an enlarged copy, the worst case)
#: 3% of the pixels split and the views moved by -0.01 to +0.09 dB.
MIN_UPLOAD_RATIO = 1.5
#: A child further than this many standard deviations from its parent's mean (along the parent's own
#: axes) falls back to the parent's range along its ray.
MAX_CHILD_SIGMAS = 2.0


def grid_erp_width(grids: tuple[str, ...], height: int, width: int) -> int:
    """Width of the ERP whose pitch the (height, width) grids sample: 4 x height for Yin-Yang, width for ERP."""
    return int(width) if tuple(grids) == ("erp",) else 4 * int(height)


def fine_erp(erp: np.ndarray, grids: tuple[str, ...], height: int, width: int) -> np.ndarray | None:
    """(E, 2 E, 3) float32 in [0, 1], E = :func:`grid_erp_width`: the upload as an ERP at twice the grids'
    pitch, or None when it is narrower than :data:`MIN_UPLOAD_RATIO` x the grids' ERP (no finer detail).

    erp: (H, 2H, 3) uint8 or float in [0, 1]; a wider upload is area-averaged, a narrower one enlarged.
    """
    arr = np.asarray(erp)
    base = grid_erp_width(grids, height, width)
    if arr.ndim != 3 or arr.shape[1] < MIN_UPLOAD_RATIO * base:
        return None
    fine = resize_erp(arr, base, 2 * base)  # float32, the upload's scale
    if arr.dtype == np.uint8:
        fine *= np.float32(1.0 / 255.0)
    return fine


def _fine_directions(kinds: np.ndarray, grids: tuple[str, ...], rows: np.ndarray, cols: np.ndarray, height: int,
                     width: int) -> np.ndarray:
    """(n, 3) camera-frame rays of fine-grid pixels (rows, cols) of grids ``kinds`` (indices into ``grids``)."""
    out = np.empty((rows.size, 3))
    for gi, kind in enumerate(grids):
        at = kinds == gi
        if not at.any():
            continue
        if kind == "erp":
            lat, lon = geo.erp_lat_lon(2 * height, 2 * width)
        else:
            lat, lon = geo.yin_lat_lon(2 * height, 2 * width)
        d = geo.direction_from_lat_lon(lat[rows[at], 0], lon[0, cols[at]])
        out[at] = d @ geo.YANG_ROTATION.T if kind == "yang" else d
    return out


def _children(parents: Gaussians, view: int, grid: np.ndarray, row: np.ndarray, col: np.ndarray,
              fine: np.ndarray, c2w: np.ndarray, grids: tuple[str, ...], height: int, width: int) -> Gaussians:
    """(4 k) children of k ``parents`` at layout pixels (grid, row, col) of one ``view``, in fine-pixel order
    (top-left, top-right, bottom-left, bottom-right) per parent (module docstring); fine: that view's
    (E, 2E, 3) fine ERP; c2w: (V, 4, 4) every view's pose."""
    k = len(parents)

    def four(x: np.ndarray) -> np.ndarray:
        return np.repeat(x, 4, axis=0)

    rot = four(quat_to_rotmat(parents.quats.astype(np.float64)))  # (4k, 3, 3), columns = the parent's axes
    scales = four(np.maximum(parents.scales.astype(np.float64), 1e-30))
    normal = rot[np.arange(4 * k), :, np.argmin(scales, axis=1)]
    mean = four(parents.means.astype(np.float64))
    centre = np.broadcast_to(c2w[view, :3, 3], (4 * k, 3))
    local_ray = _fine_directions(four(grid), grids, (2 * row[:, None] + [0, 0, 1, 1]).reshape(-1),
                                 (2 * col[:, None] + [0, 1, 0, 1]).reshape(-1), height, width)
    ray = np.einsum("ij,nj->ni", c2w[view, :3, :3], local_ray)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.einsum("ni,ni->n", normal, mean - centre) / np.einsum("ni,ni->n", normal, ray)
        local = np.einsum("nji,nj->ni", rot, centre + t[:, None] * ray - mean) / scales
        near = np.isfinite(t) & (t > 0) & (np.einsum("ni,ni->n", local, local) <= MAX_CHILD_SIGMAS**2)
    t = np.where(near, t, np.linalg.norm(mean - centre, axis=1))
    e = fine.shape[0]
    c, r = geo.project_to_grid("erp", local_ray, e, 2 * e)
    colours = np.asarray(sample_erp(fine, c, r), np.float32).reshape(k, 4, 3)
    rgb = sh_dc_to_rgb(parents.sh[:, 0, :]).astype(np.float32)
    rgb = np.clip(rgb[:, None, :] + (colours - colours.mean(axis=1, keepdims=True)), 0.0, 1.0)
    sh = four(parents.sh)
    sh[:, 0, :] = rgb_to_sh_dc(rgb.reshape(-1, 3))
    return Gaussians(means=(centre + t[:, None] * ray).astype(np.float32), scales=four(parents.scales) * np.float32(0.5),
                     quats=four(parents.quats), opacities=four(child_opacity(parents.opacities)), sh=sh)


def child_opacity(opacity: np.ndarray) -> np.ndarray:
    """(n,) float32 opacity of a split surfel's children: 1 - sqrt(1 - opacity) (module docstring)."""
    return (1.0 - np.sqrt(1.0 - np.clip(opacity.astype(np.float64), 0.0, 1.0))).astype(np.float32)


def texture_ratio(fine: np.ndarray) -> np.ndarray:
    """(E / 2, E) float32: texture / contrast of each 2x2 block of one view's (E, 2E, 3) fine ERP (the
    smooth merge's :func:`~rasterizer.compaction.merge.block_texture_contrast`; 0 on a uniform image)."""
    planes = np.ascontiguousarray(np.moveaxis(fine, -1, 0)[:, None])  # (3, 1, E, 2E)
    texture, _, contrast = block_texture_contrast(planes, np.ones((1,) + fine.shape[:2], bool), 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(contrast > 0, texture / contrast, 0.0).astype(np.float32)[0]


def split_textured(result: CompactionResult, fine, *, ratios=None, exclude: np.ndarray | None = None,
                   limit: int | None = None) -> CompactionResult:
    """``result`` with its textured pixels split into 2x2 children (module docstring).

    fine: each view's :func:`fine_erp`, (E, 2E, 3) float32 in [0, 1], or None for a view whose upload holds
    nothing finer than the grid (its pixels stay whole; a (V, E, 2E, 3) array also serves); ratios: each view's
    :func:`texture_ratio` of its ``fine`` when the caller has it (None, or a None entry: computed here); exclude: (V, G, H, W)
    bool pixels never split (the rig cap, whose colours come from the other view); limit: the most Gaussians the output
    may hold (None: no cap). The shell after the pixel-aligned Gaussians (``stats["shell"]``) is kept as it
    is. ``stats`` gains ``split_textured`` ({"split": pixels, "added": children, "seconds"}) and
    ``removed["split_textured"]`` (split minus added, negative), so the removed counts still sum to input -
    output.
    """
    t0 = time.perf_counter()
    prov = result.provenance
    g = result.gaussians
    n = len(g)
    h, w = prov.height, prov.width
    e = grid_erp_width(prov.grids, h, w)
    fine = [None if f is None else np.asarray(f, dtype=np.float32) for f in fine]
    shapes = [None if f is None else f.shape for f in fine]
    if len(fine) != prov.views or any(s is not None and s != (e, 2 * e, 3) for s in shapes):
        raise ValueError(f"fine ERPs must be {prov.views} of shape {(e, 2 * e, 3)} (or None), got {shapes}")
    flat = prov.flat_index(n)
    front = n - int(result.stats.get("shell", 0))
    view, grid, row, col = prov.decode(n)
    whole = np.flatnonzero(result.block[:front] == 1)  # pixels kept as they are, aligned with result.index
    cand = whole[np.array([f is not None for f in fine])[view[whole]]]
    if exclude is not None:
        cand = cand[~np.asarray(exclude, bool).reshape(-1)[flat[cand]]]
    given = [None] * len(fine) if ratios is None else list(ratios)
    if len(given) != len(fine) or any(g is not None and (f is None or g.shape != (e // 2, e))
                                      for f, g in zip(fine, given)):
        raise ValueError(f"ratios must be {len(fine)} of shape {(e // 2, e)} beside each fine ERP (or None), got "
                         f"{[None if g is None else g.shape for g in given]}")
    ratios = map_threads(lambda f, g: g if g is not None or f is None else texture_ratio(f), fine, given)
    r = np.empty(cand.size, np.float32)
    for gi, kind in enumerate(prov.grids):  # each candidate's block: the one its pixel's ray falls in
        at = np.flatnonzero(grid[cand] == gi)
        c, rr = geo.project_to_grid("erp", geo.grid_directions(kind, h, w)[row[cand[at]], col[cand[at]]], e // 2, e)
        c = np.mod(np.rint(c).astype(np.int64), e)
        rr = np.clip(np.rint(rr).astype(np.int64), 0, e // 2 - 1)
        for v, ratio in enumerate(ratios):
            if ratio is None:
                continue
            on = view[cand[at]] == v
            r[at[on]] = ratio[rr[on], c[on]]
    textured = r > np.float32(TEXTURE_TOL)
    split, r = cand[textured], r[textured]
    room = split.size if limit is None else max(0, (int(limit) - n) // 3)  # each split adds three
    if room < split.size:  # the most textured first
        split = np.sort(split[np.argpartition(-r, room - 1)[:room]]) if room else split[:0]
    counts = np.ones(n, np.int64)
    counts[split] = 4
    out = g.subset(np.repeat(np.arange(n), counts))
    first = np.cumsum(counts) - counts

    def write_children(v: int) -> None:  # one view's parents (their children's rows are their own)
        part = split[view[split] == v]
        if part.size:
            kids = _children(g.subset(part), v, grid[part], row[part], col[part], fine[v], prov.c2w, prov.grids, h, w)
            at = (first[part][:, None] + np.arange(4)).reshape(-1)
            for name in ("means", "scales", "opacities", "sh"):
                getattr(out, name)[at] = getattr(kids, name)

    map_threads(write_children, list(range(prov.views)))  # the views side by side
    index = result.index[~np.isin(whole, split)]
    removed = {**result.stats.get("removed", {}), "split_textured": -3 * int(split.size)}
    stats = {**result.stats, "output": len(out), "removed": removed,
             "split_textured": {"split": int(split.size), "added": 4 * int(split.size),
                                "seconds": round(time.perf_counter() - t0, 4)}}
    return CompactionResult(out, replace(prov, index=np.repeat(flat, counts)), np.repeat(result.block, counts),
                            index, stats)
