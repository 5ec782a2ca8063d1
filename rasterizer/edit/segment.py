"""Training-free segmentation of the two references on ERP images (numpy + scikit-image + scipy).

1. :func:`superpixels`: Felzenszwalb's graph segmentation on colour plus
   normalised inverse range (depth edges cut superpixels as colour edges do);
2. :class:`RegionGraph`: adjacency of superpixels (longitude wraps at the
   seam, rows meet across each pole) weighted by boundary colour contrast,
   mean-colour difference, the relative range jump and the normal angle
   across the shared boundary (:class:`SegmentOptions` scales each term);
3. :func:`seed_superpixels`: a positive point's superpixel, plus, when that
   superpixel is a strip along an edge (the transition band Felzenszwalb
   leaves between two surfaces), the adjacent non-strip superpixel whose mean
   colour is nearest the clicked pixel's: the surface the click is on;
   :func:`select_regions`: the superpixels joined to the seeds by edges no
   heavier than ``level`` (single linkage); negative points lower the level
   until none of them is joined;
4. :func:`carry_selection`: a mask of one view carried to the other through
   the encoder's matches (left-right consistent, unoccluded matches whose two
   pixels have similar colours; then this view's left-right failures whose
   colours agree): pulled per pixel, pushed from the prompted view's pixels
   (majority of masked against unmasked), and decided by superpixels where
   no match decides; then a contrast-sensitive graph cut on this view's
   colours (:func:`.graphcut.refine_mask`) drops the isolated pixels that
   wrong matches carried;
5. :func:`auto_segments`: both views cut at ``auto_level``, each region
   linked to the region of the other view most of its consistently matched
   pixels land in (when that is at least ``link_overlap`` of them), one label
   per linked group: the same label in both views.
"""

from __future__ import annotations

import warnings
from dataclasses import asdict, dataclass, fields

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from .. import geometry as geo
from .correspondences import ErpMatches, carry
from .graphcut import refine_mask


class SelectionError(ValueError):
    """A prompt that selects nothing or contradicts itself; the message says why."""


@dataclass(frozen=True)
class SegmentOptions:
    """Superpixel and region-graph settings (all unitless unless noted).

    fz_scale, fz_sigma, fz_min_size: :func:`skimage.segmentation.felzenszwalb`
    (min_size in pixels of the working ERP). inv_range_weight: weight of the
    inverse range (divided by its 99th percentile) beside RGB in [0, 1].
    colour_tol: RGB distance, depth_tol: relative range jump |r_p - r_q| / min,
    normal_tol: 1 - cos of the normal angle, each worth one unit of edge
    weight. select_level / auto_level: largest edge weight joined by a
    prompt / by the automatic segmentation. strip_depth: mean distance in
    pixels (working ERP) from a superpixel's pixels to its border at or under
    which it is a strip along an edge, not a surface (:func:`seed_superpixels`;
    docs/design.md). min_votes: matched pixels a
    superpixel needs to take its label from the other view; photo_tol: RGB
    distance (0..sqrt 3) above which a match's two pixels are too different in
    colour to be the same point (it then counts as inconsistent; m3d_bedroom
    bench edit mIoU 0.778 without, 0.81-0.82 at 0.15-0.3); snap: the carried
    mask takes whole superpixels of this view (else consistent matches keep their
    carried value per pixel and superpixels decide only the rest); weak_pull:
    left-right failures of this view whose colours agree pull like consistent
    matches where nothing consistent decides; push_majority: a pushed pixel is
    selected when more masked than unmasked pixels land on it (else any masked
    one selects it); cut_weight (0 = off), cut_beta, cut_pull, cut_fill,
    cut_margin, cut_band: the graph cut after the carry
    (:func:`.graphcut.refine_mask`: Potts weight per neighbour pair, RGB
    distance scale of its contrast term, confidence of a pixel's label where
    its own match decided it / where a superpixel or a push did, crop margin
    around the mask and band around its edges in pixels; bench edit mIoU
    0.841 -> 0.856, docs/design.md); link_overlap:
    fraction of a region's matched pixels that must land in one region of
    the other view to link them.
    """

    fz_scale: float = 100.0
    fz_sigma: float = 0.8
    fz_min_size: int = 50
    inv_range_weight: float = 1.0
    colour_tol: float = 0.12
    depth_tol: float = 0.08
    normal_tol: float = 0.4
    select_level: float = 1.5
    auto_level: float = 0.5
    strip_depth: float = 1.25
    min_votes: int = 8
    snap: bool = False
    weak_pull: bool = True
    push_majority: bool = True
    photo_tol: float = 0.2
    cut_weight: float = 3.0
    cut_beta: float = 0.05
    cut_pull: float = 0.9
    cut_fill: float = 0.7
    cut_margin: int = 8
    cut_band: int = 4
    link_overlap: float = 0.5

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict | None) -> "SegmentOptions":
        d = dict(d or {})
        unknown = sorted(set(d) - {f.name for f in fields(cls)})
        if unknown:
            raise ValueError(f"unknown segmentation option(s) {unknown}")
        return cls(**d)


