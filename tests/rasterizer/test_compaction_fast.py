"""The vectorised smooth merge and the count cap's ranking give what the straightforward formulas give.

``_reference_level1`` is the 2x2 merge as first written (per-member gathers, ``quat_to_rotmat``,
``scale_rotation_from_covariance``); the shipped code works on the block-reshaped layout in
chunks and must decide the same blocks and build the same Gaussians.
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rasterizer import compaction as cp
from rasterizer import geometry as geo
from rasterizer.compaction import CompactionOptions, Provenance, compact_result, maths, merge, smooth_merge_blocks, steps
from rasterizer.depth_gaussians import gaussians_from_depth
from rasterizer.gaussians import (
    SH_C0,
    Gaussians,
    covariance_from_scale_rotation,
    quat_to_rotmat,
    rotmat_to_quat,
    scale_rotation_from_covariance,
)

_DEFAULTS = CompactionOptions()


def _reference_plane_ok(u_w, mu, m2, plane_tol: float, cos_incidence: float) -> np.ndarray:
    """Array-form plane test, the reference for ``rasterizer.compaction.maths.plane_ok_c``: blocks whose centres lie
    on a plane seen at most at the incidence limit.

    Residual = rms distance from the best plane (smallest eigenvalue of the
    scatter), relative to the range of the block's centre; incidence = angle
    between that plane's normal and the ray to the centre. The incidence
    limit also rejects depth steps: a block whose pixels jump in range fits
    a plane almost parallel to the rays.
    """
    lam, normal, ok = maths.smallest_eigenpair(m2 / u_w[:, None])
    rng = np.sqrt(maths.sum3(mu * mu))
    cos_inc = np.abs(maths.sum3(normal * mu)) / np.where(rng > 0, rng, 1.0)
    return ok & (rng > 0) & (lam <= (plane_tol * rng) ** 2) & (cos_inc >= cos_incidence)


def _reference_texture_ok(g: Gaussians, prov: Provenance, alive, tol: float) -> np.ndarray:
    """(P, h/2, w/2) texture test of the 2x2 blocks, block by block: the luma-weighted mean |pixel - bilinear
    prediction from the block means| (a neighbour block with a missing pixel counts as the block itself)
    against ``tol`` x the grid's luma-weighted mean |colour - its mean| over its alive pixels."""
    n_grids, h, w = prov.views * len(prov.grids), prov.height, prov.width
    flat = prov.flat_index(len(g))
    img = np.zeros((prov.full_count, 3), np.float32)
    img[flat] = g.sh[:, 0, :]
    img = img.reshape(n_grids, h, w, 3)
    present = np.zeros(prov.full_count, bool)
    present[flat[alive]] = True
    present = present.reshape(n_grids, h, w)
    h2, w2 = h // 2, w // 2
    pix = [(a, b) for a in range(2) for b in range(2)]
    blk = lambda x, a, b: x[:, a: 2 * h2: 2, b: 2 * w2: 2]  # noqa: E731
    mean = sum(blk(img, a, b) for a, b in pix) / 4
    whole = np.logical_and.reduce([blk(present, a, b) for a, b in pix])
    ii, jj = np.meshgrid(np.arange(h2), np.arange(w2), indexing="ij")
    tex = np.zeros((n_grids, h2, w2), np.float32)
    for a, b in pix:
        ni = np.clip(ii + (1 if a else -1), 0, h2 - 1)  # the nearer block row / column
        nj = np.clip(jj + (1 if b else -1), 0, w2 - 1)

        def along_rows(j):
            nb = np.where(whole[:, ni, j][..., None], mean[:, ni, j], mean[:, ii, j])
            return 0.75 * mean[:, ii, j] + 0.25 * nb
        nb = np.where(whole[:, ii, nj][..., None], along_rows(nj), along_rows(jj))
        pred = 0.75 * along_rows(jj) + 0.25 * nb
        tex += np.abs(blk(img, a, b) - pred) @ merge.LUMA / 4
    ok = np.zeros((n_grids, h2, w2), bool)
    for p in range(n_grids):
        px = img[p][present[p]]
        contrast = np.abs(px - px.mean(axis=0)).mean(axis=0) @ merge.LUMA if px.size else 0.0
        ok[p] = whole[p] & (tex[p] <= np.float32(tol) * np.float32(contrast))
    return ok


