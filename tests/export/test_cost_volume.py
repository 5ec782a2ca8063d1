"""export.cost_volume: the sweep's slabs of candidates give the values of one pass."""

import pytest
import torch

from export import cost_volume
from export.aggregation import CostAggregation
from export.cost_volume import SweepCostVolume, WindowMatcher


@pytest.mark.parametrize("erp_source", [False, True])
@pytest.mark.parametrize("slab_bytes", [1, 3 * 4 * 16 * 48 * 4])
def test_slabs_equal_one_pass(monkeypatch, erp_source, slab_bytes):
    """Warp, match and guided aggregation per slab (one candidate each, or several) are the
    whole volume's to the bit, for both source layouts."""
    g_count, h, w, d = (1, 16, 32, 10) if erp_source else (2, 16, 48, 10)
    gen = torch.Generator().manual_seed(1)
    feats = torch.rand(2, g_count, 1, h, w, generator=gen)
    grids = torch.rand(2, g_count, d, h, w, 2, generator=gen) * 2 - 1
    guide = torch.rand(2 * g_count, 1, h, w, generator=gen)
    cv = SweepCostVolume(g_count, erp_source, WindowMatcher(wrap=erp_source),
                         CostAggregation((2, 3), 1e-3, wrap=erp_source))
    monkeypatch.setattr(cost_volume, "SLAB_BYTES", 1 << 40)
    whole = cv(feats, grids, guide)
    monkeypatch.setattr(cost_volume, "SLAB_BYTES", slab_bytes)
    sliced = cv(feats, grids, guide)
    assert whole.shape == (2, g_count, d, h, w)
    assert torch.equal(sliced, whole)


def test_slab_size_is_the_fewest_equal_slabs():
    mib = 1 << 20
    assert cost_volume.slab_size(64, 196_608) == 22  # 12.6 MB in three slabs of <= 4 MiB
    assert cost_volume.slab_size(64, 16) == 64
    assert cost_volume.slab_size(5, 100 * mib) == 1  # a plane over the budget: one per slab
    assert cost_volume.slab_size(1, 1) == 1
