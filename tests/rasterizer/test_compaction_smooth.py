"""Smooth-region merge: flat, evenly coloured blocks of one grid become one Gaussian; nothing else does."""

import numpy as np
import pytest

from bench.metrics import psnr
from rasterizer import compaction as cp
from rasterizer import geometry as geo
from rasterizer.compaction import (
    CompactionError,
    CompactionOptions,
    Provenance,
    compact,
    compact_result,
    merge,
    opacity_depth,
    opacity_for_depth,
    smooth_merge_blocks,
)
from rasterizer.depth_gaussians import gaussians_from_depth
from rasterizer.gaussians import Gaussians
from rasterizer.render import render

#: Only the merge runs (the other steps are tested in test_compaction.py).
ONLY_SMOOTH = dict(min_opacity=0.0, merge_smooth=True)


def wall_scene(h=32, colour=None, rng_fn=None, opacity=0.6, grid="yin", scale=1.0, cos_max=0.5):
    """One reference, one grid: the pixels looking at the wall z = 2 (camera frame) in front of it.

    ``colour(d)`` and ``rng_fn(d, rng)`` may replace the smooth gradient and the plane's ranges.
    Returns (Gaussians, Provenance, ranges (h, w) with 0 where nothing).
    """
    w = 3 * h if grid != "erp" else 2 * h
    d = geo.grid_directions(grid, h, w)
    rng = np.where(d[..., 2] > cos_max, 2.0 / np.maximum(d[..., 2], 1e-6), 0.0)
    if rng_fn is not None:
        rng = rng_fn(d, rng)
    if colour is None:
        img = np.empty((h, w, 3), np.float32)
        img[..., 0] = 0.45 + 0.1 * d[..., 0]   # gentle gradients: < 0.01 per pixel
        img[..., 1] = 0.5 + 0.05 * d[..., 1]
        img[..., 2] = 0.35
    else:
        img = colour(d).astype(np.float32)
    c2w = np.eye(4)
    c2w[:3, 3] = [0.1, -0.05, 0.2]
    g = gaussians_from_depth(img, rng * scale, c2w, grid, scale_factor=0.75, thickness=0.1, opacity=opacity)
    grids = ("erp",) if grid == "erp" else ("yin", "yang")
    offset = 0 if grid in ("erp", "yin") else h * w
    index = offset + np.flatnonzero((rng > 0).ravel())
    return g, Provenance(grids, h, w, c2w[None], index), rng


def _render_pair(a: Gaussians, b: Gaussians, c2w, width=96):
    cam = np.asarray(c2w, dtype=np.float64).copy()
    kw = dict(projection="perspective", width=width, fov_deg=70.0)
    return render(a, cam, **kw), render(b, cam, **kw)


def test_flat_plane_merges_four_to_one_and_renders_alike():
    # the wall up to 37 degrees off its normal; opacity low enough for 4x4 blocks to keep their coverage
    g, prov, _ = wall_scene(h=64, cos_max=0.8, opacity=0.2)
    out, stats = compact(g, prov, CompactionOptions(**ONLY_SMOOTH, smooth_levels=1))
    s = stats["merge_smooth"]
    assert s["blocks"] == {"2": s["added"]} and s["merged"] == 4 * s["added"]
    assert 3.5 < len(g) / len(out) < 4.0  # all but the wall's ragged border
    # seen from farther off its normal than smooth_max_incidence_deg, the wall stays as it is
    g_wide, prov_wide, _ = wall_scene(h=64, cos_max=0.5)  # up to 60 degrees off
    d_z = geo.grid_directions("yin", 64, 192)[..., 2]
    inc = CompactionOptions().smooth_max_incidence_deg
    assert inc < 59.0
    merged = compact(g_wide, prov_wide, CompactionOptions(**ONLY_SMOOTH, smooth_levels=1))[1]["merge_smooth"]["merged"]
    assert 0.9 * int((d_z > np.cos(np.radians(inc - 1))).sum()) < merged < int((d_z > np.cos(np.radians(inc + 1))).sum())
    full, small = _render_pair(g, out, prov.c2w[0])
    assert psnr(small.colour, full.colour) > 35.0  # colour over black: coverage errors would show
    inside = full.alpha > 0.5
    assert abs(float(small.alpha[inside].mean() - full.alpha[inside].mean())) < 0.02  # coverage kept
    # 4x4 blocks on top: ~16 to 1 where the wall is whole
    out2, stats2 = compact(g, prov, CompactionOptions(**ONLY_SMOOTH, smooth_levels=2))
    assert stats2["merge_smooth"]["blocks"]["4"] > 0 and len(out2) < 0.45 * len(out)
    full, small = _render_pair(g, out2, prov.c2w[0])
    assert psnr(small.colour, full.colour) > 30.0
    assert abs(float(small.alpha[inside].mean() - full.alpha[inside].mean())) < 0.03