def _reference_level1(g: Gaussians, prov: Provenance, alive, colour_tol=_DEFAULTS.smooth_colour_tol,
                      opacity_tol=_DEFAULTS.smooth_opacity_tol, plane_tol=_DEFAULTS.smooth_plane_tol,
                      max_incidence_deg=_DEFAULTS.smooth_max_incidence_deg):
    """(drop mask, merged Gaussians, top-left layout positions) of the 2x2 merge, block by block formulas."""
    n = len(g)
    flat = prov.flat_index(n)
    h, w = prov.height, prov.width
    cam_of_plane = np.repeat(prov.c2w[:, :3, 3], len(prov.grids), axis=0)
    slot = np.full(prov.full_count, -1, dtype=np.int64)
    slot[flat[alive]] = np.flatnonzero(alive)
    blocks = merge._blocks(slot.reshape(-1, h, w))
    shape = blocks.shape[:3]
    blocks = blocks.reshape(-1, 4)
    cand = np.flatnonzero(np.all(blocks >= 0, axis=1))
    members, cam = blocks[cand], cam_of_plane[cand // (shape[1] * shape[2])]
    cos_inc = float(np.cos(np.radians(max_incidence_deg)))
    pitch = (np.pi if prov.grids[0] == "erp" else 2 * geo.YIN_LAT_MAX) / h
    dc = g.sh[:, 0, :]
    c = [dc[members[:, k]] for k in range(4)]
    cmin, cmax = np.minimum.reduce(c), np.maximum.reduce(c)
    ok = maths.max3(cmax - cmin) <= np.float32(colour_tol / SH_C0)
    ok &= _reference_texture_ok(g, prov, alive, merge.TEXTURE_TOL).reshape(-1)[cand]
    o = [g.opacities[members[:, k]] for k in range(4)]
    amin, amax = np.minimum.reduce(o), np.maximum.reduce(o)
    ok &= amax - amin <= np.float32(opacity_tol)
    idx = np.flatnonzero(ok)
    m, cam = members[idx], cam[idx]
    a, area, pos = [], [], []
    for k in range(4):
        sc = g.scales[m[:, k]].astype(np.float64)
        area.append(sc[:, 0] * sc[:, 1] * sc[:, 2] / np.maximum(maths.min3(sc), 1e-300))
        a.append(g.opacities[m[:, k]].astype(np.float64))
        pos.append(g.means[m[:, k]].astype(np.float64) - cam)
    wk = [a[k] * area[k] for k in range(4)]
    wt = sum(wk)
    wsafe = np.where(wt > 0, wt, 1.0)
    mu = sum(wk[k][:, None] * pos[k] for k in range(4)) / wsafe[:, None]
    m2 = sum(maths.outer6(pos[k] - mu, wk[k]) for k in range(4))
    sel = np.flatnonzero((wt > 0) & _reference_plane_ok(wsafe, mu, m2, plane_tol, cos_inc))
    sub = g.subset(m[sel].T.ravel())
    rot = quat_to_rotmat(sub.quats)
    rs = rot * (sub.scales.astype(np.float64) ** 2)[:, None, :]
    cov_all = np.stack([maths.sum3(rs[:, i, :] * rot[:, j, :]) for i, j in maths.SYM], axis=1)
    w_all = np.concatenate([wk[k][sel] for k in range(4)])
    rng_all = np.sqrt(np.concatenate([maths.sum3(pos[k][sel] ** 2) for k in range(4)]))
    depth_all = (merge._render_area(sub.scales.astype(np.float64), rng_all * pitch)
                 * cp.opacity_depth(sub.opacities.astype(np.float64)))

    def per_block(x):
        return x.reshape((4, sel.size) + x.shape[1:]).sum(0)

    wb, mub, m2b = wt[sel], mu[sel], m2[sel]
    covb = per_block(w_all[:, None] * cov_all)
    shb = per_block(w_all[:, None, None] * sub.sh.astype(np.float64))
    depth = per_block(depth_all)
    cov = maths.sym_full((covb + m2b) / wb[:, None])
    # in-plane widening to MIN_OVERLAP of the 2x2 block's size (plane normal = smallest axis of the spread)
    spread = maths.sym_full(m2b / wb[:, None])
    nrm = np.linalg.eigh(spread)[1][:, :, 0]
    along = lambda c: np.einsum("ni,nij,nj->n", nrm, c, nrm)  # noqa: E731
    inplane = lambda c: np.trace(c, axis1=1, axis2=2) - along(c)  # noqa: E731
    delta = np.maximum(cp.MIN_OVERLAP**2 * 12.0 * 4 / 3 * inplane(spread) - inplane(cov), 0.0) / 2
    cov = cov + delta[:, None, None] * (np.eye(3) - np.einsum("ni,nj->nij", nrm, nrm))
    rngb = np.sqrt(maths.sum3(mub * mub))
    scales, quats = scale_rotation_from_covariance(cov, min_scale=1e-12)
    scales = np.maximum(scales, 1e-9 * rngb[:, None])
    need = depth / np.maximum(merge._render_area(scales, rngb * pitch), 1e-300)
    merged = Gaussians(mub + cam[sel], scales, quats, cp.opacity_for_depth(need), shb / wb[:, None, None])
    chosen = cand[idx[sel]]
    plane, pix = np.divmod(chosen, shape[1] * shape[2])
    bi, bj = np.divmod(pix, shape[2])
    top = (plane * h + 2 * bi) * w + 2 * bj
    drop = np.zeros(n, dtype=bool)
    drop[slot[np.concatenate([top, top + 1, top + w, top + w + 1])]] = True
    return drop, merged, top


def room(h=32, seed=0, views=2):
    """Every Yin and Yang pixel of ``views`` references inside a box room (a full layout, index None),
    with noisy patches (depth, colour, opacity) so that all of the merge's tests reject some blocks."""
    rng = np.random.default_rng(seed)
    w = 3 * h
    parts, poses = [], []
    for v in range(views):
        c2w = np.eye(4)
        c2w[:3, 3] = [0.3 * v, -0.1, 0.2 * v]
        for kind in ("yin", "yang"):
            d = geo.grid_directions(kind, h, w) @ np.eye(3)
            r = 2.0 / np.max(np.abs(d) * np.array([1.0, 0.8, 1.3]), axis=-1)
            noisy = rng.random((h, w)) < 0.15
            r = np.where(noisy, r * (1 + 0.05 * rng.standard_normal((h, w))), r)
            img = np.empty((h, w, 3), np.float32)
            img[..., 0] = 0.45 + 0.1 * d[..., 0]
            img[..., 1] = 0.5 + 0.05 * d[..., 1]
            img[..., 2] = np.where(rng.random((h, w)) < 0.1, rng.random((h, w)), 0.35)
            g = gaussians_from_depth(img, r, c2w, kind, scale_factor=0.75, thickness=0.1, opacity=0.6)
            assert len(g) == h * w
            parts.append(g)
        poses.append(c2w)
    g = Gaussians.concatenate(parts)
    # random rotations about the normal and a little scale jitter: covariances that are not axis-aligned
    q = g.quats.astype(np.float64) + 0.05 * rng.standard_normal(g.quats.shape)
    opa = np.where(rng.random(len(g)) < 0.05, 0.95, 0.6)
    g = g.with_(quats=q, scales=g.scales * rng.uniform(0.95, 1.05, g.scales.shape), opacities=opa)
    return g, Provenance(("yin", "yang"), h, w, np.stack(poses))


def _assert_same(sm, drop, merged, top):
    """The same blocks and Gaussians; quaternions as the covariances they give (the eigenvectors' signs are a
    free choice: a quaternion and its turns by 180 degrees about a principal axis give one Gaussian)."""
    np.testing.assert_array_equal(sm.drop, drop)
    np.testing.assert_array_equal(sm.index, top)
    for f in ("means", "scales", "opacities", "sh"):
        np.testing.assert_allclose(getattr(sm.gaussians, f), getattr(merged, f), rtol=1e-6, atol=1e-7, err_msg=f)
    cov, want = sm.gaussians.covariances(), merged.covariances()
    size = np.abs(want).max(axis=(1, 2))
    assert (np.abs(cov - want).max(axis=(1, 2)) <= 1e-6 * size).all()


@pytest.mark.parametrize("seed", [0, 1])
def test_full_layout_merge_matches_reference(seed):
    g, prov = room(seed=seed)
    alive = np.random.default_rng(seed).random(len(g)) > 0.02
    sm = smooth_merge_blocks(g, prov, alive, levels=1)
    drop, merged, top = _reference_level1(g, prov, alive)
    assert 0 < len(merged) < len(g) // 4  # the noise rejects some blocks, the walls merge
    _assert_same(sm, drop, merged, top)


def test_partial_layout_merge_matches_reference():
    g, prov = room(seed=3)
    keep = np.random.default_rng(3).random(len(g)) > 0.1
    idx = np.flatnonzero(keep)
    gp = g.subset(idx)
    pp = Provenance(prov.grids, prov.height, prov.width, prov.c2w, idx)
    alive = np.ones(len(gp), bool)
    sm = smooth_merge_blocks(gp, pp, alive, levels=1)
    drop, merged, top = _reference_level1(gp, pp, alive)
    assert len(merged) > 0
    _assert_same(sm, drop, merged, top)


def test_compact_result_order_matches_argsort_assembly():
    g, prov = room(seed=4)
    res = compact_result(g, prov, CompactionOptions())
    assert np.all(np.diff(res.provenance.index) > 0)
    kept = res.block == 1
    np.testing.assert_array_equal(res.gaussians.means[kept], g.means[res.index])
    np.testing.assert_array_equal(res.provenance.index[kept], res.index)  # full layout: position = input index


def test_footprint_and_ranges_match_plain_formulas():
    g, prov = room(seed=5)
    s = np.sort(g.scales.astype(np.float64), axis=1)
    np.testing.assert_array_equal(cp.footprint(g), np.sqrt(s[:, 1] * s[:, 2]))
    view = prov.decode(len(g))[0]
    np.testing.assert_array_equal(steps._view_of(prov, len(g)), view)
    np.testing.assert_array_equal(steps._ranges_from_own_camera(g, view, prov.c2w),
                                  np.linalg.norm(g.means.astype(np.float64) - prov.c2w[view, :3, 3], axis=1))


def test_quaternion_helpers_match_gaussians_module():
    rng = np.random.default_rng(6)
    a = rng.standard_normal((500, 3, 3))
    cov6 = np.stack([(a @ a.transpose(0, 2, 1))[:, i, j] for i, j in maths.SYM], axis=1)
    cov6[:5, 3:] = 0.0  # diagonal ones (the quaternion's other branches)
    cov6[5:10, :3] = 1.0
    cov6[10:15] = (2.0, 2.0, 2.0, 0.0, 0.0, 0.0)  # isotropic: every axis is an eigenvector
    cov6[15:20] = (1.0, 1.0, 3.0, 0.0, 0.0, 0.0)  # a repeated pair
    cov6[20:25] = (2.0, 2.0, 2.0, 1.0, 1.0, 1.0)  # (4, 1, 1): a repeated pair, not axis-aligned
    s_ref, q_ref = scale_rotation_from_covariance(maths.sym_full(cov6))
    s, q = maths.scale_rotation6(cov6, 1e-12)
    full = maths.sym_full(cov6)
    np.testing.assert_allclose(s**2, s_ref**2, rtol=0, atol=1e-13 * np.abs(full).max())  # eigenvalues, to rounding
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, rtol=1e-12)
    assert (q[:, 0] >= 0).all()
    # the same Gaussians (rows 5-9 are not PSD: both floor their negative eigenvalues)
    np.testing.assert_allclose(covariance_from_scale_rotation(s, q), covariance_from_scale_rotation(s_ref, q_ref), rtol=0,
                               atol=1e-12 * np.abs(full).max())
    evals, vecs = maths.sym3_eigh(cov6)
    np.testing.assert_allclose(evals, np.linalg.eigh(full)[0], rtol=0, atol=1e-13 * np.abs(full).max())
    np.testing.assert_allclose(np.einsum("nji,njk->nik", vecs, vecs), np.broadcast_to(np.eye(3), full.shape), atol=1e-14)
    rot = quat_to_rotmat(rng.standard_normal((500, 4)))
    np.testing.assert_array_equal(maths.rotmat_to_quat(rot), rotmat_to_quat(rot))


