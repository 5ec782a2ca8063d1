"""Refinement (the paper's +opt): refine the colour (SH) and opacity of Gaussians against their reference views.

OmniSplat+opt (paper Sec. 4.1 / Supp. A) starts from the feed-forward Gaussians
and optimises only colour and opacity on the two reference views, positions
and covariances fixed. Here the loss lives on the Yin and Yang images of each
reference (targets = :func:`rasterizer.yin_yang.erp_to_yin_yang` of the
reference ERP at the working size; no lossy ERP merge inside the loop).

Geometry is fixed, so :func:`rasterizer.splat.footprints` runs once per grid
(opacity-free footprints, valid for any opacity) and every iteration only
re-composites them (:func:`rasterizer.composite.accumulate`).

Method (chosen by measurement on m3d, encoder Gaussians, see ``docs/bench/refine.md``):

* Loss (``loss``, default "l1"): the error of the *alpha-normalised* colour
  C/A (what the ERP renderer shows after its Yin/Yang merge) on the fitted
  reference pixels, solved as a weighted linear least-squares problem: "l1"
  weights each fitted pixel once by 1 / its initial residual norm (IRLS),
  "huber" by min(1, delta / residual), "l2" equally. L1 measured best with
  view-dependent colour (docs/bench/refine.md); "l2" and "huber" stay for
  that comparison (bench/refine.py).
* Colour (default, ``optimise_opacity=False``): with opacities fixed, C/A is
  linear in the SH coefficients
  (:class:`~rasterizer.refine.backward.BlendOperator`); one iteration is
  one Jacobi-preconditioned conjugate-gradient step on the normal equations,
  with a Tikhonov pull ``colour_reg`` toward the initial colours (the problem
  is under-determined: ~N Gaussians vs fewer reference pixels). The first
  step (a per-Gaussian weighted back-projection of the residual) gave
  +1.6 dB at the m3d target; later steps deconvolve and overfit (target and
  held-out pixels agree), so the held-out early stop returns step 1-2.
* Opacity (``optimise_opacity=True``): Adam on logit(opacity) with the exact
  numpy backward of front-to-back compositing
  (:func:`~rasterizer.refine.backward.opacity_gradient`), colour re-solved
  every ``colour_every`` iterations. Measured: no held-out or target gain
  over the colour step, ~10x the cost per iteration, so it is off by default.
* Overfitting guard: a random ``holdout`` fraction of the reference pixels is
  never fitted; its loss is tracked every iteration and the parameters with
  the best held-out loss are returned (early stop after ``patience``
  iterations without improvement).
* Cross-view guard (colour mode, ``cross_check=True``, default;
  :func:`cross_view_check`): held-out pixels of the fitted views cannot see
  wrong geometry (colours that fit both references baked onto the wrong
  surfaces: zind_room09 lost 0.8 dB while its held-out loss fell 10x). So
  the colours are first fitted on each reference alone (<= ``cross_steps``
  CG steps) and scored on *all* pixels of the other reference, a novel view
  for that fit like the targets are for the final one, with a line search
  over the update's scale (``CROSS_SCALES``: a single-reference update
  overshoots, it is not averaged with the other view). If no step and scale
  lowers the cross-view error, the refinement is rejected and the unrefined
  colours are returned; otherwise the usual two-reference solve runs.
  Measured (h = 128, docs/bench/refine.md): m3d best cross-view change
  -2.1% (accept, +1.00 dB at the target, same as unguarded); zind_room09
  split 0 +4.7% (reject; unguarded -0.78 dB), split 1 +0.6% (reject;
  unguarded would have gained +0.15 dB: a missed small gain). Costs
  ~2 x ``cross_steps`` CG steps (+3-7 s on the shared 2-core machine).

Shapes: Gaussians N; per grid P = h * 3h pixels; M contributions.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import numpy as np

from ..camera import Camera
from ..composite import accumulate
from ..gaussians import Gaussians
from ..geometry import as_c2w
from ..sh import sh_basis
from ..splat import Footprints, footprints
from ..yin_yang import erp_to_yin_yang
from .backward import BlendOperator, opacity_gradient

_EPS_LOGIT = 1e-4
_A_FLOOR = 1.0 / 255.0
_L1_EPS = 0.01  # IRLS floor of the residual norm for the L1 loss
#: line search of the cross-view guard: the single-reference update scaled by these factors
CROSS_SCALES = (0.0, 0.125, 0.25, 0.5, 0.75, 1.0)


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
    cross_steps: int = 3          # guard: at most this many CG steps per single-reference fit
    cross_covis: float = 0.0      # guard fits only Gaussians seen by both references (>= this x mean strength); 0: all
    loss: str = "l1"              # "l1" (measured best) | "huber" | "l2": fixed IRLS weights of the initial residual
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
        from ..sh import SH_C0
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
                     delta: float = 0.1, report_start: bool = False, free: np.ndarray | None = None,
                     scales: Sequence[float] | None = None) -> np.ndarray:
        """Jacobi-preconditioned CG on the normal equations of the L2 colour fit (opacities fixed).

        Minimises sum_v |M_v (B_v colour_v(x) - y_v)|^2 + lam |x - sh0|^2 over the
        refined SH x (N, k, 3), warm-started at ``sh``; ``lam`` = ``reg`` times the
        mean data weight of a seen Gaussian. ``on_step(step, x, held_loss)`` is
        called after every step (held_loss: mean squared error on the held-out
        pixels, one sparse product per view); it returns True to stop.
        ``report_start``: also call it once before the first step (step -1).
        ``free`` (N,) bool: only these Gaussians change (the others keep ``sh``).
        ``scales``: held_loss passed to ``on_step`` is then an array, the held-out
        loss of ``sh + t (x - sh)`` for each t (the update scaled, a line search).
        ``loss`` "huber" / "l1": the fitted pixels are re-weighted once by the
        IRLS weight of their initial residual norm e (huber: min(1, delta / e);
        l1: 1 / max(e, 0.01)), so the solve stays linear.
        """
        ops = [BlendOperator(v.footprints, t, self.n, normalise=True) for v, t in zip(self.views, terms_all)]
        masks = [(v.fit & op.covered).astype(np.float64)[:, None] for v, op in zip(self.views, ops)]
        if loss not in ("l2", "huber", "l1"):
            raise ValueError(f"loss must be 'l2', 'huber' or 'l1', got {loss!r}")
        if loss != "l2":
            for i, v in enumerate(self.views):
                pred = ops[i] @ _colours(self.bases[i], sh.astype(np.float64), self.rest[i])
                e = np.sqrt(np.einsum("pc,pc->p", pred - v.target, pred - v.target))
                w = np.minimum(1.0, delta / np.maximum(e, 1e-12)) if loss == "huber" else 1.0 / np.maximum(e, _L1_EPS)
                masks[i] = masks[i] * w[:, None]
        active = [bool(m.any()) for m in masks]  # views with fitted pixels (the others are only scored)
        k = self.k

        def apply_j(i, x):  # (N, k, 3) -> (P, 3)
            return ops[i] @ np.einsum("nk,nkc->nc", self.bases[i], x)

        def apply_jt(i, r):  # (P, 3) -> (N, k, 3)
            return self.bases[i][:, :, None] * ops[i].rmatvec(r)[:, None, :]

        x_start = sh.astype(np.float64)

        def held_loss(x):
            if scales is not None:
                return np.array([held_loss_at(self._project(x_start + t * (x - x_start))) for t in scales])
            return held_loss_at(x)

        def held_loss_at(x):
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
        if free is not None:
            precond = precond * np.asarray(free, np.float64)[:, None, None]

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
            from ..sh import SH_C0
            return np.clip(x, -0.5 / SH_C0, 0.5 / SH_C0)
        return x


def _seen_strength(fp: Footprints, terms, n: int) -> np.ndarray:
    """(N,) sum over covered pixels of the squared alpha-normalised blend weight: how strongly a view sees each Gaussian."""
    if len(fp) == 0:
        return np.zeros(n)
    w = terms.weight.astype(np.float64)
    a = np.bincount(fp.pixel, weights=w, minlength=fp.height * fp.width)[fp.pixel]
    wn = np.where(a >= _A_FLOOR, w / np.maximum(a, _A_FLOOR), 0.0)
    return np.bincount(fp.gaussian, weights=wn * wn, minlength=n)


def cross_view_check(gaussians: Gaussians, views: Sequence[ReferenceView], terms_all, sh0: np.ndarray, k: int,
                     options: RefineOptions) -> dict | None:
    """Cross-view guard: fit the colours on each reference alone, score them on the other reference.

    For every reference r, the colour solve of :func:`refine` runs on the fit
    pixels of the *other* references' grids only (same ``colour_reg``, ``loss``,
    up to ``options.iterations`` steps, early stop after ``patience`` steps
    without improvement) and after every step the mean squared error of the
    alpha-normalised colour on *all* pixels of r's grids is recorded: r is a
    novel view for that fit, like the targets are for the final one, so wrong
    geometry (colours baked onto the wrong surfaces) shows up here while
    held-out pixels of the fitted views cannot see it.

    Returns None with fewer than two references, else a dict: ``curves``
    (per reference r: the cross MSE on r after 0, 1, ... steps), ``total``
    (their pixel-weighted sum per step; a curve that stopped early is padded
    with its last value), ``steps`` (argmin of ``total``; 0 = reject: the
    refinement makes the unseen reference worse), ``accepted``, ``seconds``.
    """
    t0 = time.perf_counter()
    refs = sorted({v.reference for v in views})
    if len(refs) < 2:
        return None
    free = None
    if options.cross_covis > 0:
        strength = {r: np.zeros(gaussians.sh.shape[0]) for r in refs}
        for v, t in zip(views, terms_all):
            strength[v.reference] += _seen_strength(v.footprints, t, gaussians.sh.shape[0])
        free = np.ones(gaussians.sh.shape[0], bool)
        for st in strength.values():
            seen = st > 0
            free &= st >= options.cross_covis * (float(st[seen].mean()) if seen.any() else 0.0)
            free &= seen
    curves, weights = [], []
    for r in refs:
        sub = []
        for v in views:
            if v.reference == r:  # scored on every pixel, never fitted
                sub.append(replace(v, fit=np.zeros_like(v.fit), held=np.ones_like(v.held)))
            else:  # fitted on the same pixels as the final solve
                sub.append(replace(v, held=np.zeros_like(v.held)))
        prob = _Problem(gaussians, sub, k)
        curve: list = []

        def on_step(step, x, loss, curve=curve):
            curve.append(np.asarray(loss, np.float64))
            best = [float(c.min()) for c in curve]
            return bool(options.patience and len(curve) - 1 - int(np.argmin(best)) >= options.patience)

        prob.solve_colour(sh0, sh0, terms_all, min(options.iterations, options.cross_steps), options.colour_reg, on_step,
                          loss=options.loss, delta=options.huber_delta, report_start=True, free=free,
                          scales=CROSS_SCALES)
        curves.append(curve)
        weights.append(prob.n_held)
    n = max(len(c) for c in curves)
    total = np.zeros((n, len(CROSS_SCALES)))
    for c, w in zip(curves, weights):
        total += w * np.array(c + [c[-1]] * (n - len(c)))
    total /= float(sum(weights))
    steps, si = (int(i) for i in np.unravel_index(int(np.argmin(total)), total.shape))
    scale = float(CROSS_SCALES[si])
    if scale == 0.0:
        steps = 0
    return {"curves": {int(r): np.array(c).tolist() for r, c in zip(refs, curves)}, "scales": list(CROSS_SCALES),
            "total": total.tolist(), "steps": steps, "scale": scale,
            "accepted": steps > 0, "covisible": None if free is None else int(free.sum()),
            "seconds": time.perf_counter() - t0}


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
    if opt.loss not in ("l2", "huber", "l1") or not opt.huber_delta > 0:
        raise ValueError(f"loss must be 'l2', 'huber' or 'l1' and huber_delta > 0, got {opt.loss!r}, {opt.huber_delta}")
    if opt.cross_steps < 1 or opt.cross_covis < 0:
        raise ValueError(f"need cross_steps >= 1 and cross_covis >= 0, got {opt.cross_steps}, {opt.cross_covis}")
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
    history.append({"iteration": 0, "fit_loss": fit, "held_loss": held if has_held else None,
                    "seconds": time.perf_counter() - t0})
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
    cross = None
    n_steps = opt.iterations
    if not opt.optimise_opacity and opt.cross_check and opt.iterations > 0:
        cross = cross_view_check(g, views, terms, sh0, k, opt)
        if cross is not None:
            # rejected: the unrefined colours are returned; accepted: the usual held-out early-stopped solve
            n_steps = opt.iterations if cross["accepted"] else 0
    if not opt.optimise_opacity:
        # colour only: one composite at the initial opacities, then `n_steps` CG steps
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
                progress(it / max(1, n_steps))
            return bool(opt.patience and has_held and it - best[1] >= opt.patience)

        if n_steps > 0:
            prob.solve_colour(sh, sh0, terms, n_steps, opt.colour_reg, on_step, loss=opt.loss,
                              delta=opt.huber_delta)
        if progress is not None and n_steps == 0 and opt.iterations > 0:
            progress(1.0)
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
    return RefineResult(_with(sh_best, logit_best), history, best_it, time.perf_counter() - t0, snapshots, cross)
