"""Per-scene edit data and the work on it: selection from points, automatic segments, masks.

:class:`EditData` is what a scene keeps for editing (6 bytes per grid pixel
of matches, float16 range maps, and each Gaussian's layout position and
block size); :class:`SceneIndex` adds the per-view ERP features,
superpixels and region graphs (built once per scene, :func:`build_index`).
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field

import numpy as np

from ..yin_yang import resize_erp, yin_yang_to_erp
from . import correspondences as corr
from .ops import gaussian_values, source_pixels
from .segment import (
    RegionGraph,
    SegmentOptions,
    SelectionError,
    auto_segments,
    carry_selection,
    normals_from_range,
    region_graph,
    seed_superpixels,
    select_regions,
    superpixels,
)


@dataclass(frozen=True)
class EditData:
    """grids, height, width of the layout; matches (2, G, H, W, 5); range_maps (2, G, H, W) scene units;
    index (N,) layout position and block (N,) pixel-block side of each stored Gaussian."""

    grids: tuple[str, ...]
    height: int
    width: int
    matches: np.ndarray
    range_maps: np.ndarray
    index: np.ndarray
    block: np.ndarray

    def to_bytes(self, compress: bool = False) -> bytes:
        """npz: packed matches (:func:`correspondences.pack`), float16 ranges, int32 index, uint8 block.

        The ranges are stored in units of a power of two near their median (``range_scale``; larger when the
        farthest would overflow), so a scene in any unit keeps float16's 3 significant digits without overflowing
        (65504) or falling to subnormals; a power of two keeps the same float16 digits a metre-scale scene had.
        Not zlib-compressed by default: every scene creation pays the packing, and ``omnisplat-bench edit``
        measures both (m3d_bedroom: about twice the bytes, a tenth of the seconds).
        """
        scale = _range_scale(self.range_maps)
        buf = io.BytesIO()
        (np.savez_compressed if compress else np.savez)(buf, grids=np.array(self.grids), size=np.array([self.height, self.width]),
                            range_maps=(self.range_maps / scale).astype(np.float16), range_scale=np.float64(scale),
                            index=self.index.astype(np.int32),
                            block=self.block.astype(np.uint8),
                            **{f"matches_{k}": v for k, v in corr.pack(self.matches).items()})
        return buf.getvalue()

    @classmethod
    def from_bytes(cls, data: bytes) -> "EditData":
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            packed = {k[len("matches_"):]: z[k] for k in z.files if k.startswith("matches_")}
            h, w = (int(v) for v in z["size"])
            scale = float(z["range_scale"]) if "range_scale" in z.files else 1.0
            ranges = z["range_maps"].astype(np.float32)
            if scale != 1.0:
                ranges *= np.float32(scale)
            return cls(tuple(str(g) for g in z["grids"]), h, w, corr.unpack(packed), ranges,
                       z["index"].astype(np.int64), z["block"].astype(np.int64))

    def subset(self, keep: np.ndarray) -> "EditData":
        """The same layout for ``gaussians.subset(keep)``."""
        return EditData(self.grids, self.height, self.width, self.matches, self.range_maps,
                        self.index[keep], self.block[keep])


#: float16's largest finite value: the largest range stored in units of :func:`_range_scale`.
_MAX_SCALED_RANGE = 65504.0


def _range_scale(ranges: np.ndarray) -> float:
    """The power of two nearest the median positive finite range (1 when there is none), raised where the largest
    range would overflow float16 in its units: a sweep whose far plane lies more than 65504 medians out (near and
    far options up to 1e12 apart) keeps every range finite, its nearest ones as float16 subnormals (fewer digits)."""
    r = np.asarray(ranges, dtype=np.float32).reshape(-1)
    pos = r[np.isfinite(r) & (r > 0)]
    if pos.size == 0:
        return 1.0
    median = np.round(np.log2(float(np.median(pos))))
    largest = np.ceil(np.log2(float(pos.max()) / _MAX_SCALED_RANGE))
    return float(2.0 ** max(median, largest))


@dataclass
class SceneIndex:
    """Everything a selection needs, per view v = 0 (a), 1 (b), on (He, 2 He) ERPs."""

    data: EditData
    colour: np.ndarray  # (2, He, We, 3) float32 in [0, 1]
    graphs: tuple[RegionGraph, RegionGraph]
    matches: tuple[corr.ErpMatches, corr.ErpMatches]  # [v]: view v's pixels -> the other view, photo-checked
    gaussian_view: np.ndarray  # (N,)
    gaussian_pixel: np.ndarray  # (N,) flat ERP pixel of its view
    opts: SegmentOptions
    _segments: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)

    @property
    def erp_height(self) -> int:
        return int(self.colour.shape[1])

    def superpixel_labels(self) -> np.ndarray:
        """(2, He, We) int32: what :func:`build_index` may be given back to skip the slow step."""
        return np.stack([g.labels for g in self.graphs])

    def segments(self) -> tuple[np.ndarray, np.ndarray]:
        """Automatic segments: (2, He, We) int32 labels shared by both views, per-label pixel counts."""
        if self._segments is None:
            self._segments = auto_segments(self.graphs, self.matches, self.opts)
        return self._segments

    def set_segments(self, labels: np.ndarray, sizes: np.ndarray) -> None:
        """Reuse stored automatic segments (what :meth:`segments` returned for this scene)."""
        self._segments = (np.asarray(labels, dtype=np.int32), np.asarray(sizes, dtype=np.int64))

    def gaussian_labels(self) -> np.ndarray:
        """(N,) int32 automatic segment of each Gaussian (that of its source pixel)."""
        return gaussian_values(self.segments()[0], self.gaussian_view, self.gaussian_pixel)


def build_index(data: EditData, images, *, erp_height: int | None = None, opts: SegmentOptions | None = None,
                labels: np.ndarray | None = None) -> SceneIndex:
    """Index of a scene from its :class:`EditData` and the two reference ERPs (H, 2H, 3) uint8 or [0, 1].

    ``erp_height`` defaults to the images' height; ``labels`` (2, He, We) reuses stored superpixels.
    """
    opts = opts or SegmentOptions()
    he = int(erp_height or np.shape(images[0])[0])
    colour = []
    for img in images:
        a = np.asarray(img)
        a = a.astype(np.float32) / 255.0 if a.dtype == np.uint8 else a.astype(np.float32)
        colour.append(a if a.shape[0] == he else resize_erp(a, he, 2 * he))
    colour = np.stack(colour)
    graphs, matches = [], []
    for v in range(2):
        rm = data.range_maps[v]
        rng = rm[0] if data.grids == ("erp",) else yin_yang_to_erp(rm[0], rm[1], he, 2 * he)
        if rng.shape[0] != he:
            rng = resize_erp(rng, he, 2 * he)
        inv = 1.0 / np.maximum(rng, 1e-6)
        lab = superpixels(colour[v], inv, opts) if labels is None else np.asarray(labels[v], dtype=np.int32)
        graphs.append(region_graph(lab, colour[v], inv, normals_from_range(rng), opts))
        matches.append(corr.erp_matches(data.matches, v, data.grids, he))
    matches = [corr.photo_checked(matches[v], colour[v], colour[1 - v], opts.photo_tol) for v in range(2)]
    view, pixel = source_pixels(data.index, data.block, data.grids, data.height, data.width, he)
    return SceneIndex(data, colour, tuple(graphs), tuple(matches), view, pixel, opts)


def points_to_pixels(points, height: int) -> np.ndarray:
    """(k, 2) (u, v) in [0, 1] on an ERP (u = (c + 0.5) / W, v = (r + 0.5) / H) -> (k,) flat pixel of (height, 2 height)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if p.size and (not np.all(np.isfinite(p)) or p.min() < 0 or p.max() > 1):
        raise SelectionError("points must be (u, v) pairs with both in [0, 1]")
    width = 2 * height
    col = np.clip(np.floor(p[:, 0] * width), 0, width - 1).astype(np.int64)
    row = np.clip(np.floor(p[:, 1] * height), 0, height - 1).astype(np.int64)
    return row * width + col


