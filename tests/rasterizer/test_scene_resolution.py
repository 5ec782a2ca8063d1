"""Rendering at the scene's own resolution: the same rays, close to the full-size rasterisation, exact where fine."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rasterizer import geometry as geo
from rasterizer.camera import Camera
from rasterizer.render import render
from rasterizer.scene_resolution import FULL_ABOVE, MIN_SCALE, reduced_pinhole, render_scale, resize_pinhole
from tests.rasterizer._support import forward_scene, pose_at, toy_scene


def _psnr(a, b):
    return -10.0 * np.log10(np.mean((np.clip(a, 0, 1) - np.clip(b, 0, 1)) ** 2))


@pytest.mark.parametrize("size,scale", [((320, 240), 0.4), ((101, 77), 0.33), ((64, 64), 0.5)])
def test_resize_samples_the_same_rays(size, scale):
    """A coarse image of each pixel's ray slopes, resized, gives the fine camera's slopes (bilinear is exact on them)."""
    cam = Camera("perspective", *size, np.eye(4), fov_deg=80.0)
    coarse = reduced_pinhole(cam, scale)
    assert coarse.width == round(size[0] * scale) and coarse.fov_deg == cam.fov_deg
    rays = geo.pinhole_directions(coarse.width, coarse.height, coarse.fov_deg)
    slopes = (rays[:, :, :2] / rays[:, :, 2:]).astype(np.float32)
    fine = resize_pinhole(slopes, cam.width, cam.height)
    want = geo.pinhole_directions(cam.width, cam.height, cam.fov_deg)
    want = want[:, :, :2] / want[:, :, 2:]
    # inside the coarse grid's outermost pixel centres (beyond them the border pixel is repeated)
    inner = np.abs(want[:, :, 0]) <= np.abs(slopes[0, 0, 0])
    inner &= np.abs(want[:, :, 1]) <= np.abs(slopes[0, 0, 1])
    assert inner.mean() > 0.8
    np.testing.assert_allclose(fine[inner], want[inner], atol=1e-5)


def test_cubic_resize_is_exact_on_quadratics_inside_and_keeps_constants_everywhere():
    """Catmull-Rom reproduces a quadratic of the coarse pixel position away from the border (two pixels in),
    gives a constant image back unchanged everywhere, and returns the coarse pixels where the grids' samples
    coincide (an interpolating kernel)."""
    h, w = 31, 47
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    quad = (0.02 * xx * xx - 0.3 * xx * yy / w + 0.5 * yy + 1.0).astype(np.float32)[:, :, None]
    width, height = 2 * w + 1, 2 * h + 1  # s = w / width: samples at (c - w) * s + (w - 1) / 2
    out = resize_pinhole(quad, width, height, kernel="cubic")[:, :, 0]
    s = w / width
    x = (np.arange(width) - (width - 1) / 2.0) * s + (w - 1) / 2.0
    y = (np.arange(height) - (height - 1) / 2.0) * s + (h - 1) / 2.0
    Y, X = np.meshgrid(y, x, indexing="ij")
    want = 0.02 * X * X - 0.3 * X * Y / w + 0.5 * Y + 1.0
    inner = (X >= 2) & (X <= w - 3) & (Y >= 2) & (Y <= h - 3)
    assert inner.mean() > 0.7
    np.testing.assert_allclose(out[inner], want[inner], rtol=2e-5, atol=2e-5)
    flat = np.full((9, 13, 3), 0.37, dtype=np.float32)
    np.testing.assert_allclose(resize_pinhole(flat, 40, 27, kernel="cubic"), 0.37, rtol=1e-6)
    img = np.random.default_rng(2).random((10, 12, 2)).astype(np.float32)
    same = resize_pinhole(img, 12, 10, kernel="cubic")  # scale 1: every sample on a pixel centre
    np.testing.assert_allclose(same, img, atol=1e-6)
    with pytest.raises(ValueError, match="kernel"):
        resize_pinhole(img, 12, 10, kernel="lanczos")


def _detail(colour):
    """Mean |luma - its 5x5 box mean|: the high-frequency energy of conventions section 6's sharpness."""
    from scipy.ndimage import uniform_filter

    y = np.clip(colour, 0, 1) @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
    return float(np.abs(y - uniform_filter(y, 5, mode="nearest")).mean())


