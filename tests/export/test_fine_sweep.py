"""Cascade stage (export/fine_sweep.py): in-graph projection, stacked Yin/Yang sampling, LR check, refinement."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from export import cost_volume
from export.aggregation import CostAggregation
from export.config import make_config
from export.cost_volume import WindowMatcher, sample_maps
from export.fine_sweep import FineSweep, _lon, project_normalised
from export.readout import DepthReadout
from rasterizer.geometry import grid_directions, project_to_grid
from rasterizer.sweep import normalised_coords

finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)


@settings(max_examples=300, deadline=None)
@given(finite, finite)
def test_lon_matches_atan2(x, z):
    if math.hypot(x, z) < 1e-6:
        return  # the axis itself: no longitude (a pole, outside every Yin/Yang domain)
    got = float(_lon(torch.tensor([x], dtype=torch.float64), torch.tensor([z], dtype=torch.float64)))
    want = math.atan2(x, z)
    if abs(abs(want) - math.pi) < 1e-12:  # the seam: +pi and -pi are the same meridian
        assert abs(abs(got) - math.pi) < 1e-9
    else:
        assert abs(got - want) < 1e-9



def domain_mask(grid: torch.Tensor) -> torch.Tensor:
    """(..., 2) grid_sample coordinates -> (...) float 1 inside [-1, 1]^2, else 0."""
    return (grid.abs().amax(-1) <= 1.0).to(grid.dtype)

def test_lon_seam_and_axes_are_finite():
    x = torch.tensor([0.0, -0.0, 1e-30, -1.0, 0.0, 1.0])
    z = torch.tensor([-1.0, -2.0, -1.0, 0.0, 0.0, 1.0])
    got = _lon(x, z)
    assert torch.all(torch.isfinite(got))
    np.testing.assert_allclose(got[[0, 1, 2, 3, 5]].abs().numpy(), [math.pi, math.pi, math.pi, math.pi / 2, math.pi / 4],
                               atol=1e-6)


@pytest.mark.parametrize("kind", ["yin", "yang", "erp"])
def test_projection_matches_the_geometry_module(kind):
    """Same grid_sample coordinates as rasterizer.geometry + rasterizer.sweep (the one convention)."""
    rng = np.random.default_rng(1)
    p = rng.normal(size=(4000, 3)) * rng.uniform(0.1, 30.0, size=(4000, 1))
    h, w = (32, 64) if kind == "erp" else (32, 96)
    want = normalised_coords(kind, *project_to_grid(kind, p, h, w), h, w)
    got = project_normalised(torch.from_numpy(p), kind, w).numpy()
    np.testing.assert_allclose(got, want, atol=2e-5)


def _rays(h, w):
    return torch.from_numpy(np.stack([grid_directions(k, h, w) for k in ("yin", "yang")]).astype(np.float32))


def _rel_rt():
    a = torch.tensor([[1, 0, 0, 0.1], [0, 1, 0, 0.2], [0, 0, 1, 1.0]], dtype=torch.float32)
    b = a.clone()
    b[:, 3] = -a[:, 3]
    return torch.stack([a, b])


def test_stacked_sampling_is_the_mask_blend_with_yin_priority():
    """One sample per point in Yin-over-Yang stacked maps == both grids sampled, Yin taken where valid."""
    torch.manual_seed(0)
    h, w, j = 16, 48, 3
    maps = torch.rand(4, 1, h, w)
    inv = torch.rand(4, 1, j, h, w) + 0.2
    fs = FineSweep(("yin", "yang"), j, None, None, None)
    pts = fs.points(inv, _rays(h, w), _rel_rt())  # (x, y, z)
    got = fs.sample(maps, pts).reshape(2, 2, j, h, w)
    src = maps.reshape(2, 2, 1, h, w).flip(0)
    per_grid = []
    for g, kind in enumerate(("yin", "yang")):
        coords = project_normalised(torch.stack(pts, dim=-1), kind)
        per_grid.append((sample_maps(src[:, g], coords.reshape(2, -1, w, 2), False).reshape(2, 2, j, h, w),
                         domain_mask(coords)))
    (s_yin, m_yin), (s_yang, m_yang) = per_grid
    assert torch.all(m_yin + m_yang > 0)  # Yin and Yang cover the sphere
    want = torch.where(m_yin > 0, s_yin, s_yang)
    np.testing.assert_allclose(got.numpy(), want.numpy(), atol=1e-5)


def _sphere_inverse_ranges(h, w, centres, radius):
    """Exact inverse range of every [view][Yin, Yang] pixel of two cameras (identity rotation) inside a sphere."""
    rays = _rays(h, w).double()
    out = []
    for c in centres:
        c = torch.tensor(c, dtype=torch.float64)
        cd = (rays * c).sum(-1)
        r = -cd + torch.sqrt(cd * cd - (c * c).sum() + radius**2)
        out.append(1.0 / r)
    return torch.stack(out).reshape(4, 1, h, w).float()


def test_lr_consistency_on_a_sphere():
    h, w = 24, 72
    ca, cb = (0.0, 0.0, 0.0), (0.0, 0.0, 1.0)
    rel = torch.zeros(2, 3, 4)
    rel[:, :, :3] = torch.eye(3)
    rel[0, :, 3] = torch.tensor([0.0, 0.0, -1.0])  # A's camera frame -> B's
    rel[1, :, 3] = torch.tensor([0.0, 0.0, 1.0])
    inv = _sphere_inverse_ranges(h, w, [ca, cb], 4.0)
    fs = FineSweep(("yin", "yang"), 3, None, None, None)
    ok = fs.lr_consistency(inv, _rays(h, w), rel, 0.002)
    assert ok.shape == (4, 1, h, w) and ok.mean() > 0.99
    bad = inv.clone()
    bad[2:, :, 8:16, 30:40] *= 1.3  # B's depth wrong in one patch: A's pixels seeing it fail
    ok_bad = fs.lr_consistency(bad, _rays(h, w), rel, 0.002)
    assert ok_bad[2:, :, 8:16, 30:40].mean() < 0.05
    assert ok_bad[:2].mean() < ok[:2].mean() - 0.005


def _texture(p: torch.Tensor) -> torch.Tensor:
    """Grey texture on the sphere (deterministic, fine detail in every direction)."""
    d = p / p.norm(dim=-1, keepdim=True)
    v = (torch.sin(23 * d[..., 0] + 3) * torch.sin(19 * d[..., 1] + 1) + torch.sin(29 * d[..., 2] + 17 * d[..., 0]))
    return 0.5 + 0.2 * v


def test_fine_sweep_refines_a_perturbed_depth():
    """Textured sphere room, two cameras 1 m apart: a coarse depth off by ~1.5 steps comes back to the truth."""
    h, w, j = 48, 144, 9
    centres = [(0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, 0.0, 1.0)]
    radius = 3.0
    inv_true = _sphere_inverse_ranges(h, w, centres[::2], radius)
    rays = _rays(h, w)
    grey = torch.stack([_texture(torch.tensor(c) + rays[i % 2] / inv_true[i, 0, ..., None]) for i, c in enumerate(centres)])
    grey = grey.reshape(4, 1, h, w)
    rel = torch.zeros(2, 3, 4)
    rel[:, :, :3] = torch.eye(3)
    rel[0, :, 3] = torch.tensor([0.0, 0.0, -1.0])
    rel[1, :, 3] = torch.tensor([0.0, 0.0, 1.0])
    step = 0.02
    fs = FineSweep(("yin", "yang"), j, WindowMatcher(2, (1, 3), 0.015, 0.002, 0.5),
                   CostAggregation((2,), 1e-2), DepthReadout(margin_scales=(0.2,)))
    start = inv_true + 1.5 * step
    refined, conf = fs(start, grey, rays, rel, torch.tensor(step), torch.tensor(0.05), torch.tensor(3.0))
    # away from the epipoles (the z axis, where no parallax exists) the truth is recovered
    zc = rays[..., 2].abs().repeat(2, 1, 1).reshape(4, 1, h, w)
    seen = zc < 0.7
    for view in (slice(0, 2), slice(2, 4)):  # both directions of the sweep
        err_before = (start - inv_true)[view].abs()[seen[view]].median()
        err_after = (refined - inv_true)[view].abs()[seen[view]].median()
        assert err_after < 0.25 * err_before
    assert torch.all(torch.isfinite(refined)) and conf.min() >= 0 and conf.max() <= 1


@pytest.mark.parametrize("slab_bytes", [1, 5 * 48 * 144 * 4 * 4])
def test_fine_sweep_slabs_give_the_one_pass_values(monkeypatch, slab_bytes):
    """Hypotheses scored in slabs (one plane each, or uneven slabs of 5 and 4) equal the whole volume at once."""
    h, w, j = 48, 144, 9
    rays = _rays(h, w)
    gen = torch.Generator().manual_seed(0)
    grey = torch.rand(4, 1, h, w, generator=gen)
    inv = 0.3 + 0.1 * torch.rand(4, 1, h, w, generator=gen)
    rel = torch.zeros(2, 3, 4)
    rel[:, :, :3] = torch.eye(3)
    rel[:, 2, 3] = torch.tensor([-1.0, 1.0])
    fs = FineSweep(("yin", "yang"), j, WindowMatcher(2, (1, 3), 0.015, 0.002, 0.5),
                   CostAggregation((2, 4), 1e-2), DepthReadout(margin_scales=(0.2,)))
    args = (inv, grey, rays, rel, torch.tensor(0.02), torch.tensor(0.05), torch.tensor(3.0))
    monkeypatch.setattr(cost_volume, "SLAB_BYTES", 1 << 40)
    assert cost_volume.slab_size(j, 4 * h * w * 4) == j
    whole = fs(*args)
    monkeypatch.setattr(cost_volume, "SLAB_BYTES", slab_bytes)
    assert cost_volume.slab_size(j, 4 * h * w * 4) == (1 if slab_bytes == 1 else 5)
    for got, want in zip(fs(*args), whole):
        assert torch.equal(got, want)


def test_config_checks_the_fine_stage():
    with pytest.raises(ValueError, match="fine_hypotheses"):
        make_config("quality", fine_hypotheses=4)
    with pytest.raises(ValueError, match="fine_downscale"):
        make_config("quality", height=128, width=256, fine_hypotheses=5, fine_downscale=3)


def test_output_confidence_is_the_larger_of_the_coarse_and_the_cascades():
    """The encoder's confidence (opacity, footprint, matches) takes the cascade's where it is higher: a fine map
    put in place of the cascade's comes out upsampled under a max, and the real one never lowers the coarse one."""
    from export.model import OmniSplatEncoder
    from export.onnx_export import dummy_inputs

    cfg = make_config("quality", height=64, width=128)
    model = OmniSplatEncoder(cfg).eval()
    inputs = dummy_inputs(cfg)
    real = model.cascade
    fine_shape = (4, 1, model.fine_h, model.fine_w)
    fine = torch.zeros(fine_shape)
    fine[:, :, : model.fine_h // 2] = 0.9

    def with_fine(value):
        def cascade(*args):
            filled, grey, conf = real(*args)
            assert conf.shape == fine_shape and 0.0 <= float(conf.min()) and float(conf.max()) <= 1.0
            return filled, grey, value
        return cascade

    with torch.no_grad():
        got = {}
        for name, value in (("coarse", torch.zeros(fine_shape)), ("fine", fine)):
            model.cascade = with_fine(value)
            got[name] = model(*inputs)[6]  # confidence (2, G, H, W)
        model.cascade = real
        both = model(*inputs)[6]
    up = torch.nn.functional.interpolate(fine, size=got["coarse"].shape[-2:], mode="bilinear", align_corners=False)
    torch.testing.assert_close(got["fine"], torch.maximum(got["coarse"], up.reshape(got["coarse"].shape)))
    assert float(got["fine"][..., : cfg.full_size[0] // 2 - 2, :].min()) >= 0.9 - 1e-6
    assert bool(torch.all(both >= got["coarse"]))
