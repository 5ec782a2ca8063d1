"""The front-to-back chunked renderer (rasterizer.front_to_back) against the slow reference loop and the
single-sort path (footprints + accumulate): same images within float rounding, early termination that
skips hidden Gaussians, and a peak number of contributions set by the image and the chunk."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rasterizer import front_to_back, splat
from rasterizer.camera import Camera
from rasterizer.composite import accumulate, gaussian_table
from rasterizer.render import render, render_camera
from rasterizer.splat import footprints, polar_rows, project
from rasterizer.splat.projection import CUT_KEEPS_PX
from tests.rasterizer._support import forward_scene, make_gaussians, pose, random_scene, reference_composite

SIZES = {"erp": (64, 32), "yin": (48, 16), "yang": (48, 16), "perspective": (40, 30)}


@pytest.fixture
def tiny_chunks(monkeypatch):
    """Chunks of a few Gaussians: many chunks, so transmittance is carried and dead pixels cull."""
    monkeypatch.setattr(front_to_back, "MIN_CHUNK", 1)
    monkeypatch.setattr(front_to_back, "CHUNK_LAYERS", 0.05)


def old_path(g, cam):
    """The single global sort: footprints cut at the opacities, then accumulate (premultiplied)."""
    from rasterizer.sh import sh_to_rgb
    colours = sh_to_rgb(g.sh, g.means, cam.centre)
    return accumulate(footprints(g, cam, opacity_bound=g.opacities), g.opacities, colours)


def new_path(g, cam):
    from rasterizer.sh import sh_to_rgb
    colours = sh_to_rgb(g.sh, g.means, cam.centre)
    p = splat.shared_pose(g, cam)
    table = gaussian_table(g.opacities, colours, p.ranges)[p.order]
    return front_to_back.premultiplied(p, cam, splat.opacity_cuts(g.opacities, len(g)), table)


def assert_same(new, old, atol=2e-5):
    for a, b in zip(new, old):
        assert a.shape == b.shape and a.dtype == b.dtype
        assert np.all(np.isfinite(a))
        assert np.allclose(a, b, rtol=1e-5, atol=atol), float(np.abs(a - b).max())


@pytest.mark.parametrize("kind", ["perspective", "yin", "erp"])
def test_front_to_back_matches_the_slow_reference_loop(kind, tiny_chunks):
    g = forward_scene(np.random.default_rng(11), 40, opacity=(0.3, 1.0))
    w, h = {"perspective": (24, 20), "yin": (36, 12), "erp": (48, 24)}[kind]
    cam = Camera(kind, w, h, np.eye(4))
    if kind == "erp":  # the reference is the pixel-space EWA: keep away from the polar path
        pr = project(g, cam)
        g = g.subset(np.sort(pr.index[polar_rows(pr, cam)[0]]))
    out = render_camera(g, cam)
    pr = project(g, cam)
    sel = pr.index
    depth = g.means[sel, 2] if kind == "perspective" else None  # the pose is the identity
    ref = reference_composite(pr.mean, pr.conic, pr.ranges, g.opacities[sel], g.rgb[sel], w, h,
                              period=w if kind == "erp" else None, depths=depth)
    assert out.alpha.max() > 0.9
    assert np.allclose(out.colour, ref[0], atol=2e-5)
    assert np.allclose(out.alpha, ref[1], atol=2e-5)
    assert np.allclose(out.range, ref[2], atol=1e-4)


@pytest.mark.parametrize("kind", ["perspective", "yin", "erp"])
def test_footprints_cut_in_standard_deviations_match_the_slow_reference_loop(kind, tiny_chunks):
    """``cut_sigma``: every footprint also ends that many standard deviations out, as the loop cut at q_max."""
    g = forward_scene(np.random.default_rng(12), 40, opacity=(0.3, 1.0))
    g = g.with_(scales=g.scales * np.random.default_rng(13).choice([0.3, 8.0], (len(g), 1)))  # sub-pixel and wide
    w, h = {"perspective": (24, 20), "yin": (36, 12), "erp": (48, 24)}[kind]
    cam = Camera(kind, w, h, np.eye(4))
    if kind == "erp":
        pr = project(g, cam)
        g = g.subset(np.sort(pr.index[polar_rows(pr, cam)[0]]))
    pr = project(g, cam)
    sel = pr.index
    depth = g.means[sel, 2] if kind == "perspective" else None
    args = (pr.mean, pr.conic, pr.ranges, g.opacities[sel], g.rgb[sel], w, h)
    kw = dict(period=w if kind == "erp" else None, depths=depth)
    # the cut's radius^2: 1.5^2, or CUT_KEEPS_PX along the narrowest axis where that is farther (the conic's
    # largest eigenvalue is 1 / the covariance's smallest)
    con = pr.conic
    lam_max = 0.5 * (con[:, 0] + con[:, 2]) + np.sqrt((0.5 * (con[:, 0] - con[:, 2])) ** 2 + con[:, 1] ** 2)
    q_max = np.maximum(1.5**2, CUT_KEEPS_PX**2 * lam_max)
    assert (q_max > 1.5**2).any()  # the floor is checked, and the plain cut but in the ERP (whose wide
    assert kind == "erp" or (q_max == 1.5**2).any()  # footprints take the polar path the loop does not model)
    cut = render_camera(g, cam, cut_sigma=1.5)
    ref = reference_composite(*args, **kw, q_max=q_max)
    assert np.allclose(cut.colour, ref[0], atol=2e-5) and np.allclose(cut.alpha, ref[1], atol=2e-5)
    uncut = reference_composite(*args, **kw)
    assert np.abs(uncut[1] - ref[1]).max() > 0.01  # the cut removed coverage a full footprint has
    # a cut beyond the 1/255 rule's reach (3.33 sigma at opacity 1) changes nothing
    far = render_camera(g, cam, cut_sigma=3.5)
    np.testing.assert_array_equal(far.colour, render_camera(g, cam).colour)


@pytest.mark.parametrize("cut", [0.0, -1.0, float("nan"), float("inf"), "2", True])
def test_a_cut_that_is_not_a_positive_number_is_refused(cut):
    with pytest.raises(ValueError, match="cut_sigma"):
        render(forward_scene(np.random.default_rng(0), 5), np.eye(4), width=16, cut_sigma=cut)


def test_a_cut_never_comes_nearer_than_two_pixels():
    """sigma_cuts: cut_sigma^2, or (2 px)^2 over the covariance's smallest eigenvalue where that is more (the
    pixel filter alone is then beyond the 1/255 rule's reach: not cut); a huge cut_sigma is no overflow."""
    a, b, c = np.array([4.0, 0.3, 0.8, 9.0]), np.array([0.0, 0.0, 0.0, 8.2]), np.array([4.0, 0.3, 8.0, 9.0])
    q = splat.sigma_cuts(a, b, c, 2.0)
    np.testing.assert_allclose(q, [4.0, 4.0 / 0.3, 4.0 / 0.8, 5.0])  # the last: eigenvalues 17.2 and 0.8
    assert q[1] > splat.Q_MAX
    np.testing.assert_allclose(splat.sigma_cuts(a, b, c, 1e200)[0], splat.Q_MAX)