def test_opaque_plane_keeps_most_coverage_and_no_4x4_blocks():
    """Opaque inputs: 2x2 merges saturate at 0.99 and keep the coverage (widened to MIN_OVERLAP of the
    block), 4x4 ones would lose coverage: none. Plain and V/A renders both match the uncompacted one."""
    g, prov, _ = wall_scene(h=64, cos_max=0.8, opacity=0.95)
    out, stats = compact(g, prov, CompactionOptions(**ONLY_SMOOTH, smooth_levels=2))
    assert stats["merge_smooth"]["blocks"].get("4", 0) == 0 and stats["merge_smooth"]["blocks"]["2"] > 0
    assert np.all(out.opacities <= 0.99 + 1e-6)
    full, small = _render_pair(g, out, prov.c2w[0])
    inside = full.alpha > 0.5
    assert float(full.alpha[inside].mean() - small.alpha[inside].mean()) < 0.01
    normalized = dict(projection="perspective", width=96, fov_deg=70.0, normalize=True)
    a, b = render(g, prov.c2w[0], **normalized), render(out, prov.c2w[0], **normalized)
    assert psnr(b.colour[inside], a.colour[inside]) > 40.0  # what the service shows


def test_merged_gaussian_moments_and_opacity():
    """Mean = weighted mean, covariance = mean covariance + spread of the means, widened in-plane to
    MIN_OVERLAP of the block size (never along the normal), coverage from Li2."""
    g, prov, _ = wall_scene(h=16, opacity=0.4)
    res = compact_result(g, prov, CompactionOptions(**ONLY_SMOOTH, smooth_levels=1))
    merged = np.flatnonzero(res.block == 2)
    assert merged.size > 0
    # members of one merged block: its 2x2 pixels in the layout
    k = merged[len(merged) // 2]
    top_left = res.provenance.index[k]
    w = prov.width
    r, c = divmod(int(top_left), w)
    pos = [(r + i) * w + (c + j) for i in (0, 1) for j in (0, 1)]
    members = np.flatnonzero(np.isin(prov.index, pos))
    assert members.size == 4
    m = g.subset(members)
    wgt = m.opacities * np.sort(m.scales, axis=1)[:, 1:].prod(axis=1)
    mu = (wgt[:, None] * m.means).sum(0) / wgt.sum()
    spread = np.einsum("n,ni,nj->ij", wgt, m.means - mu, m.means - mu) / wgt.sum()
    cov = np.einsum("n,nij->ij", wgt, m.covariances()) / wgt.sum() + spread
    one = res.gaussians.subset([k])
    np.testing.assert_allclose(one.means[0], mu, rtol=1e-5, atol=1e-6)
    n = np.linalg.eigh(spread)[1][:, 0]  # the block's plane normal
    extra = one.covariances()[0] - cov
    delta = np.trace(extra) / 2
    assert delta > 0
    np.testing.assert_allclose(extra, delta * (np.eye(3) - np.outer(n, n)), atol=1e-3 * delta)
    inplane = np.trace(one.covariances()[0]) - n @ one.covariances()[0] @ n
    target = cp.MIN_OVERLAP**2 * 12.0 * 4 / 3 * (np.trace(spread) - n @ spread @ n)  # 2x2: size^2 = 12 * 4/3 spread
    assert inplane == pytest.approx(target, rel=1e-3)
    np.testing.assert_allclose(one.rgb[0], m.rgb.mean(0), atol=1e-3)
    # optical depth (render area x Li2(opacity)) of the four is kept by the widened one
    pitch = (np.pi if prov.grids[0] == "erp" else 2 * geo.YIN_LAT_MAX) / prov.height
    cam = prov.c2w[0, :3, 3]
    depth = lambda x: merge._render_area(x.scales.astype(np.float64), np.linalg.norm(x.means - cam, axis=1) * pitch) \
        * cp.opacity_depth(x.opacities.astype(np.float64))  # noqa: E731
    assert float(depth(one)[0]) == pytest.approx(float(depth(m).sum()), rel=1e-3)
    assert 0.0 < one.opacities[0] <= 0.99


def test_dilog_opacity_depth_roundtrip():
    a = np.linspace(0.0, 0.99, 50)
    np.testing.assert_allclose(opacity_for_depth(opacity_depth(a)), a, atol=1e-4)
    assert abs(float(opacity_depth(np.array([0.5]))[0]) - 0.5822405265) < 1e-4  # Li2(1/2) = pi^2/12 - ln^2(2)/2
    assert opacity_for_depth(np.array([100.0]))[0] == pytest.approx(0.99)


def test_textured_blocks_are_not_merged():
    checker = lambda d: np.where(((np.indices(d.shape[:2]).sum(0)) % 2)[..., None] == 0, 0.2, 0.8) * np.ones(3)
    g, prov, _ = wall_scene(h=24, colour=checker)
    _, stats = compact(g, prov, CompactionOptions(**ONLY_SMOOTH))
    assert stats["removed"]["merge_smooth"] == 0 and stats["merge_smooth"]["added"] == 0
    # a colour ramp steeper than the tolerance per pixel is texture too
    ramp = lambda d: np.stack([np.indices(d.shape[:2])[1] * 0.05 % 1.0] * 3, axis=-1)
    g, prov, _ = wall_scene(h=24, colour=ramp)
    _, stats = compact(g, prov, CompactionOptions(**ONLY_SMOOTH, smooth_colour_tol=0.04))
    assert stats["merge_smooth"]["added"] == 0


def test_texture_test_keeps_grain_merges_ramps_and_is_scale_free():
    """A faint checker grain (+-0.01) on one half of a wall is kept, the
    smooth ramp on the other half merges, and doubling the contrast about mid-grey changes no decision."""
    h = 32

    def wall(contrast):
        def colour(d):
            j = np.indices(d.shape[:2])[1]
            grain = np.where(np.indices(d.shape[:2]).sum(0) % 2 == 0, 0.01, -0.01) * (j >= d.shape[1] // 2)
            c = (0.5 + 0.15 * d[..., 0] + grain)[..., None] * np.array([1.0, 0.9, 0.8])
            return 0.5 + contrast * (c - 0.5)
        return wall_scene(h=h, colour=colour, cos_max=0.8)

    g, prov, _ = wall(1.0)
    alive = np.ones(len(g), bool)
    sm = smooth_merge_blocks(g, prov, alive)
    col = prov.index % prov.width
    textured = col >= prov.width // 2
    assert not sm.drop[textured].any()
    assert sm.drop[~textured].mean() > 0.6  # all but the ragged border
    g2, prov2, _ = wall(2.0)
    sm2 = smooth_merge_blocks(g2, prov2, alive)
    np.testing.assert_array_equal(sm2.drop, sm.drop)
    np.testing.assert_array_equal(sm2.index, sm.index)


def test_depth_steps_are_not_merged():
    # every other column 30% farther: each 2x2 block straddles a step
    step = lambda d, rng: rng * np.where(np.arange(d.shape[1]) % 2 == 0, 1.0, 1.3)[None, :]
    g, prov, _ = wall_scene(h=24, rng_fn=step)
    _, stats = compact(g, prov, CompactionOptions(**ONLY_SMOOTH))
    assert stats["merge_smooth"]["added"] == 0
    # one step in the middle: the blocks on either side merge, none across it
    h, w = 24, 72
    mid = lambda d, rng: rng * np.where(np.arange(d.shape[1]) < w // 2 + 1, 1.0, 1.5)[None, :]
    g, prov, _ = wall_scene(h=h, rng_fn=mid)
    res = compact_result(g, prov, CompactionOptions(**ONLY_SMOOTH, smooth_levels=1))
    assert res.stats["merge_smooth"]["added"] > 0
    cols = res.provenance.index[res.block == 2] % w
    assert not np.any(cols == w // 2)  # the block at columns 36-37 spans the step (37 is the first far one)


def test_option_turns_it_off_and_is_validated():
    g, prov, _ = wall_scene(h=16)
    out, stats = compact(g, prov, CompactionOptions(**{**ONLY_SMOOTH, "merge_smooth": False}))
    assert len(out) == len(g) and stats["removed"]["merge_smooth"] == 0
    np.testing.assert_array_equal(out.means, g.means)
    assert CompactionOptions.off().merge_smooth is False
    assert CompactionOptions().merge_smooth is True
    assert CompactionOptions.from_dict({"merge_smooth": False}).merge_smooth is False
    for bad in ({"smooth_levels": 0}, {"smooth_levels": 5}, {"smooth_levels": True}, {"smooth_colour_tol": -1},
                {"smooth_plane_tol": float("nan")}, {"smooth_max_incidence_deg": 95}):
        with pytest.raises(CompactionError):
            CompactionOptions.from_dict(bad)


def test_stats_count_every_step():
    g, prov, _ = wall_scene(h=32)
    out, stats = compact(g, prov, CompactionOptions(**ONLY_SMOOTH))
    s = stats["merge_smooth"]
    assert stats["removed"]["merge_smooth"] == s["merged"] - s["added"]
    assert sum(stats["removed"].values()) == stats["input"] - stats["output"] == len(g) - len(out)
    assert s["merged"] == sum(int(k) ** 2 * v for k, v in s["blocks"].items())
    assert s["added"] == sum(s["blocks"].values())
    assert set(stats["seconds"]) >= {"merge_smooth"} and stats["options"]["merge_smooth"] is True


def test_blocks_stay_inside_odd_sized_grids_and_output_is_finite():
    h = 13  # odd: the last row and column have no partner and stay as they are
    g, prov, _ = wall_scene(h=h)
    res = compact_result(g, prov, CompactionOptions(**ONLY_SMOOTH, smooth_levels=3))
    res.gaussians.check_finite()
    w = 3 * h
    row, col = np.divmod(res.provenance.index % (h * w), w)
    assert np.all(row + res.block <= h) and np.all(col + res.block <= w)
    assert np.all((row % res.block == 0) & (col % res.block == 0))
    # the output is in layout order and the kept inputs are what the index says
    assert np.all(np.diff(res.provenance.index) > 0)
    np.testing.assert_array_equal(res.gaussians.means[res.block == 1], g.means[res.index])


def test_erp_layout_poles_and_seam():
    """A sphere of constant range around an ERP camera: merges up to the poles, never across the seam."""
    h, w = 32, 64
    c2w = np.eye(4)
    img = np.full((h, w, 3), 0.5, np.float32)
    g = gaussians_from_depth(img, np.full((h, w), 3.0), c2w, "erp", scale_factor=0.75, thickness=0.1, opacity=0.7)
    prov = Provenance(("erp",), h, w, c2w[None])
    res = compact_result(g, prov, CompactionOptions(**ONLY_SMOOTH, smooth_levels=2))
    res.gaussians.check_finite()
    assert res.stats["merge_smooth"]["added"] > 0 and len(res.gaussians) < 0.5 * len(g)
    col = res.provenance.index % w
    assert np.all(col + res.block <= w)  # the seam (col W-1 | col 0) is never inside a block
    row = res.provenance.index // w
    assert np.any((row == 0) & (res.block > 1))  # the polar rows merge too (squeezed, still planar)
    out = render(res.gaussians, c2w, projection="erp", width=64)
    assert np.all(np.isfinite(out.colour)) and np.all(np.abs(out.colour[out.alpha > 0.1] - 0.5) < 0.02)


@pytest.mark.parametrize("scale", [1e-4, 1e5])
def test_tiny_and_huge_ranges_merge_the_same(scale):
    g1, prov1, _ = wall_scene(h=24)
    gs, provs, _ = wall_scene(h=24, scale=scale)
    provs = Provenance(provs.grids, provs.height, provs.width, prov1.c2w, provs.index)
    # the camera centre scales with the scene
    c2w = prov1.c2w.copy()
    c2w[:, :3, 3] *= scale
    gs = gs.with_(means=(gs.means.astype(np.float64) - prov1.c2w[0, :3, 3] + c2w[0, :3, 3]))
    provs = Provenance(provs.grids, provs.height, provs.width, c2w, provs.index)
    a = compact_result(g1, prov1, CompactionOptions(**ONLY_SMOOTH))
    b = compact_result(gs, provs, CompactionOptions(**ONLY_SMOOTH))
    b.gaussians.check_finite()
    assert a.stats["merge_smooth"] == b.stats["merge_smooth"]
    np.testing.assert_allclose(b.gaussians.scales / scale, a.gaussians.scales, rtol=1e-3)


def test_only_blocks_whose_pixels_are_all_present():
    g, prov, _ = wall_scene(h=24)
    alive = np.ones(len(g), bool)
    alive[::7] = False  # scattered holes
    sm = smooth_merge_blocks(g, prov, alive, levels=1)
    assert not np.any(sm.drop & ~alive)
    # every merged block's four pixels were alive
    flat = prov.index
    alive_pos = set(flat[alive].tolist())
    w = prov.width
    for tl in sm.index[:: max(1, sm.index.size // 40)]:
        assert {int(tl), int(tl) + 1, int(tl) + w, int(tl) + w + 1} <= alive_pos


def test_merge_with_cap_and_default_steps_on_two_views():
    from tests.rasterizer._support import two_view_box

    g, prov = two_view_box()
    res = compact_result(g, prov, CompactionOptions(max_count=200))
    assert len(res.gaussians) == 200 and res.stats["output"] == 200
    assert sum(res.stats["removed"].values()) == len(g) - 200
    np.testing.assert_array_equal(res.gaussians.means[res.block == 1], g.means[res.index])
    res.gaussians.check_finite()


def test_a_count_cap_merges_the_least_textured_blocks_before_it_drops():
    """Under a count cap the merge goes on past the texture test, least textured blocks first, so the cap
    drops nothing while mergeable blocks remain: a faint grain merges before a strong one, and a ramp as
    without the cap (merged blocks keep the surface closed where dropped Gaussians would leave holes)."""
    def colour(d):
        i, j = np.indices(d.shape[:2])
        w = d.shape[1]
        amp = np.where(j < w // 3, 0.0, np.where(j < 2 * w // 3, 0.006, 0.03))
        grain = np.where((i + j) % 2 == 0, amp, -amp)
        return (0.5 + 0.15 * d[..., 0] + grain)[..., None] * np.array([1.0, 0.9, 0.8])

    g, prov, _ = wall_scene(h=32, colour=colour, cos_max=0.8)
    w = prov.width

    def merged_columns(res):
        return res.provenance.index[res.block == 2] % w

    base = compact_result(g, prov, CompactionOptions(**ONLY_SMOOTH))
    assert (merged_columns(base) < w // 3 + 1).all()  # only the ramp passes the texture test
    extra = 30
    res = compact_result(g, prov, CompactionOptions(**ONLY_SMOOTH, max_count=len(base.gaussians) - 3 * extra))
    assert res.stats["removed"]["cap"] == 0 and len(res.gaussians) == len(base.gaussians) - 3 * extra
    cols = merged_columns(res)
    assert (cols < 2 * w // 3).all()  # the strong grain is left whole
    assert ((cols >= w // 3) & (cols < 2 * w // 3)).sum() >= extra  # the faint grain merged instead
    assert set(base.provenance.index[base.block == 2]) <= set(res.provenance.index[res.block == 2])  # and the ramp
    res.gaussians.check_finite()