@settings(max_examples=60, deadline=None)
@given(log_s=st.lists(st.floats(-8, 4), min_size=3, max_size=3), seed=st.integers(0, 10_000),
       flat=st.integers(0, 3))
def test_closed_form_eigh_round_trips_extreme_and_degenerate_covariances(log_s, seed, flat):
    """The merged blocks' scale_rotation6 on covariances of scales from 1e-8 to 1e4 (anisotropy up to 1e12),
    ``flat`` of them zero (rank-deficient): finite, unit quaternions, the covariance back to eps * |cov|, and the
    scales as accurate as LAPACK's (to sqrt(eps) * s_max for the small ones)."""
    rng = np.random.default_rng(seed)
    s = 10.0 ** np.array([log_s])
    s[0, :flat] = 0.0
    q = rng.standard_normal((1, 4))
    q /= np.linalg.norm(q)
    cov = covariance_from_scale_rotation(s, q)
    cov6 = np.stack([cov[:, i, j] for i, j in maths.SYM], axis=1)
    s2, q2 = maths.scale_rotation6(cov6, 0.0)
    assert np.isfinite(s2).all() and np.isfinite(q2).all()
    np.testing.assert_allclose(np.linalg.norm(q2, axis=1), 1.0, rtol=1e-12)
    cov2 = covariance_from_scale_rotation(s2, q2)
    np.testing.assert_allclose(cov2, cov, rtol=0, atol=1e-12 * s.max() ** 2 + 1e-30)
    np.testing.assert_allclose(np.sort(s2[0]), np.sort(s[0]), rtol=1e-4, atol=1e-7 * s.max())


