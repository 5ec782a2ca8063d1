"""View-dependent colour (degree-1 SH): exact at the own reference, bounded elsewhere, and a render at each
reference that shows that reference's colours where the two disagree."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rasterizer import view_colour
from rasterizer.depth_gaussians import gaussians_from_depth
from rasterizer.gaussians import Gaussians, sh_dc_to_rgb
from rasterizer.render import render
from rasterizer.sh import sh_to_rgb
from rasterizer.view_colour import VIEW_COLOUR_RIDGE, fit_view_colour
from tests.rasterizer._support import box_range, pose_at

H, W = 16, 48  # one Yin/Yang grid
GRIDS = ("yin", "yang")


def _scene(tint_a, tint_b, offset=0.3, opacity=0.99, size=(H, W)):
    """Two references in a box room, each surface coloured by its own view's tint: (layout, ranges, poses)."""
    poses = np.stack([pose_at([0.0, 0.0, -offset]), pose_at([0.0, 0.0, offset])])
    ranges = np.stack([[box_range(k, c, size=size) for k in GRIDS] for c in poses])
    parts = []
    for v, (c, tint) in enumerate(zip(poses, (tint_a, tint_b))):
        for gi, k in enumerate(GRIDS):
            colour = np.broadcast_to(np.asarray(tint, np.float32), (*size, 3))
            parts.append(gaussians_from_depth(colour, ranges[v, gi], c, k, surfels=True, opacity=opacity))
    return Gaussians.concatenate(parts), ranges, poses


def _unit(v):
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _seen_from(g, c2w):
    return sh_to_rgb(g.sh, g.means, c2w[:3, 3])


def test_own_view_exact_and_other_view_pulled():
    g, ranges, poses = _scene((0.8, 0.2, 0.2), (0.2, 0.2, 0.8))
    fit = fit_view_colour(g, ranges, poses, GRIDS)
    assert fit.sh.shape == (len(g), 4, 3) and np.isfinite(fit.sh).all()
    n = len(g) // 2
    for v, sl in enumerate((slice(0, n), slice(n, None))):
        own = sh_dc_to_rgb(g.sh[sl, 0])
        np.testing.assert_allclose(_seen_from(fit, poses[v])[sl], own, atol=1e-5)
        # from the other camera every surface of the box is seen: the colour moves towards the other tint
        # by |dd|^2 / (|dd|^2 + ridge) of the difference (ridge formula)
        other = sh_dc_to_rgb(g.sh[n:, 0] if v == 0 else g.sh[:n, 0])[0]  # the other view's (constant) tint
        x = g.means[sl].astype(np.float64)
        dd = _unit(x - poses[1 - v, :3, 3]) - _unit(x - poses[v, :3, 3])
        k = np.sum(dd * dd, axis=1) / (np.sum(dd * dd, axis=1) + VIEW_COLOUR_RIDGE)
        np.testing.assert_allclose(_seen_from(fit, poses[1 - v])[sl], own + k[:, None] * (other - own), atol=1e-4)
        assert k.max() > 0.05  # the test box gives directions that differ


def test_chunks_give_the_one_pass_fit(monkeypatch):
    """The fit runs chunk by chunk of Gaussians; chunks of any size (an uneven last one too) give every
    Gaussian the bits of one pass."""
    g, ranges, poses = _scene((0.8, 0.2, 0.2), (0.2, 0.2, 0.8))
    rng = np.random.default_rng(4)
    g = g.with_(sh=rng.normal(0.0, 0.5, g.sh.shape).astype(np.float32))  # a different colour per Gaussian
    hidden = rng.random(ranges.shape) < 0.1
    monkeypatch.setattr(view_colour, "CHUNK", len(g))
    whole = fit_view_colour(g, ranges, poses, GRIDS, hidden=hidden).sh
    for size in (7, 500):
        monkeypatch.setattr(view_colour, "CHUNK", size)
        np.testing.assert_array_equal(fit_view_colour(g, ranges, poses, GRIDS, hidden=hidden).sh, whole)


