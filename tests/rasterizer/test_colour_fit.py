"""The closed-form colour-fit step: its local composite is the rasterizer's, it brings each reference's own
render closer to its image, and it leaves colours finite and in [0, 1] on extreme inputs."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.ndimage import gaussian_filter

from rasterizer import colour_fit
from rasterizer.camera import DEFAULT_NEAR, Camera
from rasterizer.colour_fit import check_colour_fit, fit_reference_colours, own_view_render
from rasterizer.depth_gaussians import gaussians_from_depth
from rasterizer.gaussians import Gaussians, sh_dc_to_rgb
from rasterizer.render import render
from rasterizer.splat import project
from tests.rasterizer._support import box_range, pose_at

H, W = 32, 96  # one Yin/Yang grid
GRIDS = ("yin", "yang")


def _texture(seed, size=(H, W)):
    """Pixel colours with detail a few pixels wide (as in photographs), so that the footprints' blur shows."""
    noise = gaussian_filter(np.random.default_rng(seed).random((*size, 3)), (1.0, 1.0, 0))
    return (0.5 + 0.35 * (noise - noise.mean()) / np.abs(noise - noise.mean()).max()).astype(np.float32)


def _scene(opacity=0.99, scale_factor=0.7, offset=0.3, size=(H, W), turn=(0.0, 0.0)):
    """Two references in a textured box room, turned by ``turn`` (yaw, pitch) radians: (layout, images
    (2, G, H, W, 3), poses)."""
    poses = np.stack([pose_at([0.0, 0.0, -offset]), pose_at([0.0, 0.2, offset])])
    yaw, pitch = turn
    rot_y = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
    rot_x = np.array([[1, 0, 0], [0, np.cos(pitch), -np.sin(pitch)], [0, np.sin(pitch), np.cos(pitch)]])
    poses[:, :3, :3] = rot_y @ rot_x
    images = np.stack([[_texture(3 * v + gi, size) for gi in range(len(GRIDS))] for v in range(2)])
    parts = [gaussians_from_depth(images[v, gi], box_range(k, poses[v], size=size), poses[v], k, surfels=True,
                                  opacity=opacity, scale_factor=scale_factor)
             for v in range(2) for gi, k in enumerate(GRIDS)]
    return Gaussians.concatenate(parts), images, poses


def _own_yin_psnr(g, images, poses, v, grids_used):
    """PSNR of the full rasterizer's Yin render of reference v's own Gaussians (of the first ``grids_used``
    grids) against v's Yin image."""
    n1 = H * W
    own = g.subset(np.arange(2 * v * n1, (2 * v + grids_used) * n1))
    colour = render(own, poses[v], projection="yin", width=W).colour
    return 10 * np.log10(1.0 / np.mean((colour - images[v, 0]) ** 2))


def test_own_view_render_is_the_rasterizer_within_the_window():
    g, images, poses = _scene()
    n1 = H * W
    own = g.subset(np.arange(0, 2 * n1))
    colours = sh_dc_to_rgb(own.sh[:, 0])
    local, cover = own_view_render(own, colours, poses[0], GRIDS, H, W, taps=5)
    for gi, kind in enumerate(GRIDS):
        part = own.subset(np.arange(gi * n1, (gi + 1) * n1))
        full = render(part, poses[0], projection=kind, width=W)
        got = local[gi * n1:(gi + 1) * n1].reshape(H, W, 3)
        inner = (slice(2, -2), slice(2, -2))  # the grid's border pixels miss neighbours beyond it
        assert np.abs(got[inner] - full.colour[inner]).max() < 0.01
        assert np.abs(cover[gi * n1:(gi + 1) * n1].reshape(H, W)[inner] - full.alpha[inner]).max() < 0.01
    assert cover.min() > 0.9  # opaque surfels close the surface
    # a 3 x 3 window misses the tails of 0.7-step surfels, and a 1 x 1 window is no composite at all
    narrow = np.abs(own_view_render(own, colours, poses[0], GRIDS, H, W, taps=3)[0] - local).mean()
    single = np.abs(own_view_render(own, colours, poses[0], GRIDS, H, W, taps=1)[0] - local).mean()
    assert narrow < 0.03 < single


