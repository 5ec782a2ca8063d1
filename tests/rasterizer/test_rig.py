"""The capture rig: pixels near each camera's nadir take the other view's colour (rasterizer.rig)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rasterizer.camera import camera_directions
from rasterizer.gaussians import Gaussians, rgb_to_sh_dc, sh_dc_to_rgb
from rasterizer.geometry import grid_directions
from rasterizer.rig import (
    AUTO_RIG_CAP_DEG,
    MAX_RIG_CAP_DEG,
    RIG_DETECT_MAX_DIFF,
    RIG_LAYER_CAP_DEG,
    NoRigError,
    RigLayer,
    check_rig_cap,
    overlay_rig,
    patch_rig,
    require_rig_layer,
    resolve_rig_cap,
    rig_agreement,
    rig_layer,
    rig_mask,
    rig_summary,
)
from rasterizer.scene_folder import load_scene
from rasterizer.view_colour import fit_view_colour

GRIDS, H, W = ("yin", "yang"), 24, 72
LO, HI = np.array([-3.0, -2.0, -3.0]), np.array([4.0, 1.5, 3.0])  # a box room; the floor is y = 1.5 (down)


def _box_range(centre, rays):
    """Range from ``centre`` inside the box along unit ``rays`` (..., 3)."""
    with np.errstate(divide="ignore"):
        t = np.where(rays > 0, (HI - centre) / rays, (LO - centre) / rays)
    return np.min(np.where(rays != 0, t, np.inf), axis=-1)


def _colour(x):
    """A smooth colour of world points (..., 3), so that both views agree on every surface."""
    return np.clip(0.5 + 0.4 * np.sin(1.3 * x[..., [0, 1, 2]] + np.array([0.0, 1.0, 2.0])), 0, 1)


def _layout(cap_deg, offset=(1.0, 0.0, 0.0)):
    """Two upright cameras ``offset`` apart; each one's image shows a dark rig within ``cap_deg`` of its nadir."""
    rays = np.stack([grid_directions(g, H, W) for g in GRIDS])
    c2w = np.stack([np.eye(4), np.eye(4)])
    c2w[1, :3, 3] = offset
    means, colours, ranges = [], [], []
    rig = rig_mask(GRIDS, H, W, cap_deg)
    for v in range(2):
        r = _box_range(c2w[v, :3, 3], rays)
        x = c2w[v, :3, 3] + r[..., None] * rays
        col = np.where(rig[..., None], 0.05, _colour(x))
        means.append(x.reshape(-1, 3))
        colours.append(col.reshape(-1, 3))
        ranges.append(r)
    n = 2 * len(means[0])
    g = Gaussians(np.concatenate(means).astype(np.float32), np.full((n, 3), 0.01, np.float32),
                  np.tile(np.float32([1, 0, 0, 0]), (n, 1)), np.full(n, 0.99, np.float32),
                  rgb_to_sh_dc(np.concatenate(colours))[:, None, :].astype(np.float32))
    return g, np.stack(ranges).astype(np.float32), c2w


def test_rig_mask_is_the_cap_around_the_camera_nadir():
    assert not rig_mask(GRIDS, H, W, 0.0).any()
    for grids in (GRIDS, ("erp",)):
        h, w = (H, W) if grids == GRIDS else (32, 64)
        rays = np.stack([grid_directions(g, h, w) for g in grids])
        angle = np.degrees(np.arccos(np.clip(rays[..., 1], -1, 1)))  # from camera +y (down)
        m = rig_mask(grids, h, w, 20.0)
        assert m.any() and np.all(angle[m] < 20.0) and np.all(angle[~m] >= 20.0)


@pytest.mark.parametrize("bad", [-1.0, MAX_RIG_CAP_DEG + 1, float("nan"), float("inf"), True, "20", "auto"])
def test_check_rig_cap_refuses_what_is_not_a_cap(bad):
    with pytest.raises(ValueError, match="rig_cap_deg"):
        check_rig_cap(bad)
    assert check_rig_cap(20) == 20.0 and check_rig_cap(0) == 0.0 and check_rig_cap(None) is None


def test_resolve_rig_cap_is_automatic_only_when_unset():
    assert resolve_rig_cap(None, True) == AUTO_RIG_CAP_DEG and resolve_rig_cap(None, False) == 0.0
    assert resolve_rig_cap(0, True) == 0.0 and resolve_rig_cap(12.5, False) == 12.5
    with pytest.raises(ValueError, match="automatic"):
        rig_mask(GRIDS, H, W, None)


