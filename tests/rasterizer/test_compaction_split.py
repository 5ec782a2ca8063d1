"""Detail at the upload's pitch: textured pixels split into 2x2 surfels on their parent's plane that bring a
reference's own render closer to the fine upload; flat ones, the rig cap, the shell and the cap are respected."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bench.metrics import psnr, sharpness
from rasterizer import geometry as geo
from rasterizer.camera import sample_erp
from rasterizer.compaction import CompactionOptions, Provenance, compact_result
from rasterizer.compaction.merge import TEXTURE_TOL
from rasterizer.compaction.split import (
    MAX_CHILD_SIGMAS,
    MIN_UPLOAD_RATIO,
    child_opacity,
    fine_erp,
    split_textured,
    texture_ratio,
)
from rasterizer.depth_gaussians import gaussians_from_depth
from rasterizer.gaussians import Gaussians, quat_to_rotmat, sh_dc_to_rgb
from rasterizer.render import render
from rasterizer.shell import environment_shell
from rasterizer.yin_yang import erp_to_yin_yang, resize_erp
from tests.rasterizer._support import box_range, pose_at

H, W = 24, 72  # one Yin/Yang grid; its ERP is 96 wide, the fine ERP 192 x 96
GRIDS = ("yin", "yang")
E = 4 * H


def _wall_colour(p: np.ndarray, textured_x: float = 0.0) -> np.ndarray:
    """World texture of the box walls: a smooth checker pattern (period 0.79 m: six grid pixels, twelve fine
    ones, at 2 m) where x > ``textured_x``, a gentle ramp elsewhere."""
    fine = 0.5 + 0.35 * np.sin(8.0 * p[..., 1]) * np.sin(8.0 * (p[..., 0] + p[..., 2]))
    ramp = 0.45 + 0.05 * p[..., 1]
    grey = np.where(p[..., 0] > textured_x, fine, ramp)
    return np.stack([grey, 0.9 * grey, 0.8 * grey + 0.1], axis=-1).astype(np.float32)


def _seen(c2w: np.ndarray, d: np.ndarray, **kw) -> np.ndarray:
    """Colour along camera-frame rays ``d`` (..., 3) from ``c2w`` in the box [-2, 2]^3."""
    dw = d @ c2w[:3, :3].T
    o = c2w[:3, 3]
    with np.errstate(divide="ignore"):
        t = np.where(dw > 0, (2.0 - o) / dw, np.where(dw < 0, (-2.0 - o) / dw, np.inf)).min(axis=-1)
    return _wall_colour(o + dw * t[..., None], **kw)


def _scene(**kw):
    """Two references in the box: compacted layout with a shell, the fine ERPs (2, E, 2E, 3), poses."""
    poses = np.stack([pose_at([0.0, 0.0, -0.3]), pose_at([0.1, 0.2, 0.3])])
    fine = np.stack([_seen(c, geo.grid_directions("erp", E, 2 * E), **kw) for c in poses])
    parts, ranges = [], []
    for v, c in enumerate(poses):  # the grid images as the service makes them: the upload area-averaged, resampled
        images = erp_to_yin_yang(resize_erp(fine[v], E // 2, E), height=H)
        for k, image in zip(GRIDS, images):
            rng = box_range(k, c, size=(H, W))
            ranges.append(rng)
            parts.append(gaussians_from_depth(image, rng, c, k, surfels=True, opacity=0.9))
    layout = Gaussians.concatenate(parts)
    range_maps = np.stack(ranges).reshape(2, 2, H, W)
    shell = environment_shell(layout, range_maps, poses, GRIDS, 20.0)
    prov = Provenance(GRIDS, H, W, poses, shell=len(shell))
    res = compact_result(Gaussians.concatenate([layout, shell]), prov, CompactionOptions(min_opacity=0.0))
    return res, fine, poses, len(shell)


def test_fine_erp_only_for_uploads_finer_than_the_grid():
    rng = np.random.default_rng(0)
    narrow = int(MIN_UPLOAD_RATIO * E) - 2
    assert fine_erp(rng.random((narrow // 2, narrow, 3)), GRIDS, H, W) is None
    up = (rng.random((E, 2 * E, 3)) * 255).astype(np.uint8)
    got = fine_erp(up, GRIDS, H, W)
    assert got.shape == (E, 2 * E, 3) and got.dtype == np.float32
    np.testing.assert_allclose(got, up / 255.0, atol=1e-6)  # the same pitch: the upload itself
    wide = fine_erp(np.repeat(np.repeat(up, 3, axis=0), 3, axis=1), GRIDS, H, W)  # 3x wider: area-averaged back
    np.testing.assert_allclose(wide, up / 255.0, atol=1e-5)
    erp_grid = ("erp",), E, 2 * E  # an ERP layout as wide as the upload: nothing finer
    assert fine_erp(rng.random((E, 2 * E, 3)), *erp_grid) is None
    assert fine_erp(rng.random((2 * E, 4 * E, 3)), *erp_grid).shape == (2 * E, 4 * E, 3)


def test_textured_pixels_split_in_place_and_the_rest_is_kept():
    res, fine, poses, shell = _scene()
    out = split_textured(res, fine)
    n = len(res.gaussians)
    st = out.stats["split_textured"]
    assert 0 < st["split"] < (res.block == 1).sum() and st["added"] == 4 * st["split"]
    assert len(out.gaussians) == n + 3 * st["split"] == out.stats["output"]
    assert sum(out.stats["removed"].values()) == out.stats["input"] - out.stats["output"]
    # layout order kept; each child holds its parent's position; the shell is the same, last
    pos = out.provenance.flat_index(len(out.gaussians))
    front = len(out.gaussians) - shell
    assert np.all(np.diff(pos[:front]) >= 0)
    _, counts = np.unique(pos[:front], return_counts=True)
    assert set(np.unique(counts)) <= {1, 4} and (counts == 4).sum() == st["split"]
    for name in ("means", "scales", "opacities", "sh"):
        np.testing.assert_array_equal(getattr(out.gaussians, name)[front:], getattr(res.gaussians, name)[n - shell:])
    # a parent kept whole is unchanged
    whole = np.repeat(counts == 1, counts)
    kept = res.gaussians.subset(np.flatnonzero(np.isin(res.provenance.flat_index(n)[:n - shell], pos[:front][whole])))
    np.testing.assert_array_equal(out.gaussians.opacities[:front][whole], kept.opacities)
    # only where the world is striped (x > 0), never on the ramp beyond two grid pixels (0.13 m) of its edge
    children = np.repeat(counts == 4, counts)
    assert out.gaussians.means[:front][children][:, 0].min() > -0.3
    # kept inputs: the index lists exactly the unsplit ones
    assert out.index.size == res.index.size - st["split"]


def test_children_lie_on_the_parent_plane_with_its_colour_on_average():
    res, fine, poses, shell = _scene()
    out = split_textured(res, fine)
    pos = out.provenance.flat_index(len(out.gaussians))
    front = len(out.gaussians) - shell
    first = np.flatnonzero((pos[:front][:-3] == pos[:front][3:]))
    first = first[(first == 0) | (pos[np.maximum(first - 1, 0)] != pos[first])]
    kids = out.gaussians.subset((first[:, None] + np.arange(4)).reshape(-1))
    parents = res.gaussians.subset(np.searchsorted(res.provenance.flat_index(len(res.gaussians))[:len(res.gaussians) - shell],
                                                   pos[first]))
    rot = quat_to_rotmat(parents.quats.astype(np.float64))
    k = len(parents)
    normal = rot[np.arange(k), :, np.argmin(parents.scales, axis=1)]
    off = kids.means.reshape(k, 4, 3) - parents.means[:, None, :]
    height = np.abs(np.einsum("ni,nqi->nq", normal, off))
    assert np.median(height / parents.scales.max(axis=1)[:, None]) < 1e-3  # on the plane (not the fallback)
    local = np.einsum("nji,nqj->nqi", rot, off) / parents.scales[:, None, :]
    on_plane = height < 1e-3 * parents.scales.max(axis=1)[:, None]
    assert np.all(np.linalg.norm(local, axis=2)[on_plane] <= MAX_CHILD_SIGMAS + 1e-6)
    np.testing.assert_allclose(kids.scales.reshape(k, 4, 3), np.repeat(0.5 * parents.scales[:, None, :], 4, axis=1),
                               rtol=1e-6)
    two = 1 - (1 - kids.opacities.reshape(k, 4).astype(np.float64)) ** 2  # two children composite to the parent's alpha
    np.testing.assert_allclose(two, np.repeat(parents.opacities[:, None], 4, axis=1), atol=1e-6)
    rgb = sh_dc_to_rgb(kids.sh[:, 0]).reshape(k, 4, 3)
    unclipped = np.all((rgb > 1e-4) & (rgb < 1 - 1e-4), axis=(1, 2))
    np.testing.assert_allclose(rgb[unclipped].mean(axis=1), sh_dc_to_rgb(parents.sh[unclipped, 0]), atol=1e-5)
    # they carry the upload's detail: seen from their own camera, each is nearer the fine ERP there than its parent
    view = out.provenance.decode(len(out.gaussians))[0][first]
    d = np.einsum("nji,nqj->nqi", poses[view, :3, :3], kids.means.reshape(k, 4, 3) - poses[view, None, :3, 3])
    c, r = geo.project_to_grid("erp", d.reshape(-1, 3), E, 2 * E)
    seen = np.stack([sample_erp(fine[v], c, r) for v in range(2)])[np.repeat(view, 4), np.arange(4 * k)].reshape(k, 4, 3)
    child_err = np.abs(rgb - seen).mean()
    parent_err = np.abs(sh_dc_to_rgb(parents.sh[:, 0])[:, None, :] - seen).mean()
    assert child_err < 0.5 * parent_err


def test_a_reference_render_at_the_fine_pitch_comes_closer_to_its_upload():
    res, fine, poses, _ = _scene(textured_x=-3.0)  # stripes on every wall
    out = split_textured(res, fine)
    for v in range(2):
        before = render(res.gaussians, poses[v], projection="erp", width=2 * E, normalize=False).colour
        after = render(out.gaussians, poses[v], projection="erp", width=2 * E, normalize=False).colour
        assert np.isfinite(after).all()
        assert psnr(after, fine[v]) > psnr(before, fine[v]) + 0.5
        assert sharpness(after, fine[v], 0.0) > sharpness(before, fine[v], 0.0) + 0.05


def test_the_cap_the_rig_cap_and_flat_uploads_are_respected():
    res, fine, poses, shell = _scene(textured_x=-3.0)
    n = len(res.gaussians)
    full = split_textured(res, fine).stats["split_textured"]["split"]
    capped = split_textured(res, fine, limit=n + 3 * 40 + 2)
    assert capped.stats["split_textured"]["split"] == 40 and len(capped.gaussians) <= n + 3 * 40 + 2
    assert split_textured(res, fine, limit=n - 5).stats["split_textured"]["split"] == 0
    # the most textured first: every pixel the cap split is at least as textured as every one it left
    ratio = np.stack([texture_ratio(f) for f in fine])
    prov = capped.provenance
    view, grid, row, col = prov.decode(len(capped.gaussians))

    def block_ratio(sel):
        d = np.stack([geo.grid_directions(GRIDS[gi], H, W)[r, c] for gi, r, c in zip(grid[sel], row[sel], col[sel])])
        c_, r_ = geo.project_to_grid("erp", d, E // 2, E)
        return ratio[view[sel], np.clip(np.rint(r_).astype(int), 0, E // 2 - 1), np.mod(np.rint(c_).astype(int), E)]

    pos = prov.flat_index(len(capped.gaussians))
    front = len(capped.gaussians) - shell
    _, first, counts = np.unique(pos[:front], return_index=True, return_counts=True)
    split_rows, kept_rows = first[counts == 4], first[(counts == 1) & (capped.block[first] == 1)]
    kept_ratio = block_ratio(kept_rows)
    assert block_ratio(split_rows).min() >= kept_ratio[kept_ratio > TEXTURE_TOL].max() - 1e-6
    assert full > 40
    # the rig cap never splits
    exclude = np.zeros((2, 2, H, W), bool)
    exclude[:, 1] = True  # every Yang pixel
    out = split_textured(res, fine, exclude=exclude)
    view, grid, *_ = out.provenance.decode(len(out.gaussians))
    pos = out.provenance.flat_index(len(out.gaussians))
    _, counts = np.unique(pos[:len(out.gaussians) - shell], return_counts=True)
    assert 0 < out.stats["split_textured"]["split"] < full
    assert np.all(grid[:len(out.gaussians) - shell][np.repeat(counts == 4, counts)] == 0)
    # a flat upload (no contrast at all) splits nothing and leaves the scene as it was
    flat = split_textured(res, np.full_like(fine, 0.5))
    assert flat.stats["split_textured"]["split"] == 0
    for name in ("means", "sh"):
        np.testing.assert_array_equal(getattr(flat.gaussians, name), getattr(res.gaussians, name))


def test_grazing_and_degenerate_parents_stay_finite():
    res, fine, poses, shell = _scene(textured_x=-3.0)
    g = res.gaussians
    front = len(g) - shell
    quats = g.quats.copy()
    scales = g.scales.copy()
    quats[:front:3] = [np.cos(np.pi / 4), np.sin(np.pi / 4), 0.0, 0.0]  # planes turned edge-on to many rays
    scales[1:front:5] = [1e-30, 1e-30, 1e-30]  # collapsed footprints
    res2 = type(res)(g.with_(quats=quats, scales=scales), res.provenance, res.block, res.index, res.stats)
    out = split_textured(res2, fine)
    assert out.stats["split_textured"]["split"] > 0
    out.gaussians.check_finite()
    # every child stays near its parent's range: the plane, or the parent's range where the plane runs off
    pos = out.provenance.flat_index(len(out.gaussians))
    view = out.provenance.decode(len(out.gaussians))[0]
    rng = np.linalg.norm(out.gaussians.means - poses[view, :3, 3], axis=1)
    par = np.linalg.norm(res.gaussians.means - poses[res.provenance.decode(len(g))[0], :3, 3], axis=1)
    parent_of = np.searchsorted(res.provenance.flat_index(len(g))[:front], pos[:len(out.gaussians) - shell])
    ratio = rng[:len(out.gaussians) - shell] / par[parent_of]
    assert ratio.min() > 0.5 and ratio.max() < 2.0


def test_a_view_without_a_finer_upload_keeps_its_pixels_whole():
    """One view's upload finer than the grid, the other's not (None): the first view's pixels split as they do
    when both are fine, to the bit, and the second's stay whole; with neither, nothing changes."""
    res, fine, _, shell = _scene(textured_x=-3.0)
    both = split_textured(res, fine)
    one = split_textured(res, [fine[0], None])
    n_both, n_one = len(both.gaussians), len(one.gaussians)

    def split_pixels(out, n):
        pos = out.provenance.flat_index(n)[:n - shell]
        keys, counts = np.unique(pos, return_counts=True)
        return keys[counts == 4]

    views_both = res.provenance.decode(len(res.gaussians))[0]
    flat_res = res.provenance.flat_index(len(res.gaussians))
    view_of = dict(zip(flat_res.tolist(), views_both.tolist()))
    in_both, in_one = split_pixels(both, n_both), split_pixels(one, n_one)
    assert in_one.size > 0 and all(view_of[k] == 0 for k in in_one.tolist())
    np.testing.assert_array_equal(in_one, [k for k in in_both.tolist() if view_of[k] == 0])
    assert one.stats["split_textured"]["split"] == in_one.size
    rows_both = np.isin(both.provenance.flat_index(n_both), in_one)
    rows_one = np.isin(one.provenance.flat_index(n_one), in_one)
    for name in ("means", "scales", "quats", "opacities", "sh"):
        np.testing.assert_array_equal(getattr(one.gaussians, name)[rows_one], getattr(both.gaussians, name)[rows_both])
    none = split_textured(res, [None, None])
    assert none.stats["split_textured"]["split"] == 0 and len(none.gaussians) == len(res.gaussians)