def _sorted_window_composite(g, colours, pose, kind, taps):
    """own_view_render of one grid written directly: each pixel's taps x taps window of neighbours'
    alphas sorted by range with a stable sort, running transmittance product (cumprod) front to back."""
    r = taps // 2
    proj = project(g, Camera(kind, W, H, pose, near=DEFAULT_NEAR))
    k = proj.index
    par = np.zeros((6, H + 2 * r, W + 2 * r), dtype=np.float32)
    dist = np.full((H + 2 * r, W + 2 * r), np.inf)
    rows, cols = r + k // W, r + k % W
    par[0, rows, cols], par[1, rows, cols] = proj.mean[:, 0] - k % W, proj.mean[:, 1] - k // W
    par[2:5, rows, cols] = proj.conic.T
    par[5, rows, cols] = g.opacities[k]
    dist[rows, cols] = proj.ranges
    col = np.pad(colours.reshape(H, W, 3).astype(np.float32), ((r, r), (r, r), (0, 0)))
    alpha, rng, rgb = [], [], []
    for di in range(-r, r + 1):
        for dj in range(-r, r + 1):
            q = par[:, r + di:r + di + H, r + dj:r + dj + W]
            dx, dy = -dj - q[0], -di - q[1]
            a = np.minimum(q[5] * np.exp(np.float32(-0.5) * (q[2] * dx * dx + 2 * q[3] * dx * dy + q[4] * dy * dy)),
                           np.float32(0.99))
            alpha.append(np.where(a >= np.float32(1 / 255), a, np.float32(0)))
            rng.append(dist[r + di:r + di + H, r + dj:r + dj + W])
            rgb.append(col[r + di:r + di + H, r + dj:r + dj + W])
    alpha, rng, rgb = np.stack(alpha, -1), np.stack(rng, -1), np.stack(rgb, -2)
    order = np.argsort(rng, axis=-1, kind="stable")
    front = np.take_along_axis(alpha, order, axis=-1)
    trans = np.cumprod(1 - front, axis=-1)
    front[..., 1:] *= trans[..., :-1]
    weight = np.take_along_axis(front, np.argsort(order, axis=-1), axis=-1)
    return (weight[..., None] * rgb).sum(axis=-2).reshape(-1, 3), (1 - trans[..., -1]).reshape(-1)


def test_own_view_render_sorts_each_window_front_to_back_ties_in_window_order():
    g, _, poses = _scene()
    n1 = H * W
    own = g.subset(np.arange(0, 2 * n1))
    means = own.means.copy()
    means[1:n1:2] = means[0:n1:2]  # pairs of Yin neighbours at one point: equal ranges, the window order decides
    means[n1 + 5:2 * n1:7] *= 3.0  # Yang Gaussians far behind their neighbours
    own = own.with_(means=means)
    colours = sh_dc_to_rgb(own.sh[:, 0])
    for taps in (3, 5):
        local, cover = own_view_render(own, colours, poses[0], GRIDS, H, W, taps=taps)
        for gi, kind in enumerate(GRIDS):
            part = slice(gi * n1, (gi + 1) * n1)
            want, want_cover = _sorted_window_composite(own.subset(np.arange(gi * n1, (gi + 1) * n1)), colours[part],
                                                        poses[0], kind, taps)
            np.testing.assert_allclose(local[part], want, atol=1e-6)
            np.testing.assert_array_equal(cover[part], want_cover)