@st.composite
def scenes(draw):
    """Small scenes with the hard cases: poles, the ERP seam, points at the camera, tiny and huge
    scales, opacities near the 1/255 cut and opaque layers."""
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    n = draw(st.integers(1, 60))
    d = rng.normal(size=(n, 3))
    where = rng.integers(0, 5, n)
    d[where == 1, 1] = np.sign(d[where == 1, 1] + 1e-9) * 20.0  # near a pole
    d[where == 2, 0] = rng.normal(scale=0.02, size=(where == 2).sum())  # on the seam (x ~ 0, z < 0)
    d[where == 2, 2] = -np.abs(d[where == 2, 2]) - 0.5
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = rng.uniform(0.5, 4.0, n)
    r[where == 3] = rng.uniform(0.0, 0.02, (where == 3).sum())  # at the camera (some inside near)
    scale_kind = draw(st.sampled_from(["tiny", "normal", "huge", "mixed"]))
    scales = {"tiny": rng.uniform(1e-4, 2e-3, (n, 3)), "normal": rng.uniform(0.02, 0.3, (n, 3)),
              "huge": rng.uniform(0.5, 3.0, (n, 3)),
              "mixed": np.exp(rng.uniform(np.log(1e-4), np.log(3.0), (n, 3)))}[scale_kind]
    op_kind = draw(st.sampled_from(["low", "mid", "opaque"]))
    opac = {"low": rng.uniform(0.5 / 255, 3 / 255, n), "mid": rng.uniform(0.05, 1.0, n),
            "opaque": np.full(n, 0.999)}[op_kind]
    q = rng.normal(size=(n, 4))
    g = make_gaussians(d * r[:, None], scales, q / np.linalg.norm(q, axis=1, keepdims=True), opac,
                       rng.uniform(0, 1, (n, 3)))
    return g, seed


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(scene=scenes(), kind=st.sampled_from(["erp", "yin", "yang", "perspective"]))
def test_front_to_back_matches_the_single_sort_on_random_scenes(scene, kind, tiny_chunks):
    g, seed = scene
    w, h = SIZES[kind]
    cam = Camera(kind, w, h, pose(np.random.default_rng(seed)))
    assert_same(new_path(g, cam), old_path(g, cam))


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(scene=scenes(), normalize=st.sampled_from([None, True, False]))
def test_erp_renders_both_methods_match_the_single_sort(scene, normalize, tiny_chunks):
    """Yin-Yang merge and the direct ERP (polar caps, seam) with plain and V/A compositing."""
    g, seed = scene
    c2w = pose(np.random.default_rng(seed))
    for method in ("yinyang", "direct"):
        new = render(g, c2w, projection="erp", width=64, method=method, normalize=normalize)
        with pytest.MonkeyPatch.context() as mp:  # the same render through the single global sort
            mp.setattr(front_to_back, "premultiplied", lambda p, cam, q, t, **kw: old_path(g, cam))
            old = render(g, c2w, projection="erp", width=64, method=method, normalize=normalize)
        # V/A divides by alpha >= 1/255: allow the division's amplification of rounding
        assert_same(new, old, atol=2e-5 if normalize is False or (normalize is None and method == "direct") else 1e-3)


