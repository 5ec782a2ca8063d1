"""rasterizer.edit: packing, ERP look-ups, region graph (seam, poles), prompt selection, Gaussian edits."""

import numpy as np
import pytest

from rasterizer import geometry as geo
from rasterizer.edit import correspondences as corr
from rasterizer.edit.graphcut import min_cut
from rasterizer.edit.ops import edit_gaussians, gaussian_values, palette, source_pixels
from rasterizer.edit.scene import points_to_pixels
from rasterizer.edit.segment import (
    RegionGraph,
    SegmentOptions,
    SelectionError,
    _neighbour_pairs,
    carry_selection,
    region_graph,
    select_regions,
)
from rasterizer.gaussians import SH_C0, Gaussians


def _random_matches(h=8, w=24, seed=0):
    rng = np.random.default_rng(seed)
    m = np.zeros((2, 2, h, w, 5), np.float32)
    m[..., 0] = rng.integers(0, 2, m.shape[:-1])
    m[..., 1] = rng.uniform(-0.5, w - 0.5, m.shape[:-1])
    m[..., 2] = rng.uniform(-0.5, h - 0.5, m.shape[:-1])
    m[..., 3] = rng.uniform(0, 1, m.shape[:-1])
    m[..., 4] = rng.integers(0, 3, m.shape[:-1])
    return m


def test_pack_round_trip_and_size():
    m = _random_matches()
    packed = corr.pack(m)
    assert sum(v.nbytes for v in packed.values()) == 6 * m[..., 0].size
    back = corr.unpack(packed)
    assert np.array_equal(back[..., [0, 4]], m[..., [0, 4]])
    assert np.abs(back[..., 1:3] - m[..., 1:3]).max() <= 0.5 / 32 + 1e-6
    assert np.abs(back[..., 3] - m[..., 3]).max() <= 0.5 / 255 + 1e-6
    with pytest.raises(ValueError, match="matches must be"):
        corr.pack(m[..., :4])


@pytest.mark.parametrize("grids", [("yin", "yang"), ("erp",)])
def test_identity_matches_map_erp_pixels_to_themselves(grids):
    """Matches that point every grid pixel at its own direction in the other view read back as the identity."""
    h, w = (16, 48) if grids != ("erp",) else (16, 32)
    m = np.zeros((2, len(grids), h, w, 5), np.float32)
    for g, kind in enumerate(grids):
        col, row = np.meshgrid(np.arange(w), np.arange(h))
        m[:, g, ..., 0], m[:, g, ..., 1], m[:, g, ..., 2] = g, col, row
    he = 16
    em = corr.erp_matches(m, 0, grids, he)
    col, row = np.meshgrid(np.arange(2 * he), np.arange(he))
    dc = np.abs(np.mod(em.col - col + he, 2 * he) - he)
    assert np.percentile(dc, 90) < 1.0 and np.percentile(np.abs(em.row - row), 90) < 1.0  # nearest grid pixel
    assert em.valid.all()
    # carrying a map through the identity keeps it where the nearest pixel is the same (seam included)
    values = np.arange(he * 2 * he).reshape(he, 2 * he)
    carried, ok = corr.carry(values, em)
    assert (carried == values).mean() > 0.5 and ok.all()


def test_neighbour_pairs_cross_the_seam_and_the_poles():
    a = np.zeros((4, 8), int)
    p, q = _neighbour_pairs(a)
    pairs = set(zip(p.tolist(), q.tolist()))
    assert (7, 0) in pairs  # row 0: last column next to the first (the seam)
    assert (0, 4) in pairs  # row 0, across the north pole: column c meets c + W/2
    assert (24, 28) in pairs  # last row, across the south pole
    assert (0, 8) in pairs and (0, 1) in pairs


def _chain_graph(weights):
    n = len(weights) + 1
    return RegionGraph(np.arange(n).reshape(1, n).astype(np.int32), np.ones(n, int), np.arange(n - 1),
                       np.arange(1, n), np.asarray(weights, np.float32))