def test_patch_rig_takes_the_other_views_colour_under_each_camera():
    g, rng, c2w = _layout(20.0)
    out, rig = patch_rig(g, rng, c2w, GRIDS, 20.0)
    n = len(g) // 2
    cap = np.tile(rig_mask(GRIDS, H, W, 20.0).ravel(), 2)
    np.testing.assert_array_equal(rig.reshape(-1), cap)
    np.testing.assert_array_equal(out.sh[~cap], g.sh[~cap])  # the rest of the scene is untouched
    np.testing.assert_array_equal(out.means, g.means)
    truth = _colour(g.means[cap].astype(np.float64))
    before = np.abs(sh_dc_to_rgb(g.sh[cap, 0]) - truth).mean()
    after = np.abs(sh_dc_to_rgb(out.sh[cap, 0]) - truth).mean()
    assert before > 0.3 and after < 0.05  # the floor under each camera, as the other camera saw it
    # no cap: nothing changes and nothing is hidden
    same, none = patch_rig(g, rng, c2w, GRIDS, 0.0)
    assert same is g and not none.any() and none.size == 2 * n


def test_hidden_rig_pixels_give_no_view_dependent_colour():
    g, rng, c2w = _layout(20.0)
    rig = np.stack([rig_mask(GRIDS, H, W, 20.0)] * 2)
    plain = fit_view_colour(g, rng, c2w, GRIDS)
    masked = fit_view_colour(g, rng, c2w, GRIDS, hidden=rig)
    band = np.abs(masked.sh[:, 1:]).max(axis=(1, 2))
    # a floor point under camera A that B's surfels carry is seen by A only through A's rig pixels
    n = len(g) // 2
    d = masked.means[n:] - c2w[0, :3, 3]
    under_a = np.degrees(np.arccos(np.clip(d[:, 1] / np.linalg.norm(d, axis=1), -1, 1))) < 15.0
    assert under_a.any() and np.all(band[n:][under_a] == 0)
    assert np.abs(plain.sh[n:][under_a, 1:]).max() > 0  # without the mask they would take the rig


@settings(max_examples=25, deadline=None)
@given(st.floats(0.0, MAX_RIG_CAP_DEG), st.tuples(*[st.floats(-1.5, 1.5)] * 3))
def test_patch_rig_stays_in_gamut_and_off_the_cap(cap_deg, offset):
    """Any cap and camera offset (down to coincident centres): finite colours in [0, 1], nothing else moves."""
    g, rng, c2w = _layout(cap_deg, offset)
    out, rig = patch_rig(g, rng, c2w, GRIDS, cap_deg)
    cap = rig.reshape(-1)
    rgb = sh_dc_to_rgb(out.sh[:, 0])
    assert np.all(np.isfinite(out.sh)) and rgb.min() >= -1e-5 and rgb.max() <= 1 + 1e-5
    np.testing.assert_array_equal(out.sh[~cap], g.sh[~cap])
    np.testing.assert_array_equal(out.means, g.means)


# -- the camera-attached rig layer -------------------------------------------------------------

RIG_RGB = np.float32([0.1, 0.08, 0.06])


def _nadir_deg(h, w):
    return np.degrees(np.arccos(np.clip(camera_directions("erp", h, w)[..., 1], -1, 1)))  # angle from +y


def _captures(seed_a, seed_b, disc_deg, h=64):
    """Two ERP captures with independent textures; both show a dark disc within ``disc_deg`` of the nadir."""
    imgs = [np.random.default_rng(s).uniform(0.2, 0.9, (h, 2 * h, 3)).astype(np.float32) for s in (seed_a, seed_b)]
    disc = _nadir_deg(h, 2 * h) < disc_deg
    for img in imgs:
        img[disc] = RIG_RGB
    return imgs


def test_rig_agreement_and_detection():
    a, b = _captures(1, 2, 15.0)
    assert rig_agreement(a, a) == 0.0
    assert rig_agreement(a, b) < 1e-6  # the disc covers the whole detection cap
    layer = rig_layer(a, b)
    assert layer is not None and layer.colour.shape == a.shape and layer.alpha.shape == a.shape[:2]
    bare_a, bare_b = _captures(1, 2, 0.0)  # no rig: independent textures under both cameras
    assert rig_agreement(bare_a, bare_b) > RIG_DETECT_MAX_DIFF
    assert rig_layer(bare_a, bare_b) is None
    with pytest.raises(NoRigError, match=r"no common capture rig .*mean difference 0\.\d+ > 0\.05"):
        require_rig_layer(bare_a, bare_b)
    u8 = [(np.clip(x, 0, 1) * 255).round().astype(np.uint8) for x in (a, b)]
    assert abs(rig_agreement(*u8) - rig_agreement(a, b)) < 0.01  # uint8 captures read as [0, 1]
    with pytest.raises(ValueError, match="one size"):
        rig_layer(a, b[:32, :64])


