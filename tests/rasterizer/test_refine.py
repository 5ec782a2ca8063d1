"""+opt refinement: compositing backward (finite differences, torch autograd), colour solve, refine loop."""

from __future__ import annotations

import numpy as np
import pytest

from rasterizer.camera import Camera
from rasterizer.composite import accumulate
from rasterizer.gaussians import Gaussians, rgb_to_sh_dc
from rasterizer.refine import ReferenceView, RefineOptions, reference_views, refine
from rasterizer.refine.backward import BlendOperator, opacity_gradient, suffix_sums
from rasterizer.refine.solver import _Problem
from rasterizer.splat import Footprints

from ._support import toy_scene


def synthetic_footprints(seed: int = 0, n: int = 12, pixels: int = 40, per_pixel: int = 6) -> Footprints:
    """Random per-pixel lists (front to back) with weights g in [0.1, 1]: alpha stays off the 1/255 and 0.99 kinks."""
    rng = np.random.default_rng(seed)
    pix, gid, wt = [], [], []
    depth = rng.permutation(n)  # a global depth order, as the rasterizer sorts by range
    for p in range(pixels):
        k = rng.integers(1, per_pixel + 1)
        ids = rng.choice(n, size=k, replace=False)
        ids = ids[np.argsort(depth[ids])]
        pix += [p] * k
        gid += ids.tolist()
        wt += rng.uniform(0.1, 1.0, size=k).tolist()
    return Footprints(np.array(pix, np.int32), np.array(gid, np.int32), np.array(wt, np.float32),
                      np.ones(n, np.float32), 1, pixels)


def test_suffix_sums_segmented():
    v = np.array([1.0, 2.0, 3.0, 10.0, 20.0, 5.0])
    starts = np.array([0, 3, 5])
    np.testing.assert_allclose(suffix_sums(v, starts), [5.0, 3.0, 0.0, 20.0, 0.0, 0.0])


def _linear_loss(fp, opac, cols, r, s):
    colour, alpha, _ = accumulate(fp, opac, cols)
    return float(np.sum(colour.reshape(-1, 3).astype(np.float64) * r) + np.sum(alpha.reshape(-1) * s))


def test_opacity_gradient_matches_finite_differences():
    rng = np.random.default_rng(1)
    fp = synthetic_footprints(1)
    n = 12
    opac = rng.uniform(0.2, 0.7, n).astype(np.float32)
    cols = rng.uniform(0.0, 1.0, (n, 3)).astype(np.float32)
    r = rng.standard_normal((fp.width, 3))
    s = rng.standard_normal(fp.width)
    _, _, _, terms = accumulate(fp, opac, cols, return_terms=True)
    grad = opacity_gradient(fp, terms, opac, cols, r, s)
    eps = 2e-3
    fd = np.empty(n)
    for i in range(n):  # a loop over parameters for the check only
        up, dn = opac.copy(), opac.copy()
        up[i] += eps
        dn[i] -= eps
        fd[i] = (_linear_loss(fp, up, cols, r, s) - _linear_loss(fp, dn, cols, r, s)) / (2 * eps)
    np.testing.assert_allclose(grad, fd, rtol=2e-2, atol=2e-3 * np.abs(fd).max())


def _torch_composite(torch, fp, opac, cols):
    """Reference front-to-back compositing with the 3DGS rules, a plain loop (tiny inputs)."""
    outs_c, outs_a = [], []
    for p in range(fp.height * fp.width):
        sel = np.flatnonzero(fp.pixel == p)
        t = torch.ones((), dtype=torch.float64)
        c = torch.zeros(3, dtype=torch.float64)
        a_sum = torch.zeros((), dtype=torch.float64)
        for k in sel:
            gi = int(fp.gaussian[k])
            a = torch.clamp(opac[gi] * float(fp.weight[k]), max=0.99)
            if float(a.detach()) < 1 / 255:
                continue
            if float((t * (1 - a)).detach()) < 1e-4:
                break
            c = c + a * t * cols[gi]
            a_sum = a_sum + a * t
            t = t * (1 - a)
        outs_c.append(c)
        outs_a.append(a_sum)
    return torch.stack(outs_c), torch.stack(outs_a)


