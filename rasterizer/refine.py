"""+opt: refine the colour (SH) and opacity of Gaussians against their reference views.

OmniSplat+opt (paper Sec. 4.1 / Supp. A) starts from the feed-forward Gaussians
and optimises only colour and opacity on the two reference views, positions
and covariances fixed. Here the loss lives on the Yin and Yang images of each
reference (targets = :func:`rasterizer.yin_yang.erp_to_yin_yang` of the
reference ERP at the working size; no lossy ERP merge inside the loop).

Geometry is fixed, so :func:`rasterizer.splat.footprints` runs once per grid
(opacity-free footprints, valid for any opacity) and every iteration only
re-composites them (:func:`rasterizer.composite.accumulate`).

Method (chosen by measurement on m3d, encoder Gaussians, see ``docs/bench/refine.md``):

* Loss: squared error of the *alpha-normalised* colour C/A (what the ERP
  renderer shows after its Yin/Yang merge) on the fitted reference pixels.
  L2 makes the colour sub-problem a linear least-squares problem.
* Colour (default, ``optimise_opacity=False``): with opacities fixed, C/A is
  linear in the SH coefficients
  (:class:`~rasterizer.composite_backward.BlendOperator`); one iteration is
  one Jacobi-preconditioned conjugate-gradient step on the normal equations,
  with a Tikhonov pull ``colour_reg`` toward the initial colours (the problem
  is under-determined: ~N Gaussians vs fewer reference pixels). The first
  step (a per-Gaussian weighted back-projection of the residual) gave
  +1.6 dB at the m3d target; later steps deconvolve and overfit (target and
  held-out pixels agree), so the held-out early stop returns step 1-2.
* Opacity (``optimise_opacity=True``): Adam on logit(opacity) with the exact
  numpy backward of front-to-back compositing
  (:func:`~rasterizer.composite_backward.opacity_gradient`), colour re-solved
  every ``colour_every`` iterations. Measured: no held-out or target gain
  over the colour step, ~10x the cost per iteration, so it is off by default.
* Overfitting guard: a random ``holdout`` fraction of the reference pixels is
  never fitted; its loss is tracked every iteration and the parameters with
  the best held-out loss are returned (early stop after ``patience``
  iterations without improvement).

Shapes: Gaussians N; per grid P = h * 3h pixels; M contributions.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import numpy as np

from .camera import Camera
from .composite import accumulate
from .composite_backward import BlendOperator, opacity_gradient
from .gaussians import Gaussians
from .geometry import as_c2w
from .sh import sh_basis
from .splat import Footprints, footprints
from .yin_yang import erp_to_yin_yang

_EPS_LOGIT = 1e-4
_A_FLOOR = 1.0 / 255.0


@dataclass(frozen=True)
class ReferenceView:
    """One Yin or Yang grid of one reference panorama.

    camera: the grid's Camera; footprints: fixed-geometry contributions;
    target (P, 3) float32 reference colours; fit / held (P,) bool: pixels
    fitted and held out (disjoint).
    """

    camera: Camera
    footprints: Footprints
    target: np.ndarray
    fit: np.ndarray
    held: np.ndarray
    reference: int = 0  # which reference panorama the grid belongs to (cross-view guard)


@dataclass(frozen=True)
class RefineOptions:
    """Knobs of :func:`refine` (defaults = the measured choice)."""

    iterations: int = 100
    sh_degree: int = 0            # 0: DC only; 1: also degree-1 SH (needs colour_reg; two views only)
    optimise_opacity: bool = False  # False: `iterations` CG steps on colour; True: Adam steps on opacity
    colour_every: int = 3         # opacity mode: re-solve colour every k iterations (0: only at the start)
    cg_steps: int = 1             # opacity mode: CG steps per colour solve
    colour_reg: float = 2.0       # Tikhonov weight toward the initial SH (relative to the mean data weight)
    opacity_lr: float = 0.01      # Adam step on logit opacity
    opacity_reg: float = 1e-4     # pull of logit opacity toward its initial value
    patience: int = 5             # early stop after this many iterations without held-out improvement (0: off)
    cross_check: bool = True      # colour mode: fit each reference alone, score the other (cross-view guard)
    loss: str = "l2"              # "l2" | "huber" | "l1": robust variants as fixed IRLS weights (initial residual)
    huber_delta: float = 0.1      # Huber threshold on the per-pixel colour error (RGB norm, [0, 1] units)


@dataclass
class RefineResult:
    """Refined Gaussians and the per-iteration history (dicts: iteration, fit_loss, held_loss, seconds)."""

    gaussians: Gaussians
    history: list[dict] = field(default_factory=list)
    best_iteration: int = 0
    seconds: float = 0.0
    snapshots: dict = field(default_factory=dict)  # iteration -> Gaussians (for benches)
    cross: dict | None = None  # cross-view guard: curves, chosen steps, accepted, seconds (None: not run)


def reference_views(gaussians: Gaussians, images: Sequence[np.ndarray], c2ws: Sequence, *, height: int,
                    holdout: float = 0.1, seed: int = 0, near: float | None = None,
                    prune_transmittance: float = 1e-3) -> list[ReferenceView]:
    """Yin and Yang views (h = ``height``, w = 3h) of each reference ERP image (H, W, 3) in [0, 1].

    The ERP is resampled to the grids by ``erp_to_yin_yang(image, height=h)``;
    footprints are computed once, without an opacity bound (opacities may grow).
    ``prune_transmittance`` > 0 drops the contributions that sit behind
    transmittance below it at the initial opacities (a suffix of each pixel's
    list: deeply occluded surfaces the refinement could only reveal by making
    the ones in front nearly transparent); this cuts the work per iteration.
    """
    rng = np.random.default_rng(seed)
    views = []
    for ref, (image, c2w) in enumerate(zip(images, c2ws)):
        img = np.asarray(image)
        img = img.astype(np.float32) / 255.0 if img.dtype == np.uint8 else img.astype(np.float32)
        yin, yang = erp_to_yin_yang(img, height=height)
        for kind, tgt in (("yin", yin), ("yang", yang)):
            kw = {} if near is None else {"near": near}
            cam = Camera(kind, 3 * height, height, as_c2w(c2w), **kw)
            fp = footprints(gaussians, cam)
            if prune_transmittance > 0:
                fp = prune_occluded(fp, gaussians, prune_transmittance)
            p = height * 3 * height
            held = rng.random(p) < holdout
            views.append(ReferenceView(cam, fp, np.clip(tgt.reshape(p, 3), 0.0, 1.0), ~held, held, ref))
    return views


def prune_occluded(fp: Footprints, gaussians: Gaussians, min_transmittance: float) -> Footprints:
    """Footprints without the contributions whose transmittance at the current opacities is below the bound."""
    if len(fp) == 0:
        return fp
    colours = np.zeros((len(gaussians), 3), np.float32)
    *_, terms = accumulate(fp, gaussians.opacities, colours, return_terms=True)
    keep = terms.transmittance >= np.float32(min_transmittance)
    return Footprints(fp.pixel[keep], fp.gaussian[keep], fp.weight[keep], fp.ranges, fp.height, fp.width)


# -- colour parameterisation ---------------------------------------------------------------------------

def _view_basis(gaussians: Gaussians, camera: Camera, k: int) -> np.ndarray:
    """SH basis (N, k) of the directions from the camera centre to each Gaussian."""
    if k == 1:
        from .sh import SH_C0
        return np.full((len(gaussians), 1), SH_C0, np.float32)
    d = gaussians.means.astype(np.float64) - camera.centre
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-30)
    return sh_basis(d, k)


def _colours(basis: np.ndarray, sh: np.ndarray, rest: np.ndarray | None) -> np.ndarray:
    """Colours (N, 3) = 0.5 + sum_k Y_k sh_k (+ fixed higher bands), not clamped."""
    c = np.einsum("nk,nkc->nc", basis, sh) + 0.5
    return c if rest is None else c + rest


def _logit(o: np.ndarray) -> np.ndarray:
    o = np.clip(o.astype(np.float64), _EPS_LOGIT, 1 - _EPS_LOGIT)
    return np.log(o) - np.log1p(-o)


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * x))


class _Problem:
    """The refinement problem: views, fixed colour bands, loss and gradients."""

    def __init__(self, gaussians: Gaussians, views: Sequence[ReferenceView], k: int) -> None:
        self.g = gaussians
        self.views = list(views)
        self.k = k
        self.n = len(gaussians)
        k_all = gaussians.sh.shape[1]
        self.bases = [_view_basis(gaussians, v.camera, k) for v in self.views]
        # higher SH bands than the refined ones stay fixed: their colour is a per-view constant
        self.rest = []
        for v in self.views:
            if k_all > k:
                full = _view_basis(gaussians, v.camera, k_all)
                self.rest.append(np.einsum("nk,nkc->nc", full[:, k:], gaussians.sh[:, k:]))
            else:
                self.rest.append(None)
        self.n_fit = max(1, sum(int(v.fit.sum()) for v in self.views))
        self.n_held = max(1, sum(int(v.held.sum()) for v in self.views))

    def colours(self, i: int, sh: np.ndarray) -> np.ndarray:
        return np.maximum(_colours(self.bases[i], sh, self.rest[i]), 0.0).astype(np.float32)

    def forward(self, sh: np.ndarray, opac: np.ndarray, *, grad: bool):
        """Loss on fit and held pixels, and (if grad) dL/d opacity (N,) of the fit loss."""
        fit_sse = held_sse = 0.0
        g_opac = np.zeros(self.n, np.float64) if grad else None
        terms_all = []
        for i, v in enumerate(self.views):
            cols = self.colours(i, sh)
            colour, alpha, _, terms = accumulate(v.footprints, opac, cols, return_terms=True)
            c = colour.reshape(-1, 3).astype(np.float64)
            a = alpha.reshape(-1).astype(np.float64)
            ok = a >= _A_FLOOR
            inv = np.where(ok, 1.0 / np.maximum(a, _A_FLOOR), 0.0)
            shown = c * inv[:, None]
            err = shown - v.target
            e2 = np.einsum("pc,pc->p", err, err)
            fit_sse += float(e2[v.fit].sum())
            held_sse += float(e2[v.held].sum())
            terms_all.append(terms)
            if grad:
                gs = np.where(v.fit, 2.0 / self.n_fit, 0.0)[:, None] * err  # dL/d shown
                gc = gs * inv[:, None]
                ga = -np.einsum("pc,pc->p", gs, shown) * inv
                g_opac += opacity_gradient(v.footprints, terms, opac, cols, gc, ga)
        return fit_sse / self.n_fit, held_sse / self.n_held, g_opac, terms_all

    def solve_colour(self, sh: np.ndarray, sh0: np.ndarray, terms_all, steps: int, reg: float,
                     on_step: Callable[[int, np.ndarray, float], bool] | None = None, *, loss: str = "l2",
                     delta: float = 0.1, report_start: bool = False) -> np.ndarray:
        """Jacobi-preconditioned CG on the normal equations of the L2 colour fit (opacities fixed).

        Minimises sum_v |M_v (B_v colour_v(x) - y_v)|^2 + lam |x - sh0|^2 over the
        refined SH x (N, k, 3), warm-started at ``sh``; ``lam`` = ``reg`` times the
        mean data weight of a seen Gaussian. ``on_step(step, x, held_loss)`` is
        called after every step (held_loss: mean squared error on the held-out
        pixels, one sparse product per view); it returns True to stop.
        ``report_start``: also call it once before the first step (step -1).
        ``loss`` "huber" / "l1": the fitted pixels are re-weighted once by the
        IRLS weight of their initial residual norm e (huber: min(1, delta / e);
        l1: delta / max(e, delta)), so the solve stays linear.
        """
        ops = [BlendOperator(v.footprints, t, self.n, normalise=True) for v, t in zip(self.views, terms_all)]
        masks = [(v.fit & op.covered).astype(np.float64)[:, None] for v, op in zip(self.views, ops)]
        if loss not in ("l2", "huber", "l1"):
            raise ValueError(f"loss must be 'l2', 'huber' or 'l1', got {loss!r}")
        if loss != "l2":
            for i, v in enumerate(self.views):
                pred = ops[i] @ _colours(self.bases[i], sh.astype(np.float64), self.rest[i])
                e = np.sqrt(np.einsum("pc,pc->p", pred - v.target, pred - v.target))
                w = np.minimum(1.0, delta / np.maximum(e, 1e-12)) if loss == "huber" else delta / np.maximum(e, delta)
                masks[i] = masks[i] * w[:, None]
        active = [bool(m.any()) for m in masks]  # views with fitted pixels (the others are only scored)
        k = self.k

        def apply_j(i, x):  # (N, k, 3) -> (P, 3)
            return ops[i] @ np.einsum("nk,nkc->nc", self.bases[i], x)

        def apply_jt(i, r):  # (P, 3) -> (N, k, 3)
            return self.bases[i][:, :, None] * ops[i].rmatvec(r)[:, None, :]

        def held_loss(x):
            tot = 0.0
            for i, v in enumerate(self.views):
                pred = ops[i] @ np.maximum(_colours(self.bases[i], x, self.rest[i]), 0.0)
                e = (pred - v.target)[v.held]
                tot += float(np.einsum("pc,pc->", e, e))
            return tot / self.n_held

        diag = np.zeros((self.n, k), np.float64)
        for i, op in enumerate(ops):
            if not active[i]:
                continue
            csq = op.matrix.power(2).T @ masks[i][:, 0]
            diag += csq[:, None] * self.bases[i].astype(np.float64) ** 2
        seen = diag[:, 0] > 0
        lam = reg * (float(diag[seen, 0].mean()) if seen.any() else 1.0)
        precond = 1.0 / (diag + lam)[:, :, None]

        def normal(x):
            out = lam * x
            for i in range(len(ops)):
                if active[i]:
                    out = out + apply_jt(i, masks[i] * apply_j(i, x))
            return out

        x = sh.astype(np.float64)
        b = -lam * (x - sh0)  # residual of the normal equations at x
        for i, v in enumerate(self.views):
            if active[i]:
                pred = ops[i] @ _colours(self.bases[i], x, self.rest[i])
                b = b + apply_jt(i, masks[i] * (v.target - pred))
        if report_start and on_step is not None and on_step(-1, self._project(x), held_loss(self._project(x))):
            return self._project(x)
        r = b
        z = precond * r
        p = z.copy()
        rz = np.einsum("nkc,nkc->c", r, z)
        for step in range(steps):
            ap = normal(p)
            pap = np.einsum("nkc,nkc->c", p, ap)
            alpha = np.where(pap > 0, rz / np.where(pap > 0, pap, 1.0), 0.0)
            x = x + alpha * p
            r = r - alpha * ap
            z = precond * r
            rz_new = np.einsum("nkc,nkc->c", r, z)
            beta = np.where(rz > 0, rz_new / np.where(rz > 0, rz, 1.0), 0.0)
            p = z + beta * p
            rz = rz_new
            if on_step is not None and on_step(step, self._project(x), held_loss(self._project(x))):
                break
        return self._project(x)

    def _project(self, x: np.ndarray) -> np.ndarray:
        if self.k == 1:  # DC only: keep the colour in [0, 1]
            from .sh import SH_C0
            return np.clip(x, -0.5 / SH_C0, 0.5 / SH_C0)
        return x


def refine(gaussians: Gaussians, views: Sequence[ReferenceView], options: RefineOptions = RefineOptions(),
           progress: Callable[[float], None] | None = None, *, snapshot_at: Sequence[int] = ()) -> RefineResult:
    """Refine colour and opacity of ``gaussians`` on ``views``; geometry unchanged.

    ``progress(fraction)`` is called after every iteration. Returns the
    parameters with the best held-out loss (the last ones when no pixel is
    held out) and a history of losses and elapsed seconds. ``snapshot_at``
    (colour-only mode): iterations whose parameters are also returned in
    ``snapshots``.
    """
    t0 = time.perf_counter()
    opt = options
    if opt.sh_degree not in (0, 1):
        raise ValueError(f"sh_degree must be 0 or 1, got {opt.sh_degree}")
    k = (opt.sh_degree + 1) ** 2
    k_all = max(k, gaussians.sh.shape[1])
    sh_all = np.zeros((len(gaussians), k_all, 3), np.float32)
    sh_all[:, : gaussians.sh.shape[1]] = gaussians.sh
    g = replace(gaussians, sh=sh_all)
    prob = _Problem(g, views, k)
    sh0 = sh_all[:, :k].astype(np.float64)
    sh = sh0.copy()
    logit0 = _logit(g.opacities)
    logit = logit0.copy()
    m1 = np.zeros_like(logit)
    m2 = np.zeros_like(logit)
    b1, b2 = 0.9, 0.999

    history: list[dict] = []
    has_held = any(v.held.any() for v in views)
    fit, held, g_opac, terms = prob.forward(sh.astype(np.float32), _sigmoid(logit).astype(np.float32),
                                            grad=opt.optimise_opacity and opt.iterations > 0)
    history.append({"iteration": 0, "fit_loss": fit, "held_loss": held if has_held else None, "seconds": time.perf_counter() - t0})
    best = [held if has_held else fit, 0, sh.copy(), logit.copy()]

    snap_set = set(int(i) for i in snapshot_at)
    snapshots: dict = {}

    def _with(x, lg):
        sh_out = sh_all.copy()
        sh_out[:, :k] = x.astype(np.float32)
        opac = _sigmoid(lg).astype(np.float32) if opt.optimise_opacity else g.opacities
        return replace(g, sh=sh_out, opacities=opac)

    if 0 in snap_set:
        snapshots[0] = _with(sh, logit)
    if not opt.optimise_opacity:
        # colour only: one composite at the initial opacities, then `iterations` CG steps
        def on_step(step, x, held_loss):
            it = step + 1
            history.append({"iteration": it, "fit_loss": None, "held_loss": held_loss if has_held else None,
                            "seconds": time.perf_counter() - t0})
            if has_held and held_loss < best[0]:
                best[:] = [held_loss, it, x.copy(), logit]
            elif not has_held:
                best[:] = [0.0, it, x.copy(), logit]
            if it in snap_set:
                snapshots[it] = _with(x, logit)
            if progress is not None:
                progress(it / max(1, opt.iterations))
            return bool(opt.patience and has_held and it - best[1] >= opt.patience)

        if opt.iterations > 0:
            prob.solve_colour(sh, sh0, terms, opt.iterations, opt.colour_reg, on_step)
    for it in range(opt.iterations if opt.optimise_opacity else 0):
        opac = _sigmoid(logit).astype(np.float32)
        if it > 0:
            fit, held, g_opac, terms = prob.forward(sh.astype(np.float32), opac, grad=True)
            history.append({"iteration": it, "fit_loss": fit, "held_loss": held if has_held else None,
                            "seconds": time.perf_counter() - t0})
            score = held if has_held else fit
            if score < best[0]:
                best[:] = [score, it, sh.copy(), logit.copy()]
            if opt.patience and has_held and it - best[1] >= opt.patience:
                break
        grad = g_opac * opac * (1.0 - opac) + 2.0 * opt.opacity_reg * (logit - logit0)
        m1 = b1 * m1 + (1 - b1) * grad
        m2 = b2 * m2 + (1 - b2) * grad * grad
        mhat = m1 / (1 - b1 ** (it + 1))
        vhat = m2 / (1 - b2 ** (it + 1))
        logit = np.clip(logit - opt.opacity_lr * mhat / (np.sqrt(vhat) + 1e-15), -12.0, 12.0)
        if opt.cg_steps > 0 and (it == 0 or (opt.colour_every and it % opt.colour_every == 0)):
            sh = prob.solve_colour(sh, sh0, terms, opt.cg_steps, opt.colour_reg)
        if progress is not None:
            progress((it + 1) / max(1, opt.iterations))
    if opt.optimise_opacity and opt.iterations > 0:
        fit, held, _, _ = prob.forward(sh.astype(np.float32), _sigmoid(logit).astype(np.float32), grad=False)
        history.append({"iteration": opt.iterations, "fit_loss": fit, "held_loss": held if has_held else None,
                        "seconds": time.perf_counter() - t0})
        score = held if has_held else fit
        if score < best[0] or not has_held:
            best[:] = [score, opt.iterations, sh.copy(), logit.copy()]

    _, best_it, sh_best, logit_best = best
    return RefineResult(_with(sh_best, logit_best), history, best_it, time.perf_counter() - t0, snapshots)