def test_culled_gaussians_leave_their_pixels_to_the_neighbours():
    """Gaussians the projection culls (here: at the camera, nearer than the near plane) add nothing: the
    composite of the rest is the direct one's."""
    g, _, poses = _scene()
    n1 = H * W
    own = g.subset(np.arange(0, 2 * n1))
    means = own.means.copy()
    means[::11] = poses[0, :3, 3]
    own = own.with_(means=means)
    colours = sh_dc_to_rgb(own.sh[:, 0])
    local, cover = own_view_render(own, colours, poses[0], GRIDS, H, W, taps=3)
    for gi, kind in enumerate(GRIDS):
        part = slice(gi * n1, (gi + 1) * n1)
        sub = own.subset(np.arange(gi * n1, (gi + 1) * n1))
        assert project(sub, Camera(kind, W, H, poses[0], near=DEFAULT_NEAR)).index.size < n1
        want, want_cover = _sorted_window_composite(sub, colours[part], poses[0], kind, 3)
        np.testing.assert_allclose(local[part], want, atol=1e-6)
        np.testing.assert_array_equal(cover[part], want_cover)


def test_bands_give_the_one_pass_composite(monkeypatch):
    """The window composite runs band by band of rows; bands of any height (one row, an uneven last band)
    give every pixel the bits of one pass over the grid."""
    g, _, poses = _scene()
    own = g.subset(np.arange(0, 2 * H * W))
    colours = sh_dc_to_rgb(own.sh[:, 0])
    monkeypatch.setattr(colour_fit, "BAND_PIXELS", H * W)
    whole = own_view_render(own, colours, poses[0], GRIDS, H, W, taps=5)
    for rows in (1, 5, H - 1):
        monkeypatch.setattr(colour_fit, "BAND_PIXELS", rows * W)
        banded = own_view_render(own, colours, poses[0], GRIDS, H, W, taps=5)
        np.testing.assert_array_equal(banded[0], whole[0])
        np.testing.assert_array_equal(banded[1], whole[1])


def test_the_step_brings_each_own_render_closer_to_its_image():
    g, images, poses = _scene(scale_factor=0.4)  # the head's confident surfels
    fit = fit_reference_colours(g, np.ones((2, 2, H, W)), poses, GRIDS)
    for v in range(2):
        # the Yin grid's own Gaussians, which the step models, and both grids, whose overlap it does not
        assert _own_yin_psnr(fit, images, poses, v, 1) > _own_yin_psnr(g, images, poses, v, 1) + 3.0
        assert _own_yin_psnr(fit, images, poses, v, 2) > _own_yin_psnr(g, images, poses, v, 2) + 0.3
    assert fit.sh.shape == g.sh.shape
    np.testing.assert_array_equal(fit.means, g.means)
    np.testing.assert_array_equal(fit.opacities, g.opacities)


def test_zero_strength_or_confidence_keeps_the_colours():
    g, _, poses = _scene()
    assert fit_reference_colours(g, np.ones((2, 2, H, W)), poses, GRIDS, strength=0) is g
    same = fit_reference_colours(g, np.zeros((2, 2, H, W)), poses, GRIDS)
    np.testing.assert_allclose(sh_dc_to_rgb(same.sh[:, 0]), sh_dc_to_rgb(g.sh[:, 0]), atol=1e-6)
    half = np.ones((2, 2, H, W))
    half[0] = 0.0  # only reference 1 confident: reference 0 keeps its colours
    part = fit_reference_colours(g, half, poses, GRIDS)
    n = len(g) // 2
    np.testing.assert_allclose(sh_dc_to_rgb(part.sh[:n, 0]), sh_dc_to_rgb(g.sh[:n, 0]), atol=1e-6)
    assert np.abs(sh_dc_to_rgb(part.sh[n:, 0]) - sh_dc_to_rgb(g.sh[n:, 0])).max() > 0.05


