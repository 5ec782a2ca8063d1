"""Renderer correctness: projection moments, compositing rules, seam, poles, Yin/Yang."""

import zlib

import numpy as np
import pytest

from rasterizer import geometry as geo
from rasterizer.camera import Camera
from rasterizer.composite import composite
from rasterizer.gaussians import Gaussians, covariance_from_scale_rotation, rgb_to_sh_dc
from rasterizer.render import RenderOutput, render, to_uint8
from rasterizer.splat import ALPHA_MIN, Q_MAX, footprints, polar_rows, project
from tests.rasterizer._support import forward_scene, make_gaussians, pose, random_scene, reference_composite


def truncation_factor(r2):
    """Second moment of a 2-D Gaussian truncated at Mahalanobis radius^2 r2, relative to untruncated."""
    e = np.exp(-r2 / 2)
    return 1 - (r2 / 2) * e / (1 - e)


def analytic_ellipse(kind, g, c2w, w, h, fov=90.0):
    """Independent projection: centre via geometry, covariance J Sigma J^T + 0.3 I."""
    p = geo.world_to_camera(g.means.astype(np.float64), c2w)
    if kind == "perspective":
        fx, fy, cx, cy = geo.pinhole_intrinsics(w, h, fov)
        col, row = geo.pinhole_project(p, fx, fy, cx, cy)
        jac = geo.pinhole_jacobian(p, fx, fy)
    else:
        col, row = geo.project_to_grid(kind, p, h, w)
        jac = geo.grid_jacobian(kind, p, h, w)
    jw = jac @ c2w[:3, :3].T
    cov = jw @ covariance_from_scale_rotation(g.scales, g.quats) @ np.swapaxes(jw, 1, 2) + 0.3 * np.eye(2)
    return np.array([col[0], row[0]]), cov[0]


def image_moments(a):
    h, w = a.shape
    r, c = np.mgrid[0:h, 0:w]
    s = a.sum()
    mc, mr = (a * c).sum() / s, (a * r).sum() / s
    cov = np.array([[(a * (c - mc) ** 2).sum(), (a * (c - mc) * (r - mr)).sum()],
                    [(a * (c - mc) * (r - mr)).sum(), (a * (r - mr) ** 2).sum()]]) / s
    return np.array([mc, mr]), cov


@pytest.mark.parametrize("kind,direction", [
    ("erp", (0.4, -0.3, 1.0)),
    ("erp", (-1.0, 0.5, -0.6)),
    ("yin", (0.5, 0.2, 1.0)),
    ("yang", (0.3, 0.9, -0.8)),
    ("perspective", (0.2, -0.1, 1.0)),
])
def test_single_gaussian_centre_and_second_moments_match_analytic_projection(kind, direction):
    rng = np.random.default_rng(zlib.crc32(repr((kind, direction)).encode()))
    c2w = pose(rng)
    d = np.asarray(direction) / np.linalg.norm(direction)
    mean_cam = 3.0 * d
    q = rng.normal(size=4)
    g = make_gaussians(c2w[:3, :3] @ mean_cam + c2w[:3, 3], [0.3, 0.15, 0.4], q / np.linalg.norm(q), 0.5)
    w, h = (384, 192) if kind == "erp" else (384, 128) if kind in ("yin", "yang") else (256, 192)
    out = render(g, c2w, projection=kind, width=w, height=h, method="direct")
    assert out.colour.shape == (h, w, 3) and out.alpha.shape == (h, w)
    centre, cov = analytic_ellipse(kind, g, c2w, w, h)
    assert cov[0, 0] > 4 and cov[1, 1] > 4  # resolved by many pixels
    # alpha = 0.5 g, cut where 0.5 g < 1/255: a Gaussian truncated at q = 2 ln(127.5)
    m_centre, m_cov = image_moments(out.alpha.astype(np.float64))
    assert np.allclose(m_centre, centre, atol=0.02)
    assert np.allclose(m_cov, cov * truncation_factor(2 * np.log(127.5)), rtol=0.01, atol=0.01)
    # colour is alpha * rgb over black, expected range is the centre's range
    assert np.allclose(out.colour, out.alpha[..., None] * 0.8, atol=1e-5)
    hit = out.alpha > 0
    assert np.allclose(out.range[hit], 3.0, rtol=1e-5) and np.all(out.range[~hit] == 0)


