"""A click on a strip superpixel (the band Felzenszwalb leaves along an edge) seeds the surface it is on."""

import numpy as np

from rasterizer.edit.segment import SegmentOptions, interior_depth, region_graph, seed_superpixels, select_regions


def _strip_scene():
    """Columns 0-13: dark surface A (0), 14-15: a strip of mixed colour (1), 16-31: light surface B (2).

    The strip's column 14 looks like A, column 15 like B; both its edges weigh more than the level (a strip
    between two surfaces sits at about half the weight of their edge), so single linkage alone joins nothing
    to it.
    """
    h, w = 16, 32
    labels = np.zeros((h, w), np.int32)
    labels[:, 14:16] = 1
    labels[:, 16:] = 2
    colour = np.empty((h, w, 3), np.float32)
    colour[:, :14] = 0.2
    colour[:, 14] = 0.28
    colour[:, 15] = 0.52
    colour[:, 16:] = 0.6
    inv = np.full((h, w), 0.5, np.float32)
    normals = np.tile(np.array([0, 0, 1], np.float32), (h, w, 1))
    g = region_graph(labels, colour, inv, normals, SegmentOptions())
    return g, colour


def test_interior_depth_tells_a_strip_from_a_surface():
    g, _ = _strip_scene()
    depth = interior_depth(g.labels)
    np.testing.assert_allclose(g.depth, depth)
    assert depth[1] <= SegmentOptions().strip_depth < min(depth[0], depth[2])


def test_click_on_a_strip_selects_the_surface_its_pixel_looks_like():
    g, colour = _strip_scene()
    opts = SegmentOptions()
    level = float(g.weight[(g.i == 1) | (g.j == 1)].min()) * 0.9  # both strip edges above the level
    ab = (g.i == 0) & (g.j == 2)
    assert not ab.any() or g.weight[ab].min() > level  # the seam edge A-B does not join either
    w = g.labels.shape[1]
    on_a_side, on_b_side = 8 * w + 14, 8 * w + 15
    alone, _ = select_regions(g, g.labels.ravel()[[on_a_side]], np.zeros(0, int), level)
    assert alone.tolist() == [False, True, False]  # what a plain seed gives: the strip only
    sel_a, _ = select_regions(g, seed_superpixels(g, colour, [on_a_side], opts), np.zeros(0, int), level)
    sel_b, _ = select_regions(g, seed_superpixels(g, colour, [on_b_side], opts), np.zeros(0, int), level)
    assert sel_a.tolist() == [True, True, False]
    assert sel_b.tolist() == [False, True, True]
    # a negative point on the surface the click resembles keeps that surface out of the seeds
    assert seed_superpixels(g, colour, [on_a_side], opts, exclude=np.array([0])).tolist() == [1]
    # a click inside a surface seeds that surface alone
    assert seed_superpixels(g, colour, [8 * w + 3], opts).tolist() == [0]


def test_seeds_without_stored_colour_and_depth_match_the_graphs():
    g, colour = _strip_scene()
    bare = type(g)(g.labels, g.size, g.i, g.j, g.weight)
    for px in (8 * 32 + 14, 8 * 32 + 15, 3):
        assert seed_superpixels(bare, colour, [px], SegmentOptions()).tolist() == \
            seed_superpixels(g, colour, [px], SegmentOptions()).tolist()