def test_rig_layer_is_the_rig_where_the_views_agree_and_nothing_above_its_cap():
    a, b = _captures(3, 4, 20.0)
    layer = rig_layer(a, b)
    nadir = _nadir_deg(*a.shape[:2])
    inner = nadir < 20.0 - 3 * 180 / a.shape[0]  # more than half a box (2 rows) inside the disc's edge
    assert np.all(layer.alpha[inner] == 1.0)
    np.testing.assert_allclose(layer.colour[inner], np.broadcast_to(RIG_RGB, layer.colour[inner].shape), atol=1e-6)
    assert np.all(layer.alpha[nadir > RIG_LAYER_CAP_DEG + 3.0] == 0.0)
    assert layer.alpha[(nadir > 25.0)].mean() < 0.05  # independent textures outside the disc disagree


@pytest.mark.parametrize("kind, h, w, fov", [("erp", 48, 96, 90.0), ("yang", 32, 96, 90.0),
                                            ("perspective", 41, 41, 170.0)])
def test_overlay_rig_paints_the_rig_at_the_render_cameras_own_nadir(kind, h, w, fov):
    layer = rig_layer(*_captures(5, 6, 20.0))  # opaque within ~11 deg: a box and a bilinear tap inside
    render = np.random.default_rng(7).uniform(0.3, 1.0, (h, w, 3)).astype(np.float32)
    d = camera_directions(kind, h, w, fov)
    out = overlay_rig(render, d, layer)
    from_nadir = np.degrees(np.arccos(np.clip(d[..., 1], -1, 1)))
    near, far = from_nadir < 8.0, from_nadir > RIG_LAYER_CAP_DEG + 5.0
    assert near.any() and far.any()
    np.testing.assert_allclose(out[near], np.broadcast_to(RIG_RGB, out[near].shape), atol=1e-5)
    np.testing.assert_array_equal(out[far], render[far])


def test_overlay_rig_leaves_a_forward_view_alone():
    layer = rig_layer(*_captures(5, 6, 15.0))
    render = np.random.default_rng(8).uniform(0, 1, (30, 40, 3)).astype(np.float32)
    out = overlay_rig(render, camera_directions("perspective", 30, 40, 90.0), layer)
    np.testing.assert_array_equal(out, render)  # the pinhole's lowest ray is 40+ deg above the rig's cap


@settings(max_examples=30, deadline=None)
@given(st.floats(0.0, 1.0), st.floats(0.0, 1.0), st.floats(0.0, 1.0))
def test_overlay_rig_is_a_convex_blend(alpha, layer_value, render_value):
    h, w = 8, 16
    layer = RigLayer(np.full((h, w, 3), layer_value, np.float32), np.full((h, w), alpha, np.float32), 0.0)
    render = np.full((5, 7, 3), render_value, np.float32)
    d = np.random.default_rng(0).normal(size=(5, 7, 3))
    out = overlay_rig(render, d / np.linalg.norm(d, axis=-1, keepdims=True), layer)
    assert np.all(np.isfinite(out))
    np.testing.assert_allclose(out, render_value * (1 - alpha) + layer_value * alpha, atol=1e-5)


def _pairs(scene_dir):
    scene = load_scene(scene_dir)
    return [(scene.frames[a].image(), scene.frames[b].image()) for a, b in (s.references for s in scene.splits)]


def test_dev_captures_tripod_is_detected_and_the_synthetic_scene_has_none(zind_dir, m3d_dir):
    """zind_room09 (a tripod under every pano) detects a rig at both splits; m3d_bedroom (rendered) none."""
    for a, b in _pairs(zind_dir):
        assert rig_agreement(a, b) < 0.5 * RIG_DETECT_MAX_DIFF
        layer = rig_layer(a, b)
        assert layer is not None and layer.alpha[_nadir_deg(*a.shape[:2]) < 3.0].mean() > 0.9
    for a, b in _pairs(m3d_dir):
        assert rig_agreement(a, b) > 1.5 * RIG_DETECT_MAX_DIFF and rig_layer(a, b) is None
        assert rig_summary(a, b)["detected"] is False