@dataclass(frozen=True)
class Selection:
    """masks (2, He, We) bool per view; gaussians (N,) bool; level: the edge weight joined in the
    prompted view; consistency: IoU, on pixels with consistent matches, of the prompted view's mask and
    the other view's mask carried back to it."""

    masks: np.ndarray
    gaussians: np.ndarray
    level: float
    consistency: float | None

    def coverage(self) -> tuple[float, float]:
        """Fraction of each reference's sphere (cos-latitude weighted) in the mask."""
        he = self.masks.shape[1]
        wt = np.cos((np.arange(he) + 0.5) / he * np.pi - np.pi / 2)[:, None]
        return tuple(float((m * wt).sum() / (wt.sum() * m.shape[1])) for m in self.masks)


def _finish(index: SceneIndex, masks: np.ndarray, level: float, prompted: int | None) -> Selection:
    sel = gaussian_values(masks, index.gaussian_view, index.gaussian_pixel)
    consistency = None
    if prompted is not None:
        back, ok = corr.carry(masks[1 - prompted], index.matches[prompted])
        inter = (masks[prompted] & back & ok).sum()
        union = ((masks[prompted] | back) & ok).sum()
        consistency = float(inter / union) if union else None
    return Selection(masks, sel, level, consistency)


def select_points(index: SceneIndex, view: int, points, negative=()) -> Selection:
    """The object under ``points`` (u, v) of reference ``view`` (0 / 1) in both views; :class:`SelectionError`
    for points outside [0, 1], no points, or a prompt that selects nothing."""
    he = index.erp_height
    pos = points_to_pixels(points, he)
    neg = points_to_pixels(negative, he) if len(negative) else np.zeros(0, dtype=np.int64)
    if pos.size == 0:
        raise SelectionError("give at least one positive point")
    graph = index.graphs[view]
    lab = graph.labels.ravel()
    seeds = seed_superpixels(graph, index.colour[view], pos, index.opts, exclude=lab[neg])
    chosen, level = select_regions(graph, seeds, lab[neg], index.opts.select_level)
    masks = np.zeros((2,) + graph.labels.shape, dtype=bool)
    masks[view] = chosen[graph.labels]
    other = 1 - view
    masks[other] = carry_selection(masks[view], index.matches[other], index.graphs[other], level, index.opts,
                                   index.matches[view], colour=index.colour[other])
    return _finish(index, masks, level, view)


def select_segment(index: SceneIndex, label: int) -> Selection:
    """A whole automatic segment (both views); :class:`SelectionError` when no such label."""
    labels, sizes = index.segments()
    if not (0 <= int(label) < sizes.size):
        raise SelectionError(f"unknown segment {label}; this scene has segments 0..{sizes.size - 1}")
    return _finish(index, labels == int(label), index.opts.auto_level, None)