def _wall_and_hidden(n_hidden=400, rng=None):
    """An opaque double wall 1 m in front of a perspective camera and ``n_hidden`` Gaussians behind it."""
    rng = rng or np.random.default_rng(0)
    gx, gy = np.meshgrid(np.linspace(-1.6, 1.6, 60), np.linspace(-1.3, 1.3, 50))
    wall = np.stack([gx.ravel(), gy.ravel(), np.ones(gx.size)], axis=1)
    wall = np.concatenate([wall, wall * [1, 1, 1.05]])  # two layers: T falls below 1e-4 everywhere
    hidden = np.stack([rng.uniform(-1, 1, n_hidden), rng.uniform(-0.8, 0.8, n_hidden),
                       rng.uniform(2.0, 4.0, n_hidden)], axis=1)
    means = np.concatenate([wall, hidden])
    scales = np.concatenate([np.full((len(wall), 3), 0.06), np.full((n_hidden, 3), 0.03)])
    opac = np.concatenate([np.full(len(wall), 0.99), rng.uniform(0.2, 1.0, n_hidden)])
    return make_gaussians(means, scales, None, opac, rng.uniform(0, 1, (len(means), 3))), len(wall)


def test_gaussians_behind_an_opaque_wall_are_skipped(monkeypatch):
    monkeypatch.setattr(front_to_back, "MIN_CHUNK", 1)
    g, n_wall = _wall_and_hidden()
    cam = Camera("perspective", 64, 48, np.eye(4))
    seen = []
    job_keys = splat.job_keys

    def counting(job, live, polar, **kw):
        seen.append(job.cols.index[live])
        return job_keys(job, live, polar, **kw)

    monkeypatch.setattr(splat, "job_keys", counting)
    new = new_path(g, cam)
    monkeypatch.setattr(splat, "job_keys", job_keys)
    assert_same(new, old_path(g, cam))
    assert new[1].min() > 0.99  # the wall covers the image (its pixels stop compositing at T < 1e-4)
    built = np.concatenate(seen)
    hidden_built = np.count_nonzero(built >= n_wall)
    assert hidden_built < 0.05 * (len(g) - n_wall)  # almost none of the hidden Gaussians got contributions


def test_contributions_per_chunk_are_bounded_by_the_image_not_the_scene(monkeypatch):
    """Many translucent layers (no early termination): the scene's contributions grow with the
    layers, the largest chunk stays under the chunk budget plus one image."""
    rng = np.random.default_rng(3)
    cam = Camera("perspective", 48, 32, np.eye(4))
    peaks = []
    sizes = []
    job_keys = splat.job_keys

    def recording(job, live, polar, **kw):
        key, ranks = job_keys(job, live, polar, **kw)
        sizes.append(0 if key is None else key.size)
        return key, ranks

    monkeypatch.setattr(splat, "job_keys", recording)
    for layers in (4, 40):
        gx, gy = np.meshgrid(np.linspace(-1.2, 1.2, 30), np.linspace(-0.9, 0.9, 20))
        sheet = np.stack([gx.ravel(), gy.ravel(), np.ones(gx.size)], axis=1)
        means = np.concatenate([sheet * [1, 1, 1 + 0.05 * k] for k in range(layers)])
        g = make_gaussians(means, 0.08, None, rng.uniform(0.02, 0.05, len(means)), rng.uniform(0, 1, (len(means), 3)))
        sizes.clear()
        out = new_path(g, cam)
        assert_same(out, old_path(g, cam))
        peaks.append((sum(sizes), max(sizes)))
    budget = front_to_back.chunk_budget(cam.height, cam.width)
    assert peaks[1][0] > 5 * peaks[0][0]  # ten times the layers, many times the contributions
    assert peaks[1][1] <= budget + cam.width * cam.height