@settings(max_examples=12, deadline=None)
@given(opacity=st.sampled_from([1e-6, 1e-3, 0.02, 0.5, 0.99, 1.0]),
       scale_factor=st.sampled_from([1e-4, 0.05, 0.7, 5.0, 50.0]),
       strength=st.sampled_from([0.5, 1.5, 10.0]))
def test_colours_stay_finite_and_in_range(opacity, scale_factor, strength):
    g, _, poses = _scene(opacity=opacity, scale_factor=scale_factor, size=(8, 24))
    fit = fit_reference_colours(g, np.ones((2, 2, 8, 24)), poses, GRIDS, strength=strength)
    rgb = sh_dc_to_rgb(fit.sh[:, 0])
    assert np.isfinite(fit.sh).all()
    assert rgb.min() >= -1e-6 and rgb.max() <= 1 + 1e-6
    if opacity * 0.99 < 1 / 255:  # no footprint reaches the compositor's alpha floor: nothing to fit
        np.testing.assert_allclose(rgb, sh_dc_to_rgb(g.sh[:, 0]), atol=1e-6)


def test_gaussians_at_the_camera_or_culled_keep_their_colours():
    g, _, poses = _scene(size=(8, 24))
    n1 = 8 * 24
    means = g.means.copy()
    means[:n1] = poses[0, :3, 3]  # reference 0's Yin Gaussians at its camera centre: culled by the near test
    g = g.with_(means=means)
    fit = fit_reference_colours(g, np.ones((2, 2, 8, 24)), poses, GRIDS)
    assert np.isfinite(fit.sh).all()
    np.testing.assert_allclose(sh_dc_to_rgb(fit.sh[:n1, 0]), sh_dc_to_rgb(g.sh[:n1, 0]), atol=1e-6)


@pytest.mark.parametrize("bad", [-0.1, float("nan"), float("inf"), True, "1", None])
def test_check_colour_fit_refuses_what_is_not_a_strength(bad):
    with pytest.raises(ValueError, match="colour_fit"):
        check_colour_fit(bad)
    assert check_colour_fit(0) == 0.0 and check_colour_fit(1.5) == 1.5


def test_shapes_are_checked():
    g, _, poses = _scene(size=(8, 24))
    with pytest.raises(ValueError, match="two views"):
        fit_reference_colours(g, np.ones((2, 2, 8, 25)), poses, GRIDS)
    with pytest.raises(ValueError, match="taps"):
        own_view_render(g.subset(np.arange(2 * 8 * 24)), np.zeros((2 * 8 * 24, 3)), poses[0], GRIDS, 8, 24, taps=2)


@pytest.mark.parametrize("scale", [1e-3, 1e3])
def test_a_scaled_scene_gets_the_same_colours(scale):
    # cameras turned off the box's axes: a wall facing a camera square-on gives neighbours at equal ranges,
    # whose compositing order (a near-tie) rounding may flip once the scene is scaled
    g, _, poses = _scene(size=(8, 24), turn=(0.13, 0.07))
    conf = np.full((2, 2, 8, 24), 0.8)
    small_poses = poses.copy()
    small_poses[:, :3, 3] *= scale
    small = g.with_(means=g.means * scale, scales=g.scales * scale)
    diff = np.abs(fit_reference_colours(small, conf, small_poses, GRIDS).sh
                  - fit_reference_colours(g, conf, poses, GRIDS).sh).max(axis=(1, 2))
    # the same colours up to near-ties in range, where the box's walls meet: float32 means scaled round
    # differently, and the compositing order of two surfels at one range flips (as it would in a render)
    assert np.median(diff) < 1e-5 and np.mean(diff > 2e-3) < 0.05, (np.median(diff), np.mean(diff > 2e-3))


def test_coincident_cameras_are_refused():
    g, _, poses = _scene(size=(8, 24))
    with pytest.raises(ValueError, match="centres"):
        fit_reference_colours(g, np.ones((2, 2, 8, 24)), np.stack([poses[0], poses[0]]), GRIDS)