def test_a_reduced_render_keeps_the_full_size_edges():
    """A wall of small opaque tiles of random colours, rendered a third as fine and resized: the colour's
    Catmull-Rom keeps 0.8 of the full-size render's high-frequency energy (bilinear kept 0.74), never
    goes negative, and stays within 30 dB of the full size."""
    from tests.rasterizer._support import make_gaussians

    u, v = np.meshgrid(np.linspace(-1.5, 1.5, 60), np.linspace(-1.0, 1.0, 40))
    means = np.stack([u.ravel(), v.ravel(), np.full(u.size, 2.0)], 1)
    n = len(means)
    g = make_gaussians(means, np.tile([0.03, 0.03, 0.003], (n, 1)), np.tile([1.0, 0, 0, 0], (n, 1)),
                       np.full(n, 0.95), np.random.default_rng(7).uniform(0, 1, (n, 3)))
    kw = dict(projection="perspective", width=480, height=320, fov_deg=90.0)
    assert render_scale(g, Camera("perspective", 480, 320, np.eye(4), fov_deg=90.0)) == MIN_SCALE
    exact, scene = render(g, np.eye(4), **kw).colour, render(g, np.eye(4), resolution="scene", **kw).colour
    assert _detail(scene) >= 0.8 * _detail(exact)
    assert scene.min() >= 0.0 and np.all(np.isfinite(scene))
    assert _psnr(scene, exact) >= 30.0


def test_coarse_gaussians_render_on_a_coarser_grid_close_to_exact():
    """Large Gaussians (a room of 0.35 m blobs) seen at a fine pitch: a reduced grid, within 40 dB of the full size."""
    g = toy_scene(seed=3)
    c2w = pose_at([0.2, 0.1, 0.0])
    for kw in (dict(projection="perspective", width=320, height=240, fov_deg=90.0), dict(projection="erp", width=512)):
        cam = Camera("yin", 3 * 128, 128, c2w) if kw["projection"] == "erp" else Camera(
            "perspective", kw["width"], kw["height"], c2w, fov_deg=kw["fov_deg"])
        scale = render_scale(g, cam)
        assert MIN_SCALE <= scale < FULL_ABOVE
        exact = render(g, c2w, **kw)
        scene = render(g, c2w, resolution="scene", **kw)
        assert scene.colour.shape == exact.colour.shape and scene.colour.dtype == np.float32
        assert np.all(np.isfinite(scene.colour)) and np.all(np.isfinite(scene.range))
        assert _psnr(scene.colour, exact.colour) >= 40.0
        assert np.abs(scene.alpha - exact.alpha).mean() < 0.01


def test_fine_gaussians_render_exactly():
    """Footprints of about a pixel already: the scene resolution is the full size, and the image is the exact one."""
    g = forward_scene(np.random.default_rng(5), n=400)
    g = g.with_(scales=g.scales * 0.05)
    cam = Camera("perspective", 96, 64, np.eye(4), fov_deg=70.0)
    assert render_scale(g, cam) == 1.0
    kw = dict(projection="perspective", width=96, height=64, fov_deg=70.0)
    exact, scene = render(g, np.eye(4), **kw), render(g, np.eye(4), resolution="scene", **kw)
    np.testing.assert_array_equal(scene.colour, exact.colour)


def test_no_visible_gaussian_renders_full_size():
    g = forward_scene(np.random.default_rng(1), n=20)
    behind = np.diag([1.0, 1.0, -1.0, 1.0])
    behind[0, 0] = -1.0  # looking along -z: every Gaussian is behind the camera
    assert render_scale(g, Camera("perspective", 64, 48, behind)) == 1.0
    out = render(g, behind, projection="perspective", width=64, height=48, resolution="scene")
    assert out.alpha.max() == 0.0


def test_unknown_resolution_is_refused():
    with pytest.raises(ValueError, match="resolution"):
        render(toy_scene(), np.eye(4), width=64, resolution="half")


@settings(max_examples=40, deadline=None)
@given(width=st.integers(1, 80), height=st.integers(1, 80), fov=st.floats(5.0, 170.0),
       scale=st.floats(MIN_SCALE, FULL_ABOVE))
def test_any_size_resizes_to_the_requested_size(width, height, fov, scale):
    """Odd, tiny and tall sizes: the coarse grid is at least 2x2 and the resized image has the requested size."""
    g = toy_scene(seed=1, n=80)
    cam = Camera("perspective", width, height, np.eye(4), fov_deg=fov)
    coarse = reduced_pinhole(cam, scale)
    assert coarse.width >= 2 and coarse.height >= 2
    img = render(g, np.eye(4), projection="perspective", width=coarse.width, height=coarse.height, fov_deg=fov)
    out = resize_pinhole(np.dstack([img.colour, img.alpha]), width, height)
    assert out.shape == (height, width, 4) and np.all(np.isfinite(out))
    assert out.min() >= 0.0 and out[:, :, 3].max() <= 1.0


