"""Compaction: each step removes what it should and nothing else; compacted scenes re-render alike."""

import numpy as np
import pytest

from bench.metrics import psnr
from rasterizer import geometry as geo
from rasterizer.compaction import (
    CompactionError,
    CompactionOptions,
    Provenance,
    compact,
    compact_index,
    overlap_keep_mask,
    owner_grid,
    ply_count_for_bytes,
)
from rasterizer.depth_gaussians import gaussians_from_depth
from rasterizer.gaussians import Gaussians
from rasterizer.ply import ply_bytes
from rasterizer.render import render

from ._support import H, W, pose_at, two_view_box


def test_disabled_steps_remove_nothing():
    g, prov = two_view_box()
    out, stats = compact(g, prov, CompactionOptions.off())
    assert len(out) == len(g) and stats["output"] == len(g)
    assert all(v == 0 for v in stats["removed"].values())
    np.testing.assert_array_equal(out.means, g.means)


def test_min_opacity_removes_only_transparent():
    g, prov = two_view_box()
    op = g.opacities.copy()
    op[::7] = 0.001
    g = g.with_(opacities=op)
    idx, stats = compact_index(g, prov, CompactionOptions.off().__class__(
        min_opacity=0.01, resolve_overlap="off", merge_duplicates=False, merge_smooth=False))
    assert stats["removed"]["min_opacity"] == len(range(0, len(g), 7))
    assert np.all(g.opacities[idx] >= 0.01)


def test_min_confidence_uses_layout_confidence():
    g, prov = two_view_box()
    conf = np.ones((2, 2, H, W), np.float32)
    conf[1, 0, :3] = 0.1  # view B, Yin, top three rows
    opts = CompactionOptions(min_opacity=0, min_confidence=0.5, resolve_overlap="off", merge_duplicates=False,
                             merge_smooth=False)
    _, stats = compact_index(g, prov, opts, confidence=conf)
    assert stats["removed"]["min_opacity"] == 3 * W
    with pytest.raises(CompactionError):
        compact_index(g, prov, opts)