@pytest.mark.parametrize("shape", [(3, 4, 32, 96), (3, 2, 7, 13), (1, 1, 2, 2)])
def test_block_means_are_numpys_mean_bit_for_bit(shape):
    """The texture test's 2x2 block means add four strided views in the order numpy's mean over the block
    axes does: the same bits (odd last row / column left out), and the block masks the same booleans."""
    rng = np.random.default_rng(7)
    x = (rng.random(shape) * rng.choice([1e-3, 1.0, 1e3], shape)).astype(np.float32)
    c, g, h, w = shape
    want = x[:, :, : h // 2 * 2, : w // 2 * 2].reshape(c, g, h // 2, 2, w // 2, 2).mean(axis=(3, 5))
    np.testing.assert_array_equal(merge._means2(x), want)
    p = rng.random(shape[1:]) < 0.8
    want_p = p[:, : h // 2 * 2, : w // 2 * 2].reshape(g, h // 2, 2, w // 2, 2).all(axis=(2, 4))
    np.testing.assert_array_equal(merge._all2(p), want_p)


def test_opacity_depth_is_numpys_interp_bit_for_bit():
    """The table lookup finds its interval from the even spacing and keeps np.interp's arithmetic: the same
    bits at, between and beside the table's points, beyond its ends and for NaN, in float64 and float32."""
    x_tab, y_tab = merge._LI2_X, merge._LI2_Y
    rng = np.random.default_rng(8)
    a = np.concatenate([rng.random(100_000) * 1.2 - 0.1, x_tab, np.nextafter(x_tab, 1.0), np.nextafter(x_tab, 0.0),
                        [0.0, 0.99, 1.0, -0.5, np.nan, np.inf, -np.inf]])
    for x in (a, a.astype(np.float32)):
        want = np.interp(np.clip(x, 0.0, merge.MERGED_OPACITY_MAX), x_tab, y_tab)
        np.testing.assert_array_equal(cp.opacity_depth(x), want)