def test_random_scene_perspective_and_direct_match_with_default_chunks():
    rng = np.random.default_rng(8)
    g = random_scene(rng, 3000)
    for kind, (w, h) in (("perspective", (96, 64)), ("erp", (128, 64))):
        cam = Camera(kind, w, h, pose(rng))
        assert_same(new_path(g, cam), old_path(g, cam))


@pytest.mark.parametrize("kind", ["perspective", "erp", "yang"])
def test_row_bands_in_threads_match_one_thread(kind, monkeypatch):
    monkeypatch.setattr(front_to_back, "MIN_THREAD_GAUSSIANS", 0)
    rng = np.random.default_rng(5)
    g = random_scene(rng, 4000)
    c2w = pose(rng)
    w = {"perspective": 96, "erp": 128, "yang": 96}[kind]
    kw = dict(projection=kind, width=w, method="direct")
    one = render(g, c2w, threads=1, **kw)
    for threads in (2, 3):
        many = render(g, c2w, threads=threads, **kw)
        assert_same(many, one, atol=1e-5)
    assert one.alpha.max() > 0.5


@pytest.mark.parametrize("min_drop", [0.0, 1.0])
def test_keys_at_dead_pixels_dropped_or_kept_give_the_same_image(min_drop, monkeypatch):
    """Dead pixels' keys filtered before the sort (MASK_MIN_DROP 0) or composited with weight 0 (1): the same images."""
    from rasterizer.splat import keys

    monkeypatch.setattr(front_to_back, "MIN_CHUNK", 1)
    monkeypatch.setattr(front_to_back, "CHUNK_LAYERS", 0.5)
    monkeypatch.setattr(keys, "MASK_MIN_DROP", min_drop)
    g, _ = _wall_and_hidden()
    for kind, (w, h) in (("perspective", (64, 48)), ("yin", (48, 16))):
        cam = Camera(kind, w, h, np.eye(4))
        assert_same(new_path(g, cam), old_path(g, cam))


@pytest.mark.parametrize("kind", ["perspective", "yang", "erp"])
def test_small_groups_in_coarser_classes_give_the_same_keys(kind, monkeypatch):
    """Merging small size-class groups into coarser blocks pads them with misses only: the sorted keys are equal."""
    from rasterizer.splat import keys

    rng = np.random.default_rng(12)
    g = random_scene(rng, 3000)
    w = {"perspective": 96, "yang": 96, "erp": 128}[kind]
    cam = Camera(kind, w, w // 2 if kind == "erp" else w // 3 if kind == "yang" else 64, pose(rng))
    p = splat.shared_pose(g, cam)
    cuts = splat.opacity_cuts(g.opacities, len(g))
    got, blocks = [], []
    class_keys = keys.class_keys

    def counting(*a, **kw):
        blocks[-1] += 1
        return class_keys(*a, **kw)

    monkeypatch.setattr(keys, "class_keys", counting)
    for small in (0, 1 << 30):  # no group merged; every group merged as far as it goes
        monkeypatch.setattr(keys, "SMALL_BLOCK", small)
        blocks.append(0)
        got.append(splat.sorted_keys(p, cam, cuts, splat.MAX_CONTRIBUTIONS)[0])
    assert got[0].size > 1000
    assert blocks[1] < blocks[0]
    assert np.array_equal(got[0], got[1])


@pytest.mark.parametrize("kind", ["perspective", "yin"])
def test_ranks_among_a_subset_keep_the_order_of_all_ranks(kind):
    """A camera's own ranks (one render's sort of the Gaussians it keeps) order them as the ranks of all N,
    ties (duplicated Gaussians) in input order."""
    rng = np.random.default_rng(9)
    g = random_scene(rng, 2000)
    g = g.subset(np.concatenate([np.arange(len(g)), np.arange(0, len(g), 7)]))  # exact duplicates: ties
    cam = Camera(kind, 96, 64 if kind == "perspective" else 32, pose(rng))
    p = splat.shared_pose(g, cam)
    index = np.sort(rng.choice(len(g), 900, replace=False))
    own = p.ranks_among(index)
    assert np.array_equal(np.sort(own), np.arange(index.size))
    assert np.array_equal(np.argsort(own), np.argsort(p.rank[index]))