def test_refine_gradient_matches_torch_autograd():
    """The full refinement loss (alpha-normalised colour, L2, fit mask) against torch autograd."""
    import torch
    rng = np.random.default_rng(2)
    fp = synthetic_footprints(2, n=10, pixels=30, per_pixel=8)
    n = 10
    opac = rng.uniform(0.1, 0.9, n).astype(np.float32)
    dc = rgb_to_sh_dc(rng.uniform(0.1, 0.9, (n, 3)))[:, None, :]
    target = rng.uniform(0, 1, (fp.width, 3)).astype(np.float32)
    fit = rng.random(fp.width) < 0.8
    g = Gaussians(rng.standard_normal((n, 3)), np.ones((n, 3)), np.tile([1.0, 0, 0, 0], (n, 1)), opac, dc)
    cam = Camera("yin", fp.width, 1, np.eye(4))
    view = ReferenceView(cam, fp, target, fit, ~fit)
    prob = _Problem(g, [view], 1)
    fit_loss, _, grad, _ = prob.forward(dc.astype(np.float32), opac, grad=True)

    o_t = torch.tensor(opac.astype(np.float64), requires_grad=True)
    cols = torch.tensor(prob.colours(0, dc).astype(np.float64))
    c, a = _torch_composite(torch, fp, o_t, cols)
    shown = c / a.clamp(min=1 / 255)[:, None]
    mask = torch.tensor(fit, dtype=torch.float64)[:, None]
    loss = ((shown - torch.tensor(target, dtype=torch.float64)) ** 2 * mask).sum() / fit.sum()
    loss.backward()
    assert fit_loss == pytest.approx(loss.item(), rel=1e-4)
    np.testing.assert_allclose(grad, o_t.grad.numpy(), rtol=1e-3, atol=1e-5 * np.abs(grad).max())


def test_blend_operator_reproduces_normalised_render():
    rng = np.random.default_rng(3)
    fp = synthetic_footprints(3)
    opac = rng.uniform(0.2, 0.8, 12).astype(np.float32)
    cols = rng.uniform(0, 1, (12, 3)).astype(np.float32)
    colour, alpha, _, terms = accumulate(fp, opac, cols, return_terms=True)
    op = BlendOperator(fp, terms, 12, normalise=True)
    a = alpha.reshape(-1)
    expect = colour.reshape(-1, 3) / np.maximum(a, 1e-12)[:, None]
    np.testing.assert_allclose(op @ cols.astype(np.float64), expect, rtol=1e-4, atol=1e-5)
    raw = BlendOperator(fp, terms, 12, normalise=False)
    np.testing.assert_allclose(raw @ cols.astype(np.float64), colour.reshape(-1, 3), rtol=1e-4, atol=1e-5)
    # adjoint: <B x, y> == <x, B^T y>
    y = rng.standard_normal((fp.width, 3))
    x = cols.astype(np.float64)
    assert np.sum((op @ x) * y) == pytest.approx(np.sum(x * op.rmatvec(y)), rel=1e-9)


# -- the refinement loop on a small real scene --------------------------------------------------------

def _targets_from(g, c2ws, h):
    """Yin/Yang renders of the true scene, merged back to ERP-like targets through reference_views."""
    from rasterizer.render import render

    return [render(g, c, projection="erp", width=4 * h).colour for c in c2ws]


def test_refine_recovers_perturbed_colours_and_opacities():
    truth = toy_scene(0)
    rng = np.random.default_rng(5)
    c2ws = [np.eye(4), np.eye(4)]
    c2ws[1] = np.eye(4)
    c2ws[1][0, 3] = 0.4
    h = 24
    images = _targets_from(truth, c2ws, h)
    noisy_rgb = np.clip(truth.rgb + rng.normal(0, 0.25, truth.rgb.shape), 0, 1)
    noisy_op = np.clip(truth.opacities * rng.uniform(0.4, 1.0, len(truth)), 0.05, 0.99)
    start = Gaussians(truth.means, truth.scales, truth.quats, noisy_op, rgb_to_sh_dc(noisy_rgb)[:, None, :])
    views = reference_views(start, images, c2ws, height=h, holdout=0.15, seed=0)
    res = refine(start, views, RefineOptions(iterations=30, optimise_opacity=True, cg_steps=4, colour_every=5,
                                                   opacity_lr=0.05, colour_reg=0.05, patience=0))
    hist = res.history
    assert hist[-1]["fit_loss"] < 0.5 * hist[0]["fit_loss"]
    assert hist[-1]["held_loss"] < 0.7 * hist[0]["held_loss"]
    # geometry untouched, only colour/opacity changed
    np.testing.assert_array_equal(res.gaussians.means, start.means)
    np.testing.assert_array_equal(res.gaussians.scales, start.scales)
    assert np.all((res.gaussians.opacities > 0) & (res.gaussians.opacities < 1))
    seen = np.zeros(len(start), bool)
    for v in views:
        seen[v.footprints.gaussian] = True
    err0 = np.abs(start.rgb - truth.rgb)[seen].mean()
    err1 = np.abs(res.gaussians.rgb - truth.rgb)[seen].mean()
    assert err1 < 0.8 * err0


def test_opacity_adam_alone_decreases_loss():
    truth = toy_scene(1)
    c2ws = [np.eye(4), np.eye(4)]
    c2ws[1][2, 3] = 0.4
    h = 16
    images = _targets_from(truth, c2ws, h)
    start = Gaussians(truth.means, truth.scales, truth.quats, np.full(len(truth), 0.3), truth.sh)
    views = reference_views(start, images, c2ws, height=h, holdout=0.0)
    res = refine(start, views, RefineOptions(iterations=20, optimise_opacity=True, cg_steps=0,
                                                   opacity_lr=0.05, patience=0))
    losses = [h_["fit_loss"] for h_ in res.history]
    assert losses[-1] < 0.7 * losses[0]


