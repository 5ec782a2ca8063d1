"""Scene-adaptive near/far: robust percentiles of confident ranges, and the two-pass driver."""

from types import SimpleNamespace

import numpy as np
import pytest

from service.scene_adaptive import AdaptiveRangeError, AdaptiveRangeOptions, range_from_maps, reconstruct_adaptive


def _maps(seed=0):
    rng = np.random.default_rng(seed)
    r = rng.uniform(1.0, 4.0, size=(2, 2, 16, 48))
    conf = np.ones_like(r)
    return r, conf


def test_range_tightens_to_the_confident_span():
    r, conf = _maps()
    r[0, 0, 0, :5] = 19.99  # pinned at far: "no match", ignored
    conf[1, 1, :2] = 0.0
    r[1, 1, :2] = 0.31  # unconfident outliers: ignored
    near, far, info = range_from_maps(r, conf, 0.3, 20.0, AdaptiveRangeOptions(margin=0.1))
    assert 0.85 < near < 1.0 and 4.0 < far < 4.6
    assert info["confident_fraction"] > 0.9


def test_range_never_widens_and_keeps_min_ratio():
    r = np.full((2, 2, 8, 24), 2.0)
    conf = np.ones_like(r)
    near, far, _ = range_from_maps(r, conf, 0.3, 20.0, AdaptiveRangeOptions(min_ratio=3.0))
    assert far / near == pytest.approx(3.0) and 0.3 <= near < 2.0 < far <= 20.0
    near, far, _ = range_from_maps(r * 100, conf, 0.3, 20.0)
    assert (near, far) == (0.3, 20.0)  # everything pinned/out of range: default kept


def test_too_few_confident_pixels_keeps_default():
    r, conf = _maps()
    conf[:] = 0.0
    near, far, info = range_from_maps(r, conf, 0.3, 20.0)
    assert (near, far) == (0.3, 20.0) and "reason" in info


def test_no_confident_pixel_keeps_default_even_when_min_fraction_is_0():
    """min_confidence 1 with min_fraction 0: no pixel to take percentiles of (an IndexError, a 500 from the API)."""
    r, conf = _maps()
    conf[:] = 0.9
    near, far, info = range_from_maps(r, conf, 0.3, 20.0, AdaptiveRangeOptions(min_confidence=1.0, min_fraction=0.0))
    assert (near, far) == (0.3, 20.0) and "confident" in info["reason"] and info["confident_fraction"] == 0.0


def test_one_confident_range_without_margin_keeps_default():
    """Every confident range equal, margin 0 and min_ratio 1 would give near == far, which no sweep takes."""
    r = np.full((2, 2, 8, 24), 2.0)
    near, far, info = range_from_maps(r, np.ones_like(r), 0.3, 20.0, AdaptiveRangeOptions(margin=0.0, min_ratio=1.0))
    assert (near, far) == (0.3, 20.0) and "span" in info["reason"]


def test_options_validation():
    with pytest.raises(AdaptiveRangeError):
        AdaptiveRangeOptions(low_pct=50, high_pct=10)
    with pytest.raises(AdaptiveRangeError):
        AdaptiveRangeOptions.from_dict({"nope": 1})
    assert AdaptiveRangeOptions.from_dict({"enabled": True}).enabled


class _FakeEncoder:
    """Records the near/far it is called with; range maps span 1-4 m."""

    def __init__(self):
        self.calls = []
        self.metadata = {"name": "fake"}

    def reconstruct(self, a, b, ca, cb, *, near=None, far=None, **kw):
        near = 0.3 if near is None else near
        far = 20.0 if far is None else far
        self.calls.append((near, far))
        r, conf = _maps()
        return SimpleNamespace(range_maps=r, confidence=conf, info={"near": near, "far": far},
                               timings={"total": 0.01}, gaussians=None)


def test_two_pass_reruns_with_tightened_range():
    enc, coarse = _FakeEncoder(), _FakeEncoder()
    rec = reconstruct_adaptive(enc, None, None, None, None, coarse_encoder=coarse)
    assert coarse.calls == [(0.3, 20.0)] and len(enc.calls) == 1
    near, far = enc.calls[0]
    assert 0.8 < near < 1.0 and 4.0 < far < 5.0
    assert rec.info["adaptive_range"]["near"] == near and "coarse" in rec.timings
    off = _FakeEncoder()
    reconstruct_adaptive(off, None, None, None, None, options=AdaptiveRangeOptions(enabled=False))
    assert off.calls == [(0.3, 20.0)]