def test_hidden_from_the_other_view_keeps_one_colour():
    g, ranges, poses = _scene((0.8, 0.2, 0.2), (0.2, 0.2, 0.8))
    far = ranges.copy()
    far[1] *= 0.5  # view B "sees" a surface at half the range: view A's Gaussians are behind it
    fit = fit_view_colour(g, far, poses, GRIDS)
    n = len(g) // 2
    np.testing.assert_array_equal(fit.sh[:n, 1:], 0.0)
    np.testing.assert_allclose(fit.sh[:n, 0], g.sh[:n, 0], atol=1e-6)
    assert np.abs(fit.sh[n:, 1:]).max() > 0.01  # B's Gaussians are in front of A's range: fitted


def test_render_at_each_reference_shows_its_own_colours():
    size = (24, 72)
    tint_a, tint_b = (0.8, 0.3, 0.2), (0.2, 0.3, 0.8)
    g, ranges, poses = _scene(tint_a, tint_b, offset=1.0, size=size)  # 2 m apart in a 4 m room
    fit = fit_view_colour(g, ranges, poses, GRIDS)
    for c2w, tint in zip(poses, (tint_a, tint_b)):
        one = render(g, c2w, projection="erp", width=128, method="direct")
        vd = render(fit, c2w, projection="erp", width=128, method="direct")
        assert (vd.alpha > 0.99).mean() > 0.99
        err_one = np.abs(one.colour - tint).mean()
        err_vd = np.abs(vd.colour - tint).mean()
        # one colour per Gaussian mixes the two tints (0.21 mean error); the fit leaves 0.08 (the ridge
        # keeps part of the other tint where the two directions are close)
        assert err_one > 0.15 and err_vd < 0.5 * err_one


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(0.0, 1.0), min_size=6, max_size=6), st.floats(1e-4, 1.0))
def test_dc_in_range_and_swing_bounded(colours, offset):
    """The DC band is a convex blend of the two views' colours (a viewer storing it as 8-bit loses nothing)
    and no viewing direction swings further than |c_u - c_v| / (2 sqrt(ridge)) from it; also for
    near-coincident cameras (offset down to 1e-4 of the room)."""
    g, ranges, poses = _scene(colours[:3], colours[3:], offset=offset)
    fit = fit_view_colour(g, ranges, poses, GRIDS)
    dc = sh_dc_to_rgb(fit.sh[:, 0])
    assert np.isfinite(fit.sh).all()
    assert dc.min() >= -1e-5 and dc.max() <= 1 + 1e-5
    rng = np.random.default_rng(0)
    swing = np.abs(np.subtract(colours[:3], colours[3:])).max() / (2 * np.sqrt(VIEW_COLOUR_RIDGE))
    for _ in range(3):
        eye = rng.normal(size=3) * 0.5
        rgb = sh_to_rgb(fit.sh, fit.means, eye)
        assert np.abs(rgb - np.maximum(dc, 0)).max() <= swing + 1e-4


def test_gaussian_at_a_camera_and_bad_layouts():
    g, ranges, poses = _scene((0.5, 0.5, 0.5), (0.1, 0.9, 0.1))
    means = g.means.copy()
    means[0] = poses[1, :3, 3]  # a Gaussian at the other camera's centre
    means[1] = poses[0, :3, 3]  # and one at its own
    fit = fit_view_colour(g.with_(means=means), ranges, poses, GRIDS)
    assert np.isfinite(fit.sh).all()
    with pytest.raises(ValueError, match="two views"):
        fit_view_colour(g.subset(np.arange(len(g) - 1)), ranges, poses, GRIDS)
    with pytest.raises(ValueError, match="ridge"):
        fit_view_colour(g, ranges, poses, GRIDS, ridge=0.0)