def test_bad_fine_shape_is_refused():
    res, fine, _, _ = _scene()
    with pytest.raises(ValueError, match="fine ERPs must be"):
        split_textured(res, fine[:, :-2])
    with pytest.raises(ValueError, match="fine ERPs must be"):
        split_textured(res, [fine[0]])  # one view's upload for two views


def test_texture_ratios_from_the_caller_give_the_same_split():
    """Ratios computed beside the encoder (the service's path) split exactly as those computed inside."""
    res, fine, _, _ = _scene(textured_x=-3.0)
    inside = split_textured(res, fine)
    given_ratios = split_textured(res, fine, ratios=[texture_ratio(f) for f in fine])
    one_given = split_textured(res, fine, ratios=[None, texture_ratio(fine[1])])
    assert inside.stats["split_textured"]["split"] > 0
    for out in (given_ratios, one_given):
        for name in ("means", "scales", "quats", "opacities", "sh"):
            np.testing.assert_array_equal(getattr(out.gaussians, name), getattr(inside.gaussians, name))
        np.testing.assert_array_equal(out.provenance.index, inside.provenance.index)


def test_bad_texture_ratios_are_refused():
    res, fine, _, _ = _scene()
    ratio = texture_ratio(fine[0])
    with pytest.raises(ValueError, match="ratios must be"):
        split_textured(res, fine, ratios=[ratio[:-1], None])
    with pytest.raises(ValueError, match="ratios must be"):
        split_textured(res, [fine[0], None], ratios=[None, ratio])  # a ratio for a view without a fine ERP
    with pytest.raises(ValueError, match="ratios must be"):
        split_textured(res, fine, ratios=[ratio])


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), log_scale=st.floats(-12.0, 6.0), log_range=st.floats(-6.0, 6.0),
       opacity=st.floats(0.0, 1.0))