@pytest.mark.parametrize("mode", ["split", "yin"])
def test_overlap_covers_every_direction_once(mode):
    rng = np.random.default_rng(0)
    d = rng.normal(size=(200_000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    owner = owner_grid(d, mode)
    count = np.zeros(len(d), int)
    for gi, kind in enumerate(("yin", "yang")):
        count += geo.in_grid_domain(kind, d) & (owner == gi)
    assert np.all(count == 1)
    # the pixel mask is the continuous rule at pixel centres, and removes only overlap pixels
    keep = overlap_keep_mask(("yin", "yang"), 64, 192, mode)
    for gi, kind in enumerate(("yin", "yang")):
        dirs = geo.grid_directions(kind, 64, 192)
        np.testing.assert_array_equal(keep[gi], owner_grid(dirs, mode) == gi)
        other = geo.in_grid_domain("yang" if gi == 0 else "yin", dirs)
        assert np.all(keep[gi] | other)  # dropped pixels are seen by the other grid
    frac = 1 - keep.mean()
    assert 0.03 < frac < 0.08  # ~6% of two grids' pixels is overlap


def test_overlap_step_counts_match_mask():
    g, prov = two_view_box()
    opts = CompactionOptions(min_opacity=0, resolve_overlap="split", merge_duplicates=False, merge_smooth=False)
    _, stats = compact_index(g, prov, opts)
    assert stats["removed"]["resolve_overlap"] == 2 * int((~overlap_keep_mask(("yin", "yang"), H, W)).sum())


def test_duplicates_merge_on_a_plane_seen_by_both():
    """Two cameras 0.2 m apart facing a wall 2 m away: the wall is sampled twice, once is enough."""
    h, w = 24, 72
    poses = [pose_at([-0.1, 0.0, 0.0]), pose_at([0.1, 0.0, 0.0])]
    parts = []
    for c in poses:
        for k in ("yin", "yang"):
            d = geo.grid_directions(k, h, w)
            rng = np.where(d[..., 2] > 0.3, 2.0 / np.maximum(d[..., 2], 1e-6), 0.0)  # plane z = 2 ahead only
            parts.append(gaussians_from_depth(np.full((h, w, 3), 0.5, np.float32), rng, c, k))
    g = Gaussians.concatenate(parts)
    # layout index of the kept pixels (depth > 0)
    idx = []
    for v, c in enumerate(poses):
        for gi, k in enumerate(("yin", "yang")):
            d = geo.grid_directions(k, h, w)
            idx.append((v * 2 + gi) * h * w + np.flatnonzero((d[..., 2] > 0.3).ravel()))
    prov = Provenance(("yin", "yang"), h, w, np.stack(poses), np.concatenate(idx))
    opts = CompactionOptions(min_opacity=0, resolve_overlap="off", merge_duplicates=True, merge_smooth=False)
    kept, stats = compact(g, prov, opts)
    removed = stats["removed"]["merge_duplicates"]
    assert 0.35 * len(g) < removed < 0.55 * len(g)
    # every dropped Gaussian lies within a pixel of a kept one of the other view
    view = prov.decode(len(g))[0]
    kidx = compact_index(g, prov, opts)[0]
    dropped = np.setdiff1d(np.arange(len(g)), kidx)
    kept_set = set(kidx.tolist())
    for i in dropped[:: max(1, dropped.size // 50)]:
        others = np.array([j for j in np.flatnonzero(view != view[i]) if j in kept_set])
        dist = np.linalg.norm(g.means[others] - g.means[i], axis=1).min()
        assert dist < 3 * g.scales[i, :2].max() * 2
    # a wall sampled by only one camera is never touched
    solo = g.subset(view == 0)
    solo_prov = Provenance(("yin", "yang"), h, w, np.stack(poses), prov.index[view == 0])
    _, s2 = compact(solo, solo_prov, opts)
    assert s2["removed"]["merge_duplicates"] == 0


def test_duplicates_keep_occluded_surfaces():
    """A surface hidden from the other view (its range there is much smaller) is not merged."""
    g, prov = two_view_box()
    means = g.means.copy()
    view = prov.decode(len(g))[0]
    # push view B's Gaussians far behind the box: view A's points are then in front of B's samples
    c_b = prov.c2w[1, :3, 3]
    means[view == 1] = c_b + (means[view == 1] - c_b) * 3.0
    g2 = g.with_(means=means)
    _, stats = compact(g2, prov, CompactionOptions(min_opacity=0, resolve_overlap="off"))
    assert stats["removed"]["merge_duplicates"] == 0


def test_cap_respects_count_and_bytes():
    g, prov = two_view_box()
    op = np.linspace(0.05, 1.0, len(g)).astype(np.float32)
    g = g.with_(opacities=op)
    idx, stats = compact_index(g, prov, CompactionOptions.off().__class__(
        min_opacity=0, resolve_overlap="off", merge_duplicates=False, merge_smooth=False, max_count=100))
    assert idx.size == 100 and stats["removed"]["cap"] == len(g) - 100
    # the kept ones have the largest opacity x solid angle
    view = prov.decode(len(g))[0]
    s = np.sort(g.scales, axis=1)
    score = g.opacities * s[:, 1] * s[:, 2] / np.sum((g.means - prov.c2w[view, :3, 3]) ** 2, axis=1)
    assert score[idx].min() >= np.sort(score)[-100] - 1e-9
    budget = 20_000
    out, _ = compact(g, prov, CompactionOptions(min_opacity=0, resolve_overlap="off", merge_duplicates=False,
                                                merge_smooth=False,
                                                max_bytes=budget))
    assert len(ply_bytes(out)) <= budget
    assert len(out) == ply_count_for_bytes(budget, 1) and len(out) > 0


def test_options_json_roundtrip_and_errors():
    o = CompactionOptions.from_dict({"resolve_overlap": False, "max_count": 10})
    assert o.resolve_overlap == "off" and CompactionOptions.from_dict(o.to_dict()) == o
    with pytest.raises(CompactionError):
        CompactionOptions.from_dict({"bogus": 1})
    with pytest.raises(CompactionError):
        CompactionOptions(resolve_overlap="half")
    with pytest.raises(CompactionError):
        CompactionOptions(max_count=-1)


def test_provenance_count_mismatch_raises():
    g, prov = two_view_box()
    with pytest.raises(CompactionError):
        compact(g.subset(np.arange(10)), prov)


def test_compacted_scene_renders_like_the_full_one():
    g, prov = two_view_box()
    # every step on (the product default leaves overlap and duplicates off); exact (GT) depths here,
    # so a 10% range tolerance is safe
    opts = CompactionOptions(resolve_overlap="split", merge_duplicates=True, duplicate_range_tol=0.1)
    out, stats = compact(g, prov, opts)
    assert stats["output"] < 0.75 * len(g)
    target = pose_at([0.05, 0.02, 0.0])
    full = render(g, target, projection="erp", width=96)
    small = render(out, target, projection="erp", width=96)
    assert psnr(small.colour, full.colour) > 25.0
    # and against a deliberately broken compaction (half of everything dropped at random) it is better
    rnd = g.subset(np.random.default_rng(1).random(len(g)) < len(out) / len(g))
    assert psnr(small.colour, full.colour) > psnr(render(rnd, target, projection="erp", width=96).colour,
                                                  full.colour)


def test_from_dict_defaults_match_the_dataclass_defaults():
    from rasterizer.compaction import CompactionOptions

    assert CompactionOptions.from_dict(None) == CompactionOptions()
    assert CompactionOptions.from_dict({}) == CompactionOptions()
    assert CompactionOptions.from_dict({"resolve_overlap": False}).resolve_overlap == "off"
    assert CompactionOptions.from_dict({"resolve_overlap": True}).resolve_overlap == "split"