def test_select_regions_negative_lowers_the_level():
    g = _chain_graph([0.2, 0.9, 0.5, 0.3])
    sel, level = select_regions(g, np.array([0]), np.array([], int), 1.0)
    assert sel.all() and level == 1.0
    sel, level = select_regions(g, np.array([0]), np.array([3]), 1.0)
    assert sel.tolist() == [True, True, False, False, False] and level == pytest.approx(0.5)
    sel, _ = select_regions(g, np.array([0]), np.array([1]), 1.0)
    assert sel.tolist() == [True, False, False, False, False]
    with pytest.raises(SelectionError, match="same superpixel"):
        select_regions(g, np.array([2]), np.array([2]), 1.0)


def test_region_graph_depth_edge_outweighs_flat_colour():
    """Same colour everywhere; a range step between columns 3 and 4 makes that edge heavier than the others."""
    h, w = 8, 16
    labels = (np.arange(w)[None, :] // 4).repeat(h, 0).astype(np.int32)
    colour = np.full((h, w, 3), 0.5, np.float32)
    inv = np.full((h, w), 0.5, np.float32)
    inv[:, 4:8] = 1.0
    normals = np.tile(np.array([0, 0, 1], np.float32), (h, w, 1))
    g = region_graph(labels, colour, inv, normals, SegmentOptions())
    weight = {(int(i), int(j)): float(x) for i, j, x in zip(g.i, g.j, g.weight)}
    assert weight[(0, 1)] > 5 and weight[(2, 3)] < 1e-6 and (0, 3) in weight  # (0, 3): the seam


def test_carry_selection_pixelwise_and_fills_occluded_pixels_from_superpixels():
    h, w = 4, 8
    labels = np.repeat(np.array([[0, 0, 1, 1, 2, 2, 3, 3]]), h, 0).astype(np.int32)
    g = RegionGraph(labels, np.full(4, 8), np.array([0, 1, 2]), np.array([1, 2, 3]), np.array([0.1, 5.0, 0.1], np.float32))
    col, row = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    status = np.zeros((h, w), np.uint8)
    status[:, 2:4] = corr.OCCLUDED  # superpixel 1 unseen by the source: grows from superpixel 0 (edge 0.1)
    em = corr.ErpMatches(col, row, np.ones((h, w), np.float32), status)
    src = np.zeros((h, w), bool)
    src[:, 0:2] = True
    src[0, 6] = True  # one pixel of superpixel 3: kept pixel-wise, not spread to the superpixel
    out = carry_selection(src, em, g, 1.0, SegmentOptions(min_votes=1))
    assert out[:, 0:4].all() and not out[:, 4:6].any()
    assert out[0, 6] and not out[1:, 6].any()


def test_points_to_pixels_bounds():
    assert points_to_pixels([[0.0, 0.0], [1.0, 1.0]], 4).tolist() == [0, 4 * 8 - 1]
    for bad in ([[1.01, 0.5]], [[0.5, -0.1]], [[np.nan, 0.5]]):
        with pytest.raises(SelectionError, match=r"\[0, 1\]"):
            points_to_pixels(bad, 4)


def test_source_pixels_follow_the_block_centre():
    h, w, he = 8, 24, 16
    grids = ("yin", "yang")
    index = np.array([0, (1 * 2 + 1) * h * w + 3 * w + 5])  # view 0 Yin (0, 0); view 1 Yang (3, 5)
    view, pix = source_pixels(index, np.array([1, 2]), grids, h, w, he)
    assert view.tolist() == [0, 1]
    d = corr.grid_point_directions(np.array([0, 1]), np.array([0.0, 5.5]), np.array([0.0, 3.5]), h, w)
    col, row = geo.project_to_grid("erp", d, he, 2 * he)
    expect = np.floor(row + 0.5).astype(int) * 2 * he + np.mod(np.floor(col + 0.5).astype(int), 2 * he)
    assert pix.tolist() == expect.tolist()
    maps = np.zeros((2, he, 2 * he), int)
    maps[1].flat[pix[1]] = 7
    assert gaussian_values(maps, view, pix).tolist() == [0, 7]


def _gaussians(n=5):
    rng = np.random.default_rng(0)
    q = rng.normal(size=(n, 4)).astype(np.float32)
    return Gaussians(rng.normal(size=(n, 3)).astype(np.float32), np.full((n, 3), 0.1, np.float32),
                     q / np.linalg.norm(q, axis=1, keepdims=True), np.full(n, 0.5, np.float32),
                     rng.normal(size=(n, 4, 3)).astype(np.float32))


def test_edits():
    g = _gaussians()
    sel = np.array([True, False, True, False, False])
    assert len(edit_gaussians(g, sel, "remove")) == 3 and len(edit_gaussians(g, sel, "keep")) == 2
    rec = edit_gaussians(g, sel, "recolor", color=(1.0, 0.0, 0.25))
    np.testing.assert_allclose(0.5 + SH_C0 * rec.sh[sel, 0], [[1.0, 0.0, 0.25]] * 2, atol=1e-6)
    assert np.all(rec.sh[sel, 1:] == 0) and np.array_equal(rec.sh[~sel], g.sh[~sel])
    moved = edit_gaussians(g, sel, "translate", offset=(1, 2, 3))
    np.testing.assert_allclose(moved.means[sel] - g.means[sel], [[1, 2, 3]] * 2, atol=1e-6)
    assert np.array_equal(moved.means[~sel], g.means[~sel])
    with pytest.raises(ValueError, match="unknown edit op"):
        edit_gaussians(g, sel, "explode")
    with pytest.raises(ValueError, match="entries"):
        edit_gaussians(g, sel[:3], "remove")


def test_palette_is_deterministic_and_distinct():
    p = palette(200)
    assert np.array_equal(p[:50], palette(50))
    assert len({tuple(c) for c in p}) == 200


def test_auto_segments_share_labels_across_views():
    """Two views whose matches shift by 2 columns (across the seam): regions of both get the same labels."""
    from rasterizer.edit.segment import auto_segments

    h, w = 6, 16
    cols = np.arange(w)
    labels = [np.repeat(((cols + s) % w // 4)[None], h, 0).astype(np.int32) for s in (0, 2)]
    graphs = tuple(RegionGraph(lab, np.bincount(lab.ravel()), np.array([0, 1, 2]), np.array([1, 2, 3]),
                               np.full(3, 9.0, np.float32)) for lab in labels)
    col, row = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    ok = np.zeros((h, w), np.uint8)
    # view 0 pixel c sees view 1 pixel c - 2 (and back): region k of view 0 is region k of view 1
    matches = (corr.ErpMatches(np.mod(col - 2, w), row, np.ones((h, w), np.float32), ok),
               corr.ErpMatches(np.mod(col + 2, w), row, np.ones((h, w), np.float32), ok))
    out, sizes = auto_segments(graphs, matches, SegmentOptions(min_votes=1))
    assert sizes.size == 4 and sizes.sum() == 2 * h * w
    for k in range(4):  # the same physical columns carry the same label in both views
        assert np.all(out[0][:, (4 * k - 2) % w] == out[1][:, (4 * k - 4) % w])
    assert len(np.unique(out[0])) == 4


def test_photo_check_marks_matches_that_change_colour_and_keeps_weak_ones():
    h, w = 2, 4
    col, row = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    status = np.zeros((h, w), np.uint8)
    status[1, 3] = corr.OCCLUDED
    status[1, 0] = status[1, 1] = corr.INCONSISTENT  # left-right failures
    em = corr.ErpMatches(col, row, np.ones((h, w), np.float32), status)
    here = np.zeros((h, w, 3), np.float32)
    there = here.copy()
    there[0, 1] = 0.5  # RGB distance 0.87 > 0.2: not the same point
    there[0, 2] = 0.1  # 0.17 <= 0.2: kept
    there[1, 3] = 1.0  # already occluded: stays occluded
    there[1, 1] = 1.0  # a left-right failure that changes colour too
    out = corr.photo_checked(em, here, there, 0.2)
    expect = np.zeros((h, w), np.uint8)
    expect[0, 1], expect[1, 3], expect[1, 0], expect[1, 1] = corr.PHOTO, corr.OCCLUDED, corr.INCONSISTENT, corr.PHOTO
    assert np.array_equal(out.status, expect)
    assert out.valid.sum() == 4 and out.weak.sum() == 1 and out.weak[1, 0]
    assert out.col is em.col and np.array_equal(em.status, status)  # the input is not modified


def test_push_fills_only_pixels_without_a_consistent_pull():
    h, w = 4, 8
    labels = np.repeat(np.array([[0, 0, 1, 1, 2, 2, 3, 3]]), h, 0).astype(np.int32)
    g = RegionGraph(labels, np.full(4, 8), np.array([0, 1, 2]), np.array([1, 2, 3]), np.full(3, 9.0, np.float32))
    col, row = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    ok = np.zeros((h, w), np.uint8)
    here_status = ok.copy()
    here_status[0, 5] = corr.PHOTO  # not a weak match: it does not pull
    here = corr.ErpMatches(col, row, np.ones((h, w), np.float32), here_status)  # identity pull
    # the source's pixels (0, 0) and (0, 1) push onto (0, 5) and (0, 6) of this view
    push_col = col.copy()
    push_col[0, 0], push_col[0, 1] = 5, 6
    there_status = ok.copy()
    there_status[0, 5] = there_status[0, 6] = corr.OCCLUDED  # so no unmasked pixel lands there too
    there = corr.ErpMatches(push_col, row, np.ones((h, w), np.float32), there_status)
    src = np.zeros((h, w), bool)
    src[0, 0] = src[0, 1] = True
    out = carry_selection(src, here, g, 1.0, SegmentOptions(min_votes=1), match_src=there)
    assert out[0, 5]  # its own match failed: the push decides
    assert not out[0, 6]  # a consistent pull (to an unselected pixel) wins over the push
    assert out[0, 0] and out[0, 1]  # pulled


def _strip_graph(h=4, w=8):
    """Four 2-column superpixels, edges too heavy to join anything (each decides on its own votes)."""
    labels = np.repeat(np.array([[0, 0, 1, 1, 2, 2, 3, 3]]), h, 0).astype(np.int32)
    return RegionGraph(labels, np.full(4, 2 * h), np.array([0, 1, 2]), np.array([1, 2, 3]), np.full(3, 9.0, np.float32))


def test_weak_match_pulls_where_nothing_consistent_decides():
    """A left-right failure whose colours agree (weak) decides its own pixel and votes for its superpixel."""
    h, w = 4, 8
    g = _strip_graph(h, w)
    col, row = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    status = np.full((h, w), corr.OCCLUDED, np.uint8)
    status[:, 0:2] = corr.OK  # superpixel 0: consistent, lands on unmasked pixels
    status[:, 2:4] = corr.INCONSISTENT  # superpixel 1: weak only, half of it lands on masked pixels
    status[0, 4] = corr.INCONSISTENT  # superpixel 2: one weak pixel on a masked pixel, the rest unseen
    em = corr.ErpMatches(col, row, np.ones((h, w), np.float32), status)
    src = np.zeros((h, w), bool)
    src[:, 2] = True
    src[0, 4] = True
    on = carry_selection(src, em, g, 1.0, SegmentOptions(min_votes=2, weak_pull=True))
    off = carry_selection(src, em, g, 1.0, SegmentOptions(min_votes=2, weak_pull=False))
    assert on[:, 2].all() and not on[:, 3].any() and not on[:, 0:2].any()  # weak pulls kept per pixel
    assert on[0, 4] and not on[1:, 4:6].any()  # one weak vote: below min_votes, superpixel 2 stays out
    assert not off.any()  # without weak pulls nothing consistent selects anything


def test_push_majority_needs_more_masked_than_unmasked_pushes():
    h, w = 4, 8
    g = _strip_graph(h, w)
    col, row = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    here = corr.ErpMatches(col, row, np.ones((h, w), np.float32), np.full((h, w), corr.OCCLUDED, np.uint8))
    # the source's row-0 pixels 0..2 land on (0, 6), its pixels 3..4 on (0, 7): masked are 0, 1 and 3
    push_col = col.copy()
    push_col[0, 0:3], push_col[0, 3:5] = 6, 7
    push_row = row.copy()
    push_row[0, 0:5] = 0
    ok = np.full((h, w), corr.OCCLUDED, np.uint8)
    ok[0, 0:5] = corr.OK
    there = corr.ErpMatches(push_col, push_row, np.ones((h, w), np.float32), ok)
    src = np.zeros((h, w), bool)
    src[0, [0, 1, 3]] = True
    major = carry_selection(src, here, g, 1.0, SegmentOptions(min_votes=1, push_majority=True), match_src=there)
    anyone = carry_selection(src, here, g, 1.0, SegmentOptions(min_votes=1, push_majority=False), match_src=there)
    assert major[0, 6] and not major[0, 7]  # 2 masked vs 1 unmasked; 1 vs 1 is no majority
    assert anyone[0, 6] and anyone[0, 7]
    assert major.sum() == 1 and anyone.sum() == 2  # nothing else is decided


def test_min_cut_on_a_chain():
    # source - 0 - 1 - 2 - sink; the weak link 1-2 is cut
    side = min_cut(np.array([5.0, 0, 0]), np.array([0, 0, 5.0]), np.array([0, 1]), np.array([1, 2]), np.array([3.0, 0.5]))
    assert side.tolist() == [True, True, False]


@pytest.mark.parametrize("shift", [0, 14])  # 14: the square straddles the seam
def test_graph_cut_drops_isolated_carried_pixels_but_keeps_colour_edges(shift):
    """Identity matches carry a square with a hole and a stray pixel on a flat background: the cut fills
    the hole and drops the stray pixel, but keeps a lone pixel that differs in colour from its neighbours."""
    h, w = 16, 32
    colour = np.full((h, w, 3), 0.5, np.float32)
    colour[4:12, 8:20] = (1.0, 0.0, 0.0)
    colour[2, 28] = (0.0, 0.0, 1.0)
    src = np.zeros((h, w), bool)
    src[4:12, 8:20] = True
    src[7, 12] = False  # a hole inside the square
    src[13, 3] = True  # a stray pixel on the flat background
    src[2, 28] = True  # a lone pixel with its own colour
    colour, src = np.roll(colour, shift, 1), np.roll(src, shift, 1)
    col, row = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    em = corr.ErpMatches(col, row, np.ones((h, w), np.float32), np.zeros((h, w), np.uint8))
    g = RegionGraph(np.zeros((h, w), np.int32), np.array([h * w]), np.zeros(0, int), np.zeros(0, int), np.zeros(0, np.float32))
    on = carry_selection(src, em, g, 1.0, SegmentOptions(), colour=colour)
    off = carry_selection(src, em, g, 1.0, SegmentOptions(cut_weight=0.0), colour=colour)
    want = np.zeros((h, w), bool)
    want[4:12, 8:20] = True
    want[2, 28] = True
    assert np.array_equal(on, np.roll(want, shift, 1))
    assert np.array_equal(off, src)  # without the cut every consistent pull is kept as carried


@pytest.mark.parametrize("scale", [1e-3, 1.0, 3e4, 1e6])
def test_edit_data_keeps_ranges_of_a_scene_in_any_unit(scale):
    """The stored float16 range maps neither overflow (a scene in centimetres or millimetres: ranges past
    65504) nor fall to subnormals, and a metre-scale scene keeps its float16 digits exactly."""
    from rasterizer.edit.scene import EditData

    rng = np.random.default_rng(0)
    ranges = (rng.uniform(0.3, 40.0, size=(2, 2, 8, 24)) * scale).astype(np.float32)
    ranges[0, 0, 0, :3] = 0.0  # unknown pixels stay 0
    matches = np.zeros((2, 2, 8, 24, 5), np.float32)
    data = EditData(("yin", "yang"), 8, 24, matches, ranges, np.arange(10), np.ones(10, np.int64))
    back = EditData.from_bytes(data.to_bytes()).range_maps
    assert np.isfinite(back).all() and (back[0, 0, 0, :3] == 0).all()
    np.testing.assert_allclose(back, ranges, rtol=1e-3)
    if scale == 1.0:
        np.testing.assert_array_equal(back, ranges.astype(np.float16).astype(np.float32))


def test_edit_data_keeps_ranges_finite_when_the_far_ones_lie_beyond_65504_medians():
    """Most ranges a few millimetres and a tenth at 10 km (near and far options 1e9 apart): in units of the median
    the far ones overflow float16, so the stored unit grows until they fit, and none is stored as inf."""
    from rasterizer.edit.scene import EditData

    rng = np.random.default_rng(1)
    ranges = rng.uniform(0.003, 0.006, size=(2, 2, 8, 24)).astype(np.float32)
    ranges[:, :, :1] = rng.uniform(5e3, 1e4, size=(2, 2, 1, 24))
    matches = np.zeros((2, 2, 8, 24, 5), np.float32)
    data = EditData(("yin", "yang"), 8, 24, matches, ranges, np.arange(10), np.ones(10, np.int64))
    back = EditData.from_bytes(data.to_bytes()).range_maps
    assert np.isfinite(back).all()
    np.testing.assert_allclose(back, ranges, rtol=1e-3)