def test_refine_progress_and_sh_degree_one():
    truth = toy_scene(2, n=300)
    c2ws = [np.eye(4), np.eye(4)]
    c2ws[1][0, 3] = 0.3
    images = _targets_from(truth, c2ws, 12)
    views = reference_views(truth, images, c2ws, height=12)
    seen = []
    res = refine(truth, views, RefineOptions(iterations=5, sh_degree=1, patience=0), progress=seen.append)
    assert res.gaussians.sh.shape == (len(truth), 4, 3)
    assert seen and seen[-1] == pytest.approx(1.0) and all(b >= a for a, b in zip(seen, seen[1:]))
    with pytest.raises(ValueError):
        refine(truth, views, RefineOptions(iterations=1, sh_degree=2))


def test_colour_cg_reduces_held_out_error_and_early_stops():
    truth = toy_scene(3)
    rng = np.random.default_rng(7)
    c2ws = [np.eye(4), np.eye(4)]
    c2ws[1][1, 3] = 0.3
    images = _targets_from(truth, c2ws, 20)
    noisy = np.clip(truth.rgb + rng.normal(0, 0.2, truth.rgb.shape), 0, 1)
    start = Gaussians(truth.means, truth.scales, truth.quats, truth.opacities, rgb_to_sh_dc(noisy)[:, None, :])
    views = reference_views(start, images, c2ws, height=20, holdout=0.2)
    res = refine(start, views, RefineOptions(iterations=40, colour_reg=0.1, patience=3), snapshot_at=(0, 1))
    held = [h["held_loss"] for h in res.history]
    assert min(held) < 0.5 * held[0]
    assert res.history[-1]["iteration"] <= res.best_iteration + 3  # stopped early after the best
    assert set(res.snapshots) == {0, 1}
    np.testing.assert_array_equal(res.snapshots[0].sh, start.sh)
    np.testing.assert_array_equal(res.gaussians.opacities, start.opacities)  # colour mode: opacity untouched


def _two_views(truth, start, offset, h=20):
    c2ws = [np.eye(4), np.eye(4)]
    c2ws[1][0, 3] = offset
    images = _targets_from(truth, c2ws, h)
    return reference_views(start, images, c2ws, height=h, holdout=0.1)


def test_cross_view_guard_rejects_refinement_on_wrong_geometry():
    """Geometry at 1/3 of the true depth: colours fitted on one reference land on the wrong surfaces for the other.

    Small Gaussians with random colours (a detailed room), start colours = the room's mean colour.
    """
    room = toy_scene(4, n=2000)
    truth = Gaussians(room.means, room.scales * (0.15 / 0.35), room.quats, room.opacities, room.sh)
    wrong = Gaussians(truth.means / 3.0, truth.scales / 3.0, truth.quats, truth.opacities,
                      rgb_to_sh_dc(np.tile(truth.rgb.mean(0), (len(truth), 1)))[:, None, :])
    views = _two_views(truth, wrong, 0.8, h=24)
    assert {v.reference for v in views} == {0, 1}
    res = refine(wrong, views, RefineOptions(iterations=10))
    assert res.cross is not None and not res.cross["accepted"] and res.cross["steps"] == 0
    total = np.array(res.cross["total"])  # (steps + 1, scales): cross-view MSE of the scaled single-reference fits
    assert total[1:, 1:].min() > total[0, 0]  # fitting A makes B worse at every step and scale (and vice versa)
    np.testing.assert_array_equal(res.gaussians.sh, wrong.sh)  # the unrefined colours come back
    assert res.best_iteration == 0
    # without the guard the same refinement is accepted by the held-out pixels of the reference views
    plain = refine(wrong, views, RefineOptions(iterations=10, cross_check=False))
    assert plain.best_iteration > 0 and plain.cross is None


def test_cross_view_guard_accepts_refinement_on_right_geometry():
    truth = toy_scene(5)
    rng = np.random.default_rng(3)
    noisy = np.clip(truth.rgb + rng.normal(0, 0.2, truth.rgb.shape), 0, 1)
    start = Gaussians(truth.means, truth.scales, truth.quats, truth.opacities, rgb_to_sh_dc(noisy)[:, None, :])
    views = _two_views(truth, start, 0.8)
    res = refine(start, views, RefineOptions(iterations=10, colour_reg=0.1))
    assert res.cross["accepted"] and res.cross["steps"] >= 1
    total = np.array(res.cross["total"])
    assert total.min() < 0.8 * total[0, 0]
    assert res.best_iteration >= 1 and not np.array_equal(res.gaussians.sh, start.sh)
    for loss in ("huber", "l1"):  # robust variants run through the same guard
        r = refine(start, views, RefineOptions(iterations=3, colour_reg=0.1, loss=loss))
        assert r.cross["accepted"]
    with pytest.raises(ValueError):
        refine(start, views, RefineOptions(iterations=1, loss="l3"))