def test_children_of_any_parent_are_finite_and_near_it(seed, log_scale, log_range, opacity):
    """Random orientations, footprints from about 1e-6 to 400 and ranges from about 0.005 to 1000 (points at the
    camera, huge rooms), any opacity: children stay finite, each within MAX_CHILD_SIGMAS of its parent or at its
    range, opacity in [0, 1]."""
    res, fine, poses, shell = _scene(textured_x=-3.0)
    g = res.gaussians
    front = len(g) - shell
    rng = np.random.default_rng(seed)
    view = res.provenance.decode(len(g))[0][:front]
    q = rng.standard_normal((front, 4))
    scale = np.exp(log_scale) * rng.uniform(0.1, 1.0, (front, 3))
    centre = poses[view, :3, 3]
    means = centre + np.exp(log_range) * (g.means[:front] - centre)
    g2 = g.with_(means=np.concatenate([means, g.means[front:]]).astype(np.float32),
                 quats=np.concatenate([q / np.linalg.norm(q, axis=1, keepdims=True), g.quats[front:]]).astype(np.float32),
                 scales=np.concatenate([scale, g.scales[front:]]).astype(np.float32),
                 opacities=np.concatenate([np.full(front, opacity), g.opacities[front:]]).astype(np.float32))
    out = split_textured(type(res)(g2, res.provenance, res.block, res.index, res.stats), fine)
    assert out.stats["split_textured"]["split"] > 0
    out.gaussians.check_finite()
    kids = out.gaussians.opacities[:len(out.gaussians) - shell]
    assert np.all((kids >= 0) & (kids <= 1))
    pos = out.provenance.flat_index(len(out.gaussians))[:len(out.gaussians) - shell]
    parent_of = np.searchsorted(res.provenance.flat_index(len(g))[:front], pos)
    v = view[parent_of]
    child = out.gaussians.means[:len(pos)].astype(np.float64)
    ratio = (np.linalg.norm(child - poses[v, :3, 3], axis=1)
             / np.linalg.norm(g2.means[parent_of].astype(np.float64) - poses[v, :3, 3], axis=1))
    rot = quat_to_rotmat(g2.quats[parent_of].astype(np.float64))
    local = np.einsum("nji,nj->ni", rot, child - g2.means[parent_of]) / g2.scales[parent_of].astype(np.float64)
    assert np.all((np.linalg.norm(local, axis=1) <= MAX_CHILD_SIGMAS * 1.001) | (np.abs(ratio - 1) < 1e-5))
    np.testing.assert_allclose(1 - (1 - child_opacity(np.array([opacity], np.float32)).astype(np.float64)) ** 2,
                               np.float32(opacity), atol=1e-6)