@pytest.mark.parametrize("kind", ["yin", "yang"])
def test_sample_read_from_the_full_projection_equals_the_projected_sample(kind, monkeypatch):
    """A grid camera's sample of footprints read from the projection of all Gaussians (what a Yin-Yang
    render reuses) equals the sample projected on its own."""
    from rasterizer import scene_resolution, splat
    from rasterizer.splat.projection import project_columns
    from tests.rasterizer._support import pose, random_scene

    monkeypatch.setattr(scene_resolution, "SAMPLE", 700)
    rng = np.random.default_rng(4)
    g = random_scene(rng, 5000)
    cam = Camera(kind, 192, 64, pose(rng))
    alone = scene_resolution.footprint_sigmas(g, cam)
    shared = scene_resolution.footprint_sigmas(g, cam, project_columns(splat.shared_pose(g, cam), cam))
    assert 100 < alone.size < 700
    np.testing.assert_array_equal(np.sort(shared), np.sort(alone))


def _with_backdrop(seed: int = 3, n_back: int = 3000, radius: float = 30.0):
    """The toy room (Gaussians within ~3.5 of the origin) and, after it, a backdrop of wide opaque discs on a
    sphere of ``radius``: (Gaussians, backdrop count)."""
    from rasterizer.gaussians import Gaussians, rgb_to_sh_dc

    room = toy_scene(seed=seed)
    rng = np.random.default_rng(seed + 1)
    d = rng.standard_normal((n_back, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    back = Gaussians(d * radius, np.full((n_back, 3), 1.5), np.tile([1.0, 0, 0, 0], (n_back, 1)),
                     np.full(n_back, 0.99), rgb_to_sh_dc(rng.uniform(0.1, 0.9, (n_back, 3)))[:, None, :])
    return Gaussians.concatenate([room, back]), n_back


VIEWS = [dict(projection="perspective", width=320, height=240, fov_deg=90.0), dict(projection="erp", width=512)]


@pytest.mark.parametrize("kw", VIEWS, ids=["perspective", "erp"])
def test_backdrop_composited_under_the_rest_is_the_one_pass_image(kw):
    """Front to back split at a backdrop that lies behind everything: the rest's composite plus (1 - its alpha)
    times the backdrop's own composite is the one-pass image, at full size. Not to rounding: a pixel stops
    where its next contribution would take T below 1e-4, so with alphas up to 0.99 the one pass may leave up
    to 1% of a pixel to the background where the backdrop alone, starting at T = 1, goes on (and the ERP's
    Yin-Yang merge is linear in each part, not in their product)."""
    g, k = _with_backdrop()
    c2w = pose_at([0.3, -0.2, 0.1])
    n = len(g) - k
    one = render(g, c2w, normalize=False, **kw)
    front = render(g.subset(slice(0, n)), c2w, normalize=False, **kw)
    back = render(g.subset(slice(n, len(g))), c2w, normalize=False, **kw)
    keep = 1.0 - front.alpha
    colour = front.colour + keep[:, :, None] * back.colour
    alpha = front.alpha + keep * back.alpha
    np.testing.assert_allclose(colour, one.colour, atol=0.01)
    np.testing.assert_allclose(alpha, one.alpha, atol=0.01)
    assert np.abs(colour - one.colour).mean() < 2e-4 and np.abs(alpha - one.alpha).mean() < 2e-4


@pytest.mark.parametrize("kw", VIEWS, ids=["perspective", "erp"])
def test_backdrop_at_its_own_resolution_is_close_to_one_pass(kw):
    """The API's path (resolution "scene", the shell as backdrop): each part at its own resolution, within 45 dB
    of the one-pass scene render, alpha within 0.01; exact renders and counts outside 1..N-1 ignore it."""
    g, k = _with_backdrop()
    c2w = pose_at([0.3, -0.2, 0.1])
    for normalize in (False, True):
        one = render(g, c2w, normalize=normalize, resolution="scene", **kw)
        two = render(g, c2w, normalize=normalize, resolution="scene", backdrop=k, **kw)
        assert two.colour.shape == one.colour.shape and two.colour.dtype == np.float32
        assert np.all(np.isfinite(two.colour)) and np.all(np.isfinite(two.range))
        assert not np.array_equal(two.colour, one.colour)  # rendered apart, not ignored
        assert _psnr(two.colour, one.colour) >= 45.0
        assert np.abs(two.alpha - one.alpha).max() < 0.01
        rel = np.abs(two.range - one.range) / np.maximum(one.range, 1e-6)
        assert np.median(rel) < 0.01  # the mean of a 3 m room and a 30 m backdrop moves with the 1% the stop rule leaves
    one_thread = render(g, c2w, resolution="scene", backdrop=k, threads=1, **kw)
    np.testing.assert_allclose(one_thread.colour, render(g, c2w, resolution="scene", backdrop=k, **kw).colour,
                               atol=1e-6)  # the backdrop in its own thread or in turn: the same image
    exact = render(g, c2w, **kw)
    np.testing.assert_array_equal(render(g, c2w, backdrop=k, **kw).colour, exact.colour)
    scene = render(g, c2w, resolution="scene", **kw)
    for count in (0, len(g), -1):
        np.testing.assert_array_equal(render(g, c2w, resolution="scene", backdrop=count, **kw).colour, scene.colour)
