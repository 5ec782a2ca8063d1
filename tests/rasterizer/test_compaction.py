"""Compaction: each dropping step removes what it should and nothing else (the smooth merge: test_compaction_smooth)."""

import numpy as np
import pytest

from rasterizer.compaction import (
    CompactionError,
    CompactionOptions,
    compact,
    compact_index,
    ply_count_for_bytes,
)
from rasterizer.ply import ply_bytes

from ._support import H, W, two_view_box


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
    idx, stats = compact_index(g, prov, CompactionOptions(min_opacity=0.01, merge_smooth=False))
    assert stats["removed"]["min_opacity"] == len(range(0, len(g), 7))
    assert np.all(g.opacities[idx] >= 0.01)


def test_min_confidence_uses_layout_confidence():
    g, prov = two_view_box()
    conf = np.ones((2, 2, H, W), np.float32)
    conf[1, 0, :3] = 0.1  # view B, Yin, top three rows
    opts = CompactionOptions(min_opacity=0, min_confidence=0.5, merge_smooth=False)
    _, stats = compact_index(g, prov, opts, confidence=conf)
    assert stats["removed"]["min_opacity"] == 3 * W
    with pytest.raises(CompactionError):
        compact_index(g, prov, opts)


def test_cap_respects_count_and_bytes():
    g, prov = two_view_box()
    op = np.linspace(0.05, 1.0, len(g)).astype(np.float32)
    g = g.with_(opacities=op)
    idx, stats = compact_index(g, prov, CompactionOptions(min_opacity=0, merge_smooth=False, max_count=100))
    assert idx.size == 100 and stats["removed"]["cap"] == len(g) - 100
    # the kept ones have the largest opacity x solid angle
    view = prov.decode(len(g))[0]
    s = np.sort(g.scales, axis=1)
    score = g.opacities * s[:, 1] * s[:, 2] / np.sum((g.means - prov.c2w[view, :3, 3]) ** 2, axis=1)
    assert score[idx].min() >= np.sort(score)[-100] - 1e-9
    budget = 20_000
    out, _ = compact(g, prov, CompactionOptions(min_opacity=0, merge_smooth=False, max_bytes=budget))
    assert len(ply_bytes(out)) <= budget
    assert len(out) == ply_count_for_bytes(budget, 1) and len(out) > 0


def test_options_json_roundtrip_and_errors():
    o = CompactionOptions.from_dict({"merge_smooth": False, "max_count": 10})
    assert o.max_count == 10 and not o.merge_smooth and CompactionOptions.from_dict(o.to_dict()) == o
    with pytest.raises(CompactionError, match="bogus"):
        CompactionOptions.from_dict({"bogus": 1})
    with pytest.raises(CompactionError):
        CompactionOptions(smooth_levels=0)
    with pytest.raises(CompactionError):
        CompactionOptions(max_count=-1)


def test_provenance_count_mismatch_raises():
    g, prov = two_view_box()
    with pytest.raises(CompactionError):
        compact(g.subset(np.arange(10)), prov)


def test_from_dict_defaults_match_the_dataclass_defaults():
    from rasterizer.compaction import CompactionOptions

    assert CompactionOptions.from_dict(None) == CompactionOptions()
    assert CompactionOptions.from_dict({}) == CompactionOptions()