def test_yang_render_is_yin_render_of_the_yang_pose():
    rng = np.random.default_rng(3)
    g = random_scene(rng, 300)
    c2w = pose(rng)
    yang = render(g, c2w, projection="yang", width=192)
    yin = render(g, geo.yang_pose(c2w), projection="yin", width=192)
    assert yang.alpha.shape == (64, 192) and yang.alpha.max() > 0.5
    assert np.allclose(yang.colour, yin.colour, atol=1e-5)
    assert np.allclose(yang.alpha, yin.alpha, atol=1e-5)
    assert np.allclose(yang.range, yin.range, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("kind", ["perspective", "yin", "erp"])
def test_footprints_and_composite_match_a_slow_reference_loop(kind):
    n = 40
    g = forward_scene(np.random.default_rng(11), n)
    w, h = {"perspective": (24, 20), "yin": (36, 12), "erp": (48, 24)}[kind]
    cam = Camera(kind, w, h, np.eye(4))
    if kind == "erp":  # the reference is the pixel-space EWA: keep away from the polar path
        g = g.subset(np.flatnonzero(np.isin(np.arange(n), project(g, cam).index[polar_rows(project(g, cam), cam)[0]])))
        n = len(g)
        assert n > 25
    fp = footprints(g, cam)
    colours = g.rgb
    colour, alpha, rng_img = composite(fp, g.opacities, colours)
    pr = project(g, cam)
    full = np.zeros((n, 2))
    conic = np.full((n, 3), [1e9, 0, 1e9])
    ranges = np.zeros(n)
    full[pr.index], conic[pr.index], ranges[pr.index] = pr.mean, pr.conic, pr.ranges
    keep = np.zeros(n, bool)
    keep[pr.index] = True
    sel = np.flatnonzero(keep)
    # a pinhole camera sorts by camera-frame z, as 3DGS viewers do (the pose is the identity here)
    depth = g.means[:, 2] if kind == "perspective" else None
    ref = reference_composite(full[sel], conic[sel], ranges[sel], g.opacities[sel], colours[sel], w, h,
                              period=w if kind == "erp" else None, depths=None if depth is None else depth[sel])
    assert alpha.max() > 0.5
    assert np.allclose(colour, ref[0], atol=2e-5)
    assert np.allclose(alpha, ref[1], atol=2e-5)
    assert np.allclose(rng_img, ref[2], atol=1e-4)
    # each pixel lists its Gaussians front to back
    same = fp.pixel[1:] == fp.pixel[:-1]
    r = (fp.ranges if depth is None else depth)[fp.gaussian]
    assert np.all(np.diff(fp.pixel) >= 0) and np.all(r[1:][same] >= r[:-1][same])
    assert np.all((fp.weight >= ALPHA_MIN * 0.999) & (fp.weight <= 1))


def test_footprints_are_opacity_free_and_can_be_recomposited():
    rng = np.random.default_rng(5)
    g = random_scene(rng, 200)
    cam = Camera("erp", 96, 48, np.eye(4))
    fp = footprints(g, cam)  # no opacity bound: valid for any opacities
    new_op = rng.uniform(0, 1, len(g)).astype(np.float32)
    colour, alpha, rng_img = composite(fp, new_op, g.rgb)
    out = render(g.with_(opacities=new_op), np.eye(4), projection="erp", width=96, method="direct")
    assert np.allclose(colour, out.colour, atol=1e-5)
    assert np.allclose(alpha, out.alpha, atol=1e-5)


def test_erp_wraps_across_the_seam():
    base = dict(scales=[0.3, 0.3, 0.05], opacities=0.7)
    front = render(make_gaussians([0.0, 0.0, 2.0], **base), np.eye(4), projection="erp", width=128, method="direct")
    # rotate the same Gaussian to lon = pi (behind): the image is rolled by W/2 and splits at the seam
    back = render(make_gaussians([0.0, 0.0, -2.0], **base), np.eye(4), projection="erp", width=128, method="direct")
    assert back.alpha[:, 0].max() > 0.3 and back.alpha[:, -1].max() > 0.3
    assert np.allclose(np.roll(front.alpha, 64, axis=1), back.alpha, atol=1e-5)


def test_erp_pole_gaussian_is_a_cap_and_cheap():
    w, h = 128, 64
    g = make_gaussians([0.0, -2.0, 0.0], [0.2, 0.2, 0.2], opacities=0.9)  # straight up
    out = render(g, np.eye(4), projection="erp", width=w, method="direct")
    top = out.alpha[:6]
    assert top[0].min() > 0.5
    assert np.allclose(top, top[:, :1], atol=1e-4)  # rotationally symmetric: rows constant
    assert np.all(out.alpha[h // 2:] == 0)
    fp = footprints(g, Camera("erp", w, h, np.eye(4)))
    assert len(fp) <= w * 12  # a band of rows, each column once


@pytest.mark.parametrize("lat_deg", [87.0, 80.0, -84.0])
def test_erp_near_pole_direct_agrees_with_yinyang(lat_deg):
    """Near the poles the direct ERP splat (wrapped, mirrored) matches the pole-free Yin-Yang path."""
    lat, lon = np.radians(lat_deg), 0.7
    d = geo.direction_from_lat_lon(lat, lon)
    g = make_gaussians(2.0 * d, [0.12, 0.12, 0.02], opacities=0.8)
    w = 256
    direct = render(g, np.eye(4), projection="erp", width=w, method="direct")
    yy = render(g, np.eye(4), projection="erp", width=w, method="yinyang")
    # compare solid-angle-weighted alpha mass and its overlap
    wrow = np.cos(geo.erp_lat_lon(w // 2, w)[0])
    m_direct, m_yy = (direct.alpha * wrow).sum(), (yy.alpha * wrow).sum()
    assert abs(m_direct / m_yy - 1) < 0.05
    # the rest is the Yin-Yang path's bilinear resampling blur
    assert (np.abs(direct.alpha - yy.alpha) * wrow).sum() / m_yy < 0.2


def test_perspective_axis_and_behind_camera():
    g = make_gaussians([[0.0, 0.0, 3.0], [0.0, 0.0, -3.0]], [0.1, 0.1, 0.1], opacities=0.9)
    out = render(g, np.eye(4), projection="perspective", width=65, height=49, fov_deg=60)
    centre, _ = image_moments(out.alpha.astype(np.float64))
    assert np.allclose(centre, [32, 24], atol=1e-3)
    assert out.range.max() == pytest.approx(3.0, rel=1e-5)  # the Gaussian behind is culled


def test_yin_culls_gaussians_outside_its_domain():
    g = make_gaussians([[0.0, 0.0, -3.0], [0.0, -3.0, 0.1]], [0.05, 0.05, 0.05], opacities=0.9)
    out = render(g, np.eye(4), projection="yin", width=96)
    assert out.alpha.max() == 0
    assert len(project(g, Camera("yin", 96, 32, np.eye(4))).index) == 0


def test_render_output_contract_and_to_uint8():
    g = random_scene(np.random.default_rng(2), 50)
    for kw in (dict(projection="erp", width=64), dict(projection="erp", width=64, method="direct"),
               dict(projection="yin", width=60), dict(projection="perspective", width=40, height=30)):
        out = render(g, np.eye(4), **kw)
        assert isinstance(out, RenderOutput)
        assert out.colour.dtype == out.alpha.dtype == out.range.dtype == np.float32
        assert out.colour.shape[:2] == out.alpha.shape == out.range.shape
        assert np.all((out.alpha >= 0) & (out.alpha <= 1))
    u = to_uint8(np.array([[[-0.5, 0.5, 2.0], [np.nan, 1.0, 0.0]]], dtype=np.float32))
    assert u.dtype == np.uint8 and u.tolist() == [[[0, 128, 255], [0, 255, 0]]]
    with pytest.raises(ValueError, match="projection"):
        render(g, np.eye(4), projection="fisheye", width=64)
    with pytest.raises(ValueError, match="method"):
        render(g, np.eye(4), projection="erp", width=64, method="magic")


def test_truncation_constant():
    assert Q_MAX == pytest.approx(2 * np.log(255))


@pytest.mark.parametrize("kind", ["erp", "yin", "yang", "perspective"])
def test_footprints_order_with_many_layers_seam_and_poles(kind):
    """The final key sort merges pre-sorted per-offset runs; the result must still be fully sorted.

    Many overlapping layers (shells at several ranges), Gaussians straddling the ERP seam
    (lon = +-180 deg, wrapping columns) and the poles, and a perspective view: every pixel's
    list must be in (range, input index) order (camera z for the pinhole view, as 3DGS viewers
    sort) and the contributions must be exactly those of an independent lexsort of the same
    (pixel, Gaussian) pairs.
    """
    rng = np.random.default_rng(3)
    n = 3000
    d = rng.normal(size=(n, 3))
    d[: n // 6, 0] = rng.normal(scale=0.05, size=n // 6)  # seam: x ~ 0, z < 0
    d[: n // 6, 2] = -np.abs(d[: n // 6, 2]) - 0.5
    d[n // 6: n // 3, 1] = np.sign(d[n // 6: n // 3, 1]) * 5.0  # near the poles
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    means = d * rng.choice([1.0, 1.5, 2.2, 3.0], size=(n, 1)) * rng.uniform(0.98, 1.02, (n, 1))
    q = rng.normal(size=(n, 4))
    g = make_gaussians(means, rng.uniform(0.01, 0.12, (n, 3)), q / np.linalg.norm(q, axis=1, keepdims=True),
                       rng.uniform(0.2, 1.0, n), rng.uniform(0, 1, (n, 3)))
    w, h = {"erp": (128, 64), "yin": (96, 32), "yang": (96, 32), "perspective": (64, 48)}[kind]
    cam = Camera(kind, w, h, np.eye(4))
    for bound in (None, g.opacities):
        fp = footprints(g, cam, opacity_bound=bound)
        assert len(fp) > 20 * h * w / 4  # many layers per pixel
        r = (means[:, 2] if kind == "perspective" else fp.ranges)[fp.gaussian]  # the pose is the identity
        ref = np.lexsort((fp.gaussian, r, fp.pixel))
        assert np.array_equal(ref, np.arange(len(fp)))
        assert np.unique(fp.pixel.astype(np.int64) * n + fp.gaussian).size == len(fp)


def test_normalize_divides_colour_by_alpha_and_keeps_alpha():
    """normalize=True is the guarded colour/alpha division the Yin-Yang ERP path applies."""
    rng = np.random.default_rng(5)
    n = 300
    means = rng.normal(size=(n, 3)) * 0.5 + np.array([0.0, 0.0, 3.0])
    g = Gaussians(means, np.full((n, 3), 0.05), np.tile([1.0, 0, 0, 0], (n, 1)), rng.uniform(0.05, 0.6, n),
                  rgb_to_sh_dc(rng.uniform(0.2, 0.9, (n, 3)))[:, None, :])
    for projection in ("perspective", "yin"):
        plain = render(g, np.eye(4), projection=projection, width=96, height=72 if projection == "perspective" else None)
        norm = render(g, np.eye(4), projection=projection, width=96, height=72 if projection == "perspective" else None,
                      normalize=True)
        assert np.array_equal(plain.alpha, norm.alpha) and np.array_equal(plain.range, norm.range)
        ok = plain.alpha >= 1 / 255
        assert ok.any() and (~ok).any()
        assert np.allclose(norm.colour[ok], plain.colour[ok] / plain.alpha[ok][:, None], rtol=1e-5, atol=1e-6)
        assert np.all(norm.colour[~ok] == 0)
        # thin coverage no longer darkens: normalised colours stay within the Gaussians' colour range
        assert norm.colour[ok].max() <= 0.9 + 1e-4 and norm.colour[ok].min() >= 0.2 - 1e-4


# --- fast paths of the renderer (shared pose, key compositing, chunking, sparse merge) --------------------

def test_yinyang_render_is_the_same_with_one_or_two_threads_and_matches_footprints():
    """The front-to-back Yin/Yang path gives what footprints + accumulate give, in any thread layout."""
    from rasterizer import front_to_back
    from rasterizer.composite import accumulate
    rng = np.random.default_rng(21)
    g = random_scene(rng, 25_000, size=(0.01, 0.08))  # above the two-thread threshold
    c2w = pose(rng)
    one = render(g, c2w, projection="erp", width=128, threads=1)
    two = render(g, c2w, projection="erp", width=128, threads=2)
    for a, b in zip(one, two):
        assert np.array_equal(a, b)
    # per grid: the chunked key path equals the public footprints + accumulate (float rounding of log T)
    from rasterizer import splat
    from rasterizer.composite import gaussian_table
    from rasterizer.sh import sh_to_rgb
    cam0 = Camera("yin", 192, 64, c2w)
    p = splat.shared_pose(g, cam0)
    qcut = splat.opacity_cuts(g.opacities, len(g))
    colours = sh_to_rgb(g.sh, g.means, cam0.centre)
    table = gaussian_table(g.opacities, colours, p.ranges)[p.order]
    for kind in ("yin", "yang"):
        cam = Camera(kind, 192, 64, c2w)
        fused = front_to_back.premultiplied(p, cam, qcut, table)
        ref = accumulate(footprints(g, cam, opacity_bound=g.opacities), g.opacities, colours)
        assert fused[1].max() > 0.5
        for a, b in zip(fused, ref):
            assert np.allclose(a, b, rtol=1e-5, atol=1e-5)


def test_accumulate_does_not_depend_on_its_chunking(monkeypatch):
    from rasterizer import composite as comp
    rng = np.random.default_rng(8)
    g = random_scene(rng, 400)
    fp = footprints(g, Camera("erp", 96, 48, np.eye(4)))
    ref = comp.accumulate(fp, g.opacities, g.rgb, return_terms=True)
    monkeypatch.setattr(comp, "_CHUNK", 37)  # many chunks, segments never split
    small = comp.accumulate(fp, g.opacities, g.rgb, return_terms=True)
    for a, b in zip(ref[:3], small[:3]):
        assert np.allclose(a, b, atol=1e-6)
    for name in ("alpha", "transmittance", "weight", "starts", "pixels"):
        assert np.allclose(getattr(ref[3], name), getattr(small[3], name), atol=1e-6)


@pytest.mark.parametrize("kind", ["yin", "yang", "erp", "perspective"])
def test_shared_pose_and_factors_give_the_same_footprints(kind):
    """footprints with caller-provided camera points / factors (a shared pose) equal a fresh call."""
    from rasterizer.splat import gaussian_factors
    rng = np.random.default_rng(4)
    g = random_scene(rng, 1500)
    c2w = pose(rng)
    cam = Camera(kind, 96 if kind != "perspective" else 64, 32 if kind != "perspective" else 48, c2w)
    p_cam = cam.to_camera(g.means)
    pts = (p_cam, np.sqrt(np.einsum("ij,ij->i", p_cam, p_cam)))
    a = footprints(g, cam, opacity_bound=g.opacities)
    b = footprints(g, cam, opacity_bound=g.opacities, factors=gaussian_factors(g), camera_points=pts)
    assert len(a) > 1000
    for f in ("pixel", "gaussian", "weight", "ranges"):
        assert np.array_equal(getattr(a, f), getattr(b, f))


def test_gaussian_factors_match_rotation_times_scales():
    from rasterizer.gaussians import quat_to_rotmat
    from rasterizer.splat import gaussian_factors
    rng = np.random.default_rng(6)
    g = random_scene(rng, 40_000)  # several chunks
    f = gaussian_factors(g).T.reshape(-1, 3, 3)
    ref = quat_to_rotmat(g.quats) * np.asarray(g.scales, dtype=np.float64)[:, None, :]
    assert np.allclose(f, ref, atol=1e-12)


@pytest.mark.parametrize("kind", ["yin", "yang"])
def test_grid_domain_cull_drops_only_gaussians_without_contributions(kind, monkeypatch):
    """The shared Yin/Yang domain cull is conservative: without it the footprints are the same."""
    from rasterizer import splat
    from rasterizer.splat import projection
    rng = np.random.default_rng(12)
    g = random_scene(rng, 3000, size=(0.02, 0.5))
    cam = Camera(kind, 96, 32, pose(rng))
    culled = footprints(g, cam)
    kept = splat.grid_keep(splat.shared_pose(g, cam), cam)
    assert 0 < kept.size < len(g)
    monkeypatch.setattr(projection, "grid_keep",
                        lambda p, c: np.flatnonzero(p.ranges >= c.near))
    full = footprints(g, cam)
    for f in ("pixel", "gaussian", "weight"):
        assert np.array_equal(getattr(culled, f), getattr(full, f))


def _bilinear_clamped(img, col, row):
    """Slow reference: bilinear sample of img (h, w, C) at continuous (col, row), clamped to the border."""
    h, w = img.shape[:2]
    col, row = np.clip(col, 0, w - 1), np.clip(row, 0, h - 1)
    c0 = np.minimum(np.floor(col).astype(int), max(w - 2, 0))
    r0 = np.minimum(np.floor(row).astype(int), max(h - 2, 0))
    fc, fr = (col - c0)[..., None], (row - r0)[..., None]
    c1, r1 = np.minimum(c0 + 1, w - 1), np.minimum(r0 + 1, h - 1)
    return ((img[r0, c0] * (1 - fc) + img[r0, c1] * fc) * (1 - fr)
            + (img[r1, c0] * (1 - fc) + img[r1, c1] * fc) * fr)


@pytest.mark.parametrize("h", [3, 16, 40])
def test_sparse_yin_yang_merge_equals_the_dense_blend(h, monkeypatch):
    """The merge equals both grids sampled at every ERP pixel and blended by the Yin weight; the taps made
    block by block (large ERPs) give the same bits as the cached ones, with and without threads."""
    from concurrent.futures import ThreadPoolExecutor

    from rasterizer import yin_yang
    from rasterizer.yin_yang import FEATHER_PIXELS, blend_weight_yin, yin_yang_to_erp
    rng = np.random.default_rng(h)
    a, b = (rng.random((h, 3 * h, 5)).astype(np.float32) for _ in range(2))
    a[rng.random((h, 3 * h)) < 0.3] = 0
    d = geo.grid_directions("erp", 2 * h, 4 * h)
    wy = blend_weight_yin(d, feather=FEATHER_PIXELS * 2 * geo.YIN_LAT_MAX / h)[..., None]
    ref = (wy * _bilinear_clamped(a, *geo.project_to_grid("yin", d, h, 3 * h))
           + (1 - wy) * _bilinear_clamped(b, *geo.project_to_grid("yang", d, h, 3 * h)))
    cached = yin_yang_to_erp(a, b, 2 * h, 4 * h)
    np.testing.assert_allclose(cached, ref, atol=2e-6)
    with ThreadPoolExecutor(2) as pool:
        assert np.array_equal(yin_yang_to_erp(a, b, 2 * h, 4 * h, pool=pool), cached)
    monkeypatch.setattr(yin_yang, "CACHED_TAPS_PIXELS", 0)
    monkeypatch.setattr(yin_yang, "TAP_BLOCK_PIXELS", 7 * h)  # several row blocks, the last one short
    assert np.array_equal(yin_yang_to_erp(a, b, 2 * h, 4 * h), cached)
    with ThreadPoolExecutor(2) as pool:
        assert np.array_equal(yin_yang_to_erp(a, b, 2 * h, 4 * h, pool=pool), cached)