def normals_from_range(range_erp: np.ndarray) -> np.ndarray:
    """Camera-frame unit normals (H, W, 3) of an ERP range map (H, W) by central differences
    (longitude wraps at the seam; one-sided at the top and bottom rows)."""
    h, w = range_erp.shape
    p = geo.grid_directions("erp", h, w) * range_erp[..., None]
    du = np.roll(p, -1, axis=1) - np.roll(p, 1, axis=1)
    dv = np.gradient(p, axis=0)
    n = np.cross(du, dv)
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    return n.astype(np.float32)


def superpixels(colour: np.ndarray, inv_range: np.ndarray, opts: SegmentOptions) -> np.ndarray:
    """(H, W) int32 superpixel ids 0..n-1 of an ERP from colour (H, W, 3) in [0, 1] and inverse range (H, W)."""
    from skimage.segmentation import felzenszwalb  # the only scikit-image use: imported when first needed

    scale = np.float32(np.percentile(inv_range, 99) or 1.0)
    feat = np.concatenate([colour, (inv_range / scale * opts.inv_range_weight)[..., None]], -1).astype(np.float32)
    with warnings.catch_warnings():  # 4 channels on purpose: colour + inverse range
        warnings.filterwarnings("ignore", message="Got image with third dimension", category=RuntimeWarning)
        labels = felzenszwalb(feat, scale=opts.fz_scale, sigma=opts.fz_sigma, min_size=opts.fz_min_size,
                              channel_axis=-1)
    return labels.astype(np.int32)


