"""rasterizer.sweep: pose-dependent graph inputs against independent geometry."""

import numpy as np
import pytest

from rasterizer import geometry as geo
from rasterizer import sweep


def _pose(t, yaw=0.0):
    c, s = np.cos(yaw), np.sin(yaw)
    m = np.eye(4)
    m[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    m[:3, 3] = t
    return m


def _unnormalise(kind, g, h, w):
    """grid_sample (x, y) back to pixel coordinates (col, row) of the unpadded source."""
    if kind == "erp":
        col = (g[..., 0] + 1) * (w + 2 * sweep.ERP_PAD) / 2 - 0.5 - sweep.ERP_PAD
    else:
        col = (g[..., 0] + 1) * w / 2 - 0.5
    return col, (g[..., 1] + 1) * h / 2 - 0.5


def _owner(kind_t, p_src, erp):
    """The source grid a point is sampled in: Yin where its domain holds it, else Yang."""
    if erp:
        return "erp"
    return "yin" if geo.in_grid_domain("yin", p_src) else "yang"


def _unstack(g, h):
    """grid_sample (x, y) in the stacked Yin-over-Yang source -> (x, y) in its own grid."""
    row = (g[..., 1] + 1) * (2 * h + 2) / 2 - 0.5
    row = np.where(row > h + 0.5, row - (h + 2), row)
    return np.stack([g[..., 0], (2 * row + 1) / h - 1], axis=-1)


def test_candidates_uniform_in_inverse_range():
    inv = sweep.inverse_depth_candidates(0.5, 10.0, 5)
    assert inv.dtype == np.float32
    assert np.allclose(inv, [0.1, 0.575, 1.05, 1.525, 2.0])
    with pytest.raises(ValueError):
        sweep.inverse_depth_candidates(2.0, 1.0, 8)


@pytest.mark.parametrize("erp", [False, True])
def test_warp_grids_hit_the_projected_world_point(erp):
    """Every (target pixel, plane) lands where geometry.py projects the same world point."""
    rng = np.random.default_rng(1)
    c2w_a, c2w_b = _pose([0.1, -0.2, 0.3], 0.4), _pose([0.9, 0.1, -0.5], -1.1)
    h, w = (6, 12) if erp else (6, 18)
    inv = sweep.inverse_depth_candidates(0.4, 12.0, 4)
    out = sweep.warp_grids(c2w_a, c2w_b, inv, sweep.grids_for_mode(erp), h, w)
    g = len(sweep.grids_for_mode(erp))
    assert out.shape == (2, g, 4, h, w, 2) and out.dtype == np.float32
    seen = set()
    for direction, (tgt, src) in enumerate(((c2w_a, c2w_b), (c2w_b, c2w_a))):
        for gt, kt in enumerate(sweep.grids_for_mode(erp)):
            for _ in range(20):
                k, r, c = rng.integers(4), rng.integers(h), rng.integers(w)
                ray = geo.grid_directions(kt, h, w)[r, c]
                world = tgt[:3, :3] @ (ray / inv[k]) + tgt[:3, 3]
                p_src = geo.world_to_camera(world, src)
                ks = _owner(kt, p_src, erp)
                seen.add(ks)
                col, row = geo.project_to_grid(ks, p_src, h, w)
                g_xy = out[direction, gt, k, r, c]
                if not erp:
                    assert (g_xy[1] <= 1 / (h + 1) - 1e-6) == (ks == "yin")  # Yin's rows (and its repeated one) on top
                    g_xy = _unstack(g_xy, h)
                    assert np.all(np.abs(g_xy) <= 1 + 1e-5)  # in the owning grid's domain
                gcol, grow = _unnormalise(ks, g_xy, h, w)
                dcol = (gcol - col + w / 2) % w - w / 2 if ks == "erp" else gcol - col
                assert abs(dcol) < 2e-3 * w and abs(grow - row) < 2e-3 * h
    assert seen == ({"erp"} if erp else {"yin", "yang"})


def test_far_plane_with_pure_translation_is_near_identity():
    c2w_b = _pose([0.0, 0.0, 1.0])
    h, w = 8, 24
    inv = sweep.inverse_depth_candidates(0.5, 1e6, 3)
    out = sweep.warp_grids(np.eye(4), c2w_b, inv, ("yin", "yang"), h, w)
    rr, cc = np.mgrid[0:h, 0:w]
    for g, kind in enumerate(("yin", "yang")):
        # each pixel in its own grid, except Yang pixels in the overlap, which Yin's domain holds
        own = np.ones((h, w), dtype=bool) if kind == "yin" else \
            ~geo.in_grid_domain("yin", geo.to_grid_frame("yang", geo.grid_directions("yin", h, w)))
        col, row = _unnormalise("yin", _unstack(out[0, g, 0], h), h, w)
        assert own.mean() > 0.5
        assert np.allclose(col[own], cc[own], atol=1e-3) and np.allclose(row[own], rr[own], atol=1e-3)


def test_sweep_inputs_shapes_and_zero_baseline():
    a, b = np.eye(4), _pose([0.0, 0.0, 1.0])
    si = sweep.sweep_inputs(a, b, near=0.3, far=20, num_planes=6, feature_size=(4, 12))
    assert si["warp_grids"].shape == (2, 2, 6, 4, 12, 2)
    assert si["rel_rt"].shape == (2, 3, 4) and si["c2w"].shape == (2, 4, 4) and si["cam_quats"].shape == (2, 4)
    # rel_rt[0] maps A-camera points to B-camera points: A's centre sits at -1 z in B
    assert np.allclose(si["rel_rt"][0][:, 3], [0, 0, -1])
    with pytest.raises(ValueError, match="coincide"):
        sweep.sweep_inputs(a, a, near=0.3, far=20, num_planes=6, feature_size=(4, 12))


def test_default_near_far_tracks_baseline():
    n1, f1 = sweep.default_near_far(np.eye(4), _pose([0, 0, 1.0]))
    n4, f4 = sweep.default_near_far(np.eye(4), _pose([0, 0, 4.0]))
    assert 0 < n1 < n4 < f1 <= f4
    assert n1 == pytest.approx(sweep.NEAR_PER_BASELINE) and f1 == pytest.approx(20.0)
    # pure proportionality: a globally scaled scene gets the scaled sweep range
    for s in (1e-3, 0.5, 4.0, 1e3):
        n, f = sweep.default_near_far(np.eye(4), _pose([0, 0, s]))
        assert n == pytest.approx(sweep.NEAR_PER_BASELINE * s) and f == pytest.approx(20.0 * s)
    with pytest.raises(ValueError):
        sweep.default_near_far(np.eye(4), _pose([0, 0, 1.0]), near_ratio=2.0, far_ratio=1.0)


def test_warp_grids_are_invariant_to_a_global_similarity():
    """Scaling and rotating both poses (and the default near/far with them) leaves the grids unchanged."""
    a, b = np.eye(4), _pose([0.3, -0.2, 1.0])
    rot = np.eye(4)
    c, s = np.cos(0.7), np.sin(0.7)
    rot[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    out = []
    for scale in (1.0, 1e-3, 1e3):
        m = rot.copy()
        m[:3, :3] *= scale
        pa, pb = m @ a, m @ b
        pa[:3, :3] /= scale
        pb[:3, :3] /= scale
        near, far = sweep.default_near_far(pa, pb)
        out.append(sweep.sweep_inputs(pa, pb, near=near, far=far, num_planes=6, feature_size=(4, 12))["warp_grids"])
    assert np.allclose(out[0], out[1], atol=2e-4) and np.allclose(out[0], out[2], atol=2e-4)


@pytest.mark.parametrize("erp", [False, True])
def test_warp_grids_bit_identical_to_geometry_projection(erp):
    """The fused float32 projection equals normalised_coords(project_to_grid(.)) of the owning grid exactly."""
    a, b = _pose([0.2, -0.1, 0.4], 0.3), _pose([0.8, 0.2, -0.6], -0.9)
    grids = sweep.grids_for_mode(erp)
    h, w = (6, 12) if erp else (6, 18)
    inv = sweep.inverse_depth_candidates(0.3, 20.0, 5)
    out = sweep.warp_grids(a, b, inv, grids, h, w, cache=False)
    ranges = (1.0 / inv).astype(np.float32)[:, None, None, None]
    for direction, (tgt, src) in enumerate(((a, b), (b, a))):
        rel = sweep.relative_pose(tgt, src).astype(np.float32)
        for gt, kt in enumerate(grids):
            pts = (geo.grid_directions(kt, h, w).astype(np.float32) @ rel[:3, :3].T)[None] * ranges + rel[:3, 3]
            if erp:
                want = sweep.normalised_coords("erp", *geo.project_to_grid("erp", pts, h, w), h, w)
            else:
                yin = sweep.in_yin_domain(*np.moveaxis(pts, -1, 0))
                assert yin.any() and not yin.all()
                want = np.where(yin[..., None], sweep.normalised_coords("yin", *geo.project_to_grid("yin", pts, h, w), h, w),
                                sweep.normalised_coords("yang", *geo.project_to_grid("yang", pts, h, w), h, w))
                want[..., 1] = sweep.stacked_rows(want[..., 1], yin, h)
            np.testing.assert_array_equal(out[direction, gt], want)


def test_warp_grid_cache_hits_and_evicts():
    sweep.clear_warp_cache()
    a, b, c = np.eye(4), _pose([0.0, 0.0, 1.0]), _pose([0.5, 0.0, 1.0], 0.2)
    inv = sweep.inverse_depth_candidates(0.3, 20.0, 4)
    first = sweep.warp_grids(a, b, inv, ("yin", "yang"), 4, 12)
    assert not first.flags.writeable
    assert sweep.warp_grids(a, b, inv, ("yin", "yang"), 4, 12) is first
    np.testing.assert_array_equal(first, sweep.warp_grids(a, b, inv, ("yin", "yang"), 4, 12, cache=False))
    # a different pose, size or candidate set is a different entry
    assert sweep.warp_grids(a, c, inv, ("yin", "yang"), 4, 12) is not first
    assert sweep.warp_grids(a, b, inv[:3], ("yin", "yang"), 4, 12).shape[2] == 3
    for i in range(sweep.WARP_CACHE_SIZE + 1):
        sweep.warp_grids(a, _pose([0.0, 0.0, 2.0 + i]), inv, ("yin", "yang"), 4, 12)
    assert sweep.warp_grids(a, b, inv, ("yin", "yang"), 4, 12) is not first  # evicted (LRU)
    sweep.clear_warp_cache()


def test_inverse_range_candidates_and_their_plane_step():
    """Candidates uniform in inverse range; the graph's plane step is their spacing at any range and a
    fractional plane index reads linearly between neighbouring candidates (export.readout)."""
    torch = pytest.importorskip("torch")
    from export.readout import index_to_inverse, plane_step

    b = 1.5
    near, far = sweep.default_near_far(np.eye(4), _pose([b, 0, 0]))
    inv = sweep.inverse_depth_candidates(near, far, 64).astype(np.float64)
    assert inv[0] == pytest.approx(1 / far, rel=1e-5) and inv[-1] == pytest.approx(1 / near, rel=1e-5)
    assert np.ptp(np.diff(inv)) < 1e-4 * np.diff(inv).mean()  # float32 candidates
    at = torch.from_numpy(inv[[0, 30, 63]].reshape(3, 1))
    step = plane_step(at, torch.from_numpy(inv))
    assert step.shape == at.shape
    np.testing.assert_allclose(step.numpy().ravel(), inv[1] - inv[0], rtol=1e-9)
    k = torch.tensor([0.0, 10.5, 63.0], dtype=torch.float64)
    got = index_to_inverse(k, torch.from_numpy(inv)).numpy()
    np.testing.assert_allclose(got, [inv[0], 0.5 * (inv[10] + inv[11]), inv[-1]], rtol=1e-12)