def _neighbour_pairs(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Flat indices (p, q) of 4-neighbour pixel pairs of an ERP (H, W): across the seam and across the poles too."""
    h, w = a.shape
    idx = np.arange(h * w).reshape(h, w)
    pole = lambda row: (row, np.roll(row, w // 2))
    pairs = [(idx, np.roll(idx, -1, axis=1)), (idx[:-1], idx[1:]), pole(idx[0]), pole(idx[-1])]
    return (np.concatenate([p.ravel() for p, _ in pairs]), np.concatenate([q.ravel() for _, q in pairs]))


@dataclass(frozen=True)
class RegionGraph:
    """Superpixels of one view and their weighted adjacency.

    labels (H, W) int32; size (n,) pixels; i, j, weight (E,) edges i < j; mean_colour (n, 3) RGB in [0, 1]
    and depth (n,) mean distance of a superpixel's pixels to its border in pixels (both computed from
    ``labels`` and the colour when not given: :func:`region_graph` gives them).
    """

    labels: np.ndarray
    size: np.ndarray
    i: np.ndarray
    j: np.ndarray
    weight: np.ndarray
    mean_colour: np.ndarray | None = None
    depth: np.ndarray | None = None

    @property
    def n(self) -> int:
        return int(self.size.size)

    def components(self, level: float, nodes: np.ndarray | None = None) -> np.ndarray:
        """(n,) component id of each superpixel when edges of weight <= ``level`` (between ``nodes``, bool (n,)) join."""
        keep = self.weight <= level
        if nodes is not None:
            keep &= nodes[self.i] & nodes[self.j]
        m = coo_matrix((np.ones(int(keep.sum()), dtype=np.int8), (self.i[keep], self.j[keep])), shape=(self.n, self.n))
        return connected_components(m, directed=False)[1]


def interior_depth(labels: np.ndarray) -> np.ndarray:
    """(n,) mean distance in pixels from each superpixel's pixels to its border (a pixel with a 4-neighbour of
    another superpixel is at 0; longitude wraps at the seam). A strip k pixels wide has about (k - 2) / 4."""
    pad = 8
    lab = np.concatenate([labels[:, -pad:], labels, labels[:, :pad]], axis=1)
    inner = np.ones(lab.shape, dtype=bool)
    inner[:, 1:] &= lab[:, 1:] == lab[:, :-1]
    inner[:, :-1] &= lab[:, :-1] == lab[:, 1:]
    inner[1:] &= lab[1:] == lab[:-1]
    inner[:-1] &= lab[:-1] == lab[1:]
    dist = ndimage.distance_transform_edt(inner)[:, pad:-pad]
    n = int(labels.max()) + 1
    return (np.bincount(labels.ravel(), weights=dist.ravel(), minlength=n)
            / np.maximum(np.bincount(labels.ravel(), minlength=n), 1)).astype(np.float32)


def superpixel_means(labels: np.ndarray, colour: np.ndarray, size: np.ndarray) -> np.ndarray:
    """(n, 3) mean colour of each superpixel of ``labels`` (H, W) from ``colour`` (H, W, 3); ``size`` (n,) their
    pixel counts (an empty label's mean is 0)."""
    flat, col = labels.ravel(), colour.reshape(-1, 3)
    sums = np.stack([np.bincount(flat, weights=col[:, c], minlength=len(size)) for c in range(3)], -1)
    return sums / np.maximum(size, 1)[:, None]


def region_graph(labels: np.ndarray, colour: np.ndarray, inv_range: np.ndarray, normals: np.ndarray,
                 opts: SegmentOptions) -> RegionGraph:
    """Edge weight = boundary colour contrast / colour_tol + mean-colour difference / colour_tol
    + median-free mean relative range jump / depth_tol + mean (1 - n_p . n_q) / normal_tol, averaged over the
    boundary's pixel pairs (see the module docstring)."""
    n = int(labels.max()) + 1
    flat = labels.ravel()
    p, q = _neighbour_pairs(labels)
    differ = flat[p] != flat[q]
    p, q = p[differ], q[differ]
    a, b = np.minimum(flat[p], flat[q]), np.maximum(flat[p], flat[q])
    key, inv_key = np.unique(a.astype(np.int64) * n + b, return_inverse=True)
    col = colour.reshape(-1, 3)
    ir = inv_range.ravel()
    nrm = normals.reshape(-1, 3)
    size = np.bincount(flat, minlength=n)
    mean_col = superpixel_means(labels, colour, size)
    counts = np.bincount(inv_key, minlength=key.size)

    def mean(v):
        return np.bincount(inv_key, weights=v, minlength=key.size) / counts

    contrast = mean(np.linalg.norm(col[p] - col[q], axis=-1))
    jump = mean(np.abs(ir[p] - ir[q]) / np.maximum(np.minimum(ir[p], ir[q]), 1e-6))
    bend = mean(1.0 - np.clip((nrm[p] * nrm[q]).sum(-1), -1.0, 1.0))
    i, j = (key // n).astype(np.int64), (key % n).astype(np.int64)
    diff = np.linalg.norm(mean_col[i] - mean_col[j], axis=-1)
    weight = (contrast + diff) / opts.colour_tol + jump / opts.depth_tol + bend / opts.normal_tol
    return RegionGraph(labels, size, i, j, weight.astype(np.float32), mean_col.astype(np.float32), interior_depth(labels))


def seed_superpixels(graph: RegionGraph, colour: np.ndarray, pixels: np.ndarray, opts: SegmentOptions,
                     exclude: np.ndarray = ()) -> np.ndarray:
    """Superpixel ids seeded by flat ``pixels`` (k,) of this view (colour (H, W, 3) in [0, 1]).

    Each pixel seeds its superpixel; when that superpixel is a strip (:attr:`RegionGraph.depth` at most
    ``opts.strip_depth``: the band of mixed colour and range Felzenszwalb leaves along an edge, whose
    edges to both sides weigh about half the edge between the sides, i.e. near the level), the adjacent
    superpixel that is not a strip and whose mean colour is nearest the pixel's own seeds too, unless it
    is in ``exclude`` (the negative points' ids). Without it a click on a strip selects the strip alone or
    a whole surface depending on where the strip's border fell.
    """
    pixels = np.asarray(pixels, dtype=np.int64).ravel()
    lab = graph.labels.ravel()
    ids = lab[pixels]
    mean_col = superpixel_means(graph.labels, colour, graph.size) if graph.mean_colour is None else graph.mean_colour
    depth = interior_depth(graph.labels) if graph.depth is None else graph.depth
    strip = depth <= opts.strip_depth
    # candidate (seed k, neighbour) pairs: edges touching a strip seed whose other end is no strip
    k_i, e_i = np.nonzero(ids[:, None] == graph.i[None, :])
    k_j, e_j = np.nonzero(ids[:, None] == graph.j[None, :])
    k = np.concatenate([k_i, k_j])
    nb = np.concatenate([graph.j[e_i], graph.i[e_j]])
    ok = strip[ids[k]] & ~strip[nb]
    k, nb = k[ok], nb[ok]
    if k.size == 0:
        return np.unique(ids)
    dist = np.linalg.norm(mean_col[nb] - colour.reshape(-1, 3)[pixels[k]], axis=-1)
    order = np.lexsort((dist, k))  # per seed, nearest first
    nearest = nb[order][np.r_[True, k[order][1:] != k[order][:-1]]]
    nearest = nearest[~np.isin(nearest, np.asarray(exclude, dtype=np.int64))]
    return np.unique(np.concatenate([ids, nearest]))


def select_regions(graph: RegionGraph, positive: np.ndarray, negative: np.ndarray, level: float) -> tuple[np.ndarray, float]:
    """(n,) bool of the superpixels joined to ``positive`` ids at ``level``, lowered (bisection over the
    edge weights) until no ``negative`` id is joined; returns (selection, level used)."""
    positive, negative = np.unique(positive), np.unique(negative)
    if np.intersect1d(positive, negative).size:
        raise SelectionError("a positive and a negative point fall in the same superpixel; move one of them")

    def joined(lv: float) -> tuple[np.ndarray, bool]:
        comp = graph.components(lv)
        sel = np.isin(comp, comp[positive])
        return sel, bool(negative.size and sel[negative].any())

    sel, clash = joined(level)
    if not clash:
        return sel, float(level)
    cand = np.unique(graph.weight[graph.weight < level])
    lo, hi = -1, cand.size - 1  # joined(cand[hi]) may clash; below cand[0] nothing joins
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if joined(float(cand[mid]))[1]:
            hi = mid - 1
        else:
            lo = mid
    used = float(cand[lo]) if lo >= 0 else 0.0
    return (joined(used)[0] if lo >= 0 else np.isin(np.arange(graph.n), positive)), used


def carry_selection(mask_src: np.ndarray, match: ErpMatches, graph: RegionGraph, level: float,
                    opts: SegmentOptions, match_src: ErpMatches | None = None,
                    colour: np.ndarray | None = None) -> np.ndarray:
    """(H, W) bool mask of this view from the other view's mask (H, W) bool (module docstring, step 4).

    ``match`` maps this view's pixels into the other view (pulled: a consistent match takes the
    mask value it lands on); ``match_src`` (optional) maps the other view's pixels into this one
    (pushed: where this view's own match is not consistent, the other view's consistent pixels that land
    on a pixel vote on it, masked against unmasked: that keeps thin or small objects whose range this
    view estimated worse). ``graph`` is this view's. With ``opts.weak_pull``, this view's
    :attr:`~.correspondences.ErpMatches.weak` matches (left-right failures whose colours agree: the
    other view's range is off there) vote for their superpixel and decide their own pixel before the
    superpixel and the pushes do; pixels left (occluded, colour mismatch, no match) take the decision of
    their superpixel: the majority of its matched pixels, or, when it has fewer than ``opts.min_votes``,
    the selection grown to it from decided superpixels at ``level``. With ``colour`` (H, W, 3) in [0, 1],
    this view's image, and ``opts.cut_weight`` > 0, the mask then goes through
    :func:`.graphcut.refine_mask` (pixels decided by their own pull are the confident ones).
    """
    values, valid = carry(mask_src.astype(np.float32), match)
    inside = values >= 0.5
    weak = match.weak & ~valid if opts.weak_pull else np.zeros_like(valid)
    lab = graph.labels.ravel()
    voter = (valid | weak).ravel()
    votes = np.bincount(lab[voter], minlength=graph.n)
    ins = np.bincount(lab[voter], weights=inside.ravel()[voter], minlength=graph.n)
    known = votes >= opts.min_votes
    sel = known & (ins >= 0.5 * np.maximum(votes, 1))
    if sel.any():
        comp = graph.components(level, nodes=sel | ~known)  # grow only into superpixels the other view did not see
        sel |= ~known & np.isin(comp, comp[sel])
    region = sel[graph.labels]
    if match_src is not None:
        h, w = region.shape
        src = match_src.valid
        land = (np.clip(np.rint(match_src.row[src]).astype(np.int64), 0, h - 1) * w
                + np.mod(np.rint(match_src.col[src]).astype(np.int64), w))
        pushed_in = np.bincount(land[mask_src[src]], minlength=h * w).reshape(h, w)
        if opts.push_majority:
            pushed_out = np.bincount(land[~mask_src[src]], minlength=h * w).reshape(h, w)
            region = np.where(pushed_in + pushed_out > 0, pushed_in > pushed_out, region)
        else:
            region = region | (pushed_in > 0)
    pulled = (valid | weak) & (not opts.snap)
    out = np.where(pulled, inside, region)  # a consistent (or weak) pull is trusted
    if colour is None:
        return out
    return refine_mask(out, pulled, colour, weight=opts.cut_weight, beta=opts.cut_beta, pull=opts.cut_pull,
                       fill=opts.cut_fill, margin=opts.cut_margin, band=opts.cut_band)


def auto_segments(graphs: tuple[RegionGraph, RegionGraph], matches: tuple[ErpMatches, ErpMatches],
                  opts: SegmentOptions) -> tuple[np.ndarray, np.ndarray]:
    """Per-view label maps (2, H, W) int32 and per-label pixel counts, labels shared across views.

    ``matches[v]`` maps view v's pixels into the other view. Labels are numbered by
    decreasing total size (0 = largest).
    """
    regions = [g.components(opts.auto_level)[g.labels] for g in graphs]  # (H, W) region id per view
    counts = [int(r.max()) + 1 for r in regions]
    offset = np.array([0, counts[0]])
    src, dst = [], []
    for v in range(2):
        other, _ = carry(regions[1 - v], matches[v])
        ok = matches[v].valid
        src.append(regions[v][ok] + offset[v])
        dst.append(other[ok] + offset[1 - v])
    total = counts[0] + counts[1]
    s, d = np.concatenate(src), np.concatenate(dst)
    pair, pair_n = np.unique(s.astype(np.int64) * total + d, return_counts=True)  # directed: region -> region
    votes = np.bincount(s, minlength=total)  # matched pixels per region
    ps, pd = pair // total, pair % total
    # each region links to the region of the other view most of its matched pixels land in (at most one
    # partner per region: a region can gather several, but never chains through a second-best overlap)
    best = np.zeros(total, dtype=np.int64)
    np.maximum.at(best, ps, pair_n)
    link = (pair_n == best[ps]) & (pair_n >= opts.link_overlap * votes[ps]) & (votes[ps] >= opts.min_votes)
    m = coo_matrix((np.ones(int(link.sum()), dtype=np.int8), (ps[link], pd[link])), shape=(total, total))
    group = connected_components(m, directed=False)[1]
    per_view = [group[regions[v] + offset[v]] for v in range(2)]
    size = np.bincount(np.concatenate([p.ravel() for p in per_view]), minlength=int(group.max()) + 1)
    order = np.argsort(-size, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    labels = np.stack([rank[p] for p in per_view]).astype(np.int32)
    return labels, size[order]
