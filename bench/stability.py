"""``omnisplat-bench stability``: stiff and extreme cases, one pass/fail row and a figure each.

Every case builds a synthetic panorama pair (:mod:`bench.synthetic`),
runs the ONNX encoder and the renderer, and checks a named criterion:

* "finite": every Gaussian field, range map, confidence and rendered pixel is
  finite and the render's alpha lies in [0, 1];
* "sane render": the render's PSNR at the target is at least that of the
  best constant image (the GT's mean colour) minus ``SANE_MARGIN_DB``: it
  shows the scene, not holes, black or garbage (quality itself is the
  quality bench's job);
* "same image": renders after a global rotation or scale match the plain
  render to >= ``SAME_IMAGE_DB`` dB (equivariance, scale invariance);
* "refuses": the encoder raises ``EncoderInputError`` with a message.

    omnisplat-bench stability                 # full: 128x256 model (32 planes, features /2), all cases,
                                              # writes docs/bench/stability.{json,md} and stability/*.png
    omnisplat-bench stability --short --json  # CI: 64x128 model (16 planes, features /1), fewer variants,
                                              # one JSON object on stdout
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from bench import metrics

from .figures import strip
from .machine import machine_info, machine_line
from .models import DEFAULT_MODELS_DIR, bench_model
from .report import write_json
from .synthetic import SyntheticScene, camera, random_rotation, similarity

#: "Same image" threshold for equivariance and scale cases (float32 rounding only).
SAME_IMAGE_DB = 35.0
#: A "sane render" may fall this far below the best constant image's PSNR.
SANE_MARGIN_DB = 3.0
#: Constant-colour inputs must render that colour (mean |error| over covered pixels).
CONSTANT_TOL = 0.02
DEFAULT_OUT = Path(__file__).resolve().parents[1] / "docs" / "bench"

CAM_A = camera([-0.25, 0.0, 0.0])
CAM_B = camera([0.25, 0.0, 0.0])
CAM_T = camera([0.05, 0.05, 0.15])


@dataclass
class CaseResult:
    name: str
    passed: bool
    criterion: str
    detail: str = ""
    figure: str | None = None
    seconds: float = 0.0
    metrics: dict = field(default_factory=dict)


@dataclass
class Env:
    """What every case needs: the encoder, the working size, where figures go."""

    encoder: object
    height: int
    width: int
    fig_dir: Path
    short: bool

    @property
    def render_width(self) -> int:
        return self.width


class Outcome:
    """A reconstruction attempt: the Reconstruction or the refusal, plus finite-ness problems."""

    def __init__(self, rec=None, error: Exception | None = None):
        self.rec, self.error = rec, error
        self.problems = [] if rec is None else reconstruction_problems(rec)


def reconstruction_problems(rec) -> list[str]:
    """Names of non-finite or out-of-range parts of a Reconstruction (empty list = all good)."""
    problems = []
    g = rec.gaussians
    if len(g) == 0:
        problems.append("no Gaussians")
    for name in ("means", "scales", "quats", "opacities", "sh"):
        if not np.all(np.isfinite(getattr(g, name))):
            problems.append(f"gaussians.{name} not finite")
    if np.any(g.scales < 0) or np.any((g.opacities < 0) | (g.opacities > 1)):
        problems.append("scales < 0 or opacities outside [0, 1]")
    for name in ("range_maps", "confidence"):
        arr = getattr(rec, name, None)
        if arr is not None and not np.all(np.isfinite(np.asarray(arr, dtype=np.float64))):
            problems.append(f"{name} not finite")
    return problems


def render_problems(out) -> list[str]:
    problems = []
    for name in ("colour", "alpha", "range"):
        if not np.all(np.isfinite(getattr(out, name))):
            problems.append(f"render {name} not finite")
    if np.any(out.alpha < -1e-6) or np.any(out.alpha > 1 + 1e-6):
        problems.append("render alpha outside [0, 1]")
    return problems


# -- helpers ---------------------------------------------------------------------------

def _error_class():
    from service.encoder import EncoderInputError

    return EncoderInputError


def attempt(env: Env, img_a, img_b, c2w_a, c2w_b, **kw) -> Outcome:
    """Reconstruct; an ``EncoderInputError`` is a refusal, any other exception propagates."""
    try:
        return Outcome(env.encoder.reconstruct(img_a, img_b, c2w_a, c2w_b, **kw))
    except _error_class() as exc:
        return Outcome(error=exc)


def render(env: Env, gaussians, c2w, scale: float = 1.0):
    """Yin-Yang ERP render at the target; ``scale`` scales the renderer's near-cull distance with the scene."""
    from rasterizer.camera import DEFAULT_NEAR
    from rasterizer.render import render as _render

    return _render(gaussians, c2w, projection="erp", width=env.render_width, method="yinyang", near=DEFAULT_NEAR * scale)


def constant_psnr(gt: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR of the best constant image (the GT's mean colour) over ``mask``."""
    sel = gt if mask is None else gt[mask]
    return metrics.psnr(np.broadcast_to(sel.reshape(-1, 3).mean(axis=0), sel.shape), sel)


def masked_psnr(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> float:
    return metrics.psnr(np.clip(pred, 0, 1)[mask], gt[mask])


def pair(env: Env, scene: SyntheticScene, c2w_a=CAM_A, c2w_b=CAM_B, c2w_t=CAM_T):
    """Reference images at the model size and the GT target at the render size."""
    a, _ = scene.render(c2w_a, env.height, env.width)
    b, _ = scene.render(c2w_b, env.height, env.width)
    t, _ = scene.render(c2w_t, env.render_width // 2, env.render_width)
    return a, b, t


def _fig(env: Env, name: str, panels, caption: str) -> str:
    return str(strip(panels, env.fig_dir / f"{name}.png", caption))


def _diff(a, b, gain=4.0):
    return np.clip(np.abs(np.asarray(a) - np.asarray(b)).mean(axis=-1) * gain, 0, 1)


def reconstruct_and_score(env: Env, name: str, scene: SyntheticScene, *, c2w_a=CAM_A, c2w_b=CAM_B, c2w_t=CAM_T,
                          images=None, require_quality=True, allow_refusal=False, mask=None,
                          extra_check: Callable | None = None, **kw) -> CaseResult:
    """The common case: reconstruct, render the target, check finite (+ beats constant)."""
    a, b, t = pair(env, scene, c2w_a, c2w_b, c2w_t) if images is None else images
    out = attempt(env, a, b, c2w_a, c2w_b, **kw)
    crit = "finite" + (" and sane render" if require_quality else "") + (" (or refuses)" if allow_refusal else "")
    if out.error is not None:
        fig = _fig(env, name, [("ref A", a), ("ref B", b), ("GT target", t)], f"refused: {out.error}")
        return CaseResult(name, allow_refusal and bool(str(out.error)), crit, f"refused: {out.error}", fig)
    r = render(env, out.rec.gaussians, c2w_t)
    problems = out.problems + render_problems(r)
    colour = np.asarray(r.colour)
    m = {"num_gaussians": len(out.rec.gaussians)}
    if mask is None:
        mask = np.ones(colour.shape[:2], dtype=bool)
    if not problems and t is not None:
        m["psnr"] = masked_psnr(colour, t, mask)
        m["constant_psnr"] = constant_psnr(t, mask)
        if require_quality and m["psnr"] < m["constant_psnr"] - SANE_MARGIN_DB:
            problems.append(f"PSNR {m['psnr']:.2f} dB more than {SANE_MARGIN_DB:g} dB below the constant image's "
                            f"{m['constant_psnr']:.2f} dB")
    if extra_check is not None and not problems:
        problems += extra_check(colour, np.asarray(r.alpha), m)
    detail = "; ".join(problems) if problems else ", ".join(f"{k} {v:.2f}" if isinstance(v, float) else f"{k} {v}"
                                                            for k, v in m.items())
    panels = [("ref A", a), ("ref B", b), ("GT target", t), ("render", colour)]
    if t is not None:
        panels.append(("|render - GT| x4", _diff(colour, t)))
    fig = _fig(env, name, panels, f"{name}: {detail}")
    return CaseResult(name, not problems, crit, detail, fig, metrics=m)


def must_refuse(env: Env, name: str, images, c2w_a, c2w_b, mentions: tuple[str, ...] = (), **kw) -> CaseResult:
    """The encoder must raise EncoderInputError whose message names the problem (one of ``mentions``)."""
    a, b = images
    out = attempt(env, a, b, c2w_a, c2w_b, **kw)
    if out.error is not None:
        msg = str(out.error).lower()
        ok = bool(msg.strip()) and (not mentions or any(w in msg for w in mentions))
        detail = f"EncoderInputError: {out.error}" + ("" if ok else f" (message names none of {list(mentions)})")
    else:
        ok = False
        bad = "; ".join(out.problems) or "finite output"
        detail = f"accepted instead of refusing ({bad})"
    fig = _fig(env, name, [("ref A", a), ("ref B", b)], detail)
    crit = "refuses with EncoderInputError" + (f" naming {'/'.join(mentions)}" if mentions else "")
    return CaseResult(name, ok, crit, detail, fig)


def same_image(env: Env, name: str, scene: SyntheticScene, transform: Callable[[np.ndarray], np.ndarray],
               label: str, scale: float = 1.0, near_far: tuple[float, float] | None = None) -> CaseResult:
    """Renders before/after a global similarity of all poses must match (images unchanged).

    ``near_far``: pass this sweep range for the plain run and ``scale`` times it for the moved one
    (default: the encoder's own defaults for both).
    """
    a, b, t = pair(env, scene)
    kw0 = {} if near_far is None else {"near": near_far[0], "far": near_far[1]}
    kw1 = {} if near_far is None else {"near": near_far[0] * scale, "far": near_far[1] * scale}
    base = attempt(env, a, b, CAM_A, CAM_B, **kw0)
    moved = attempt(env, a, b, transform(CAM_A), transform(CAM_B), **kw1)
    crit = f"finite and same image (PSNR >= {SAME_IMAGE_DB:g} dB)"
    for o, which in ((base, "plain"), (moved, label)):
        if o.error is not None:
            fig = _fig(env, name, [("ref A", a), ("ref B", b)], f"{which} refused: {o.error}")
            return CaseResult(name, False, crit, f"{which} refused: {o.error}", fig)
    r0 = render(env, base.rec.gaussians, CAM_T)
    r1 = render(env, moved.rec.gaussians, transform(CAM_T), scale)
    problems = base.problems + moved.problems + render_problems(r0) + render_problems(r1)
    m = {}
    if not problems:
        m["psnr_vs_plain"] = metrics.psnr(r1.colour, r0.colour)
        m["psnr_plain_vs_gt"] = metrics.psnr(r0.colour, t)
        m["psnr_moved_vs_gt"] = metrics.psnr(r1.colour, t)
        if m["psnr_vs_plain"] < SAME_IMAGE_DB:
            problems.append(f"renders differ: PSNR {m['psnr_vs_plain']:.2f} dB < {SAME_IMAGE_DB:g}")
    detail = "; ".join(problems) if problems else ", ".join(f"{k} {v:.2f}" for k, v in m.items())
    fig = _fig(env, name, [("GT target", t), ("render plain", r0.colour), (f"render {label}", r1.colour),
                           ("|diff| x10", _diff(r0.colour, r1.colour, 10.0))], f"{name}: {detail}")
    return CaseResult(name, not problems, crit, detail, fig, metrics=m)


# -- the cases ---------------------------------------------------------------------------

HALL = SyntheticScene(room_lo=(-60.0, -1.5, -3.0), room_hi=(60.0, 1.5, 3.0),
                      spheres=((0.6, 0.4, 1.4, 0.4), (-0.8, -0.3, -1.5, 0.5), (8.0, 0.0, 1.8, 0.9),
                               (-15.0, 0.3, -1.5, 1.0), (35.0, 0.0, 1.5, 1.2), (-45.0, 0.0, 1.6, 1.2)))


def case_baseline(env: Env, b: float) -> CaseResult:
    """Cameras b apart in a 120 m hall; small baselines may be refused, larger ones must render the scene."""
    a_pos, b_pos = np.array([-b / 2, 0, 0]), np.array([b / 2, 0, 0])
    t_pos = np.array([0.2 * b, 0, 0]) + min(b, 0.5) * np.array([0.0, 0.1, 0.2])
    small = b < 0.01
    return reconstruct_and_score(env, f"baseline_{_len_label(b)}", HALL, c2w_a=camera(a_pos), c2w_b=camera(b_pos),
                                 c2w_t=camera(t_pos), require_quality=not small, allow_refusal=small)


BASELINE_WORDS = ("baseline", "coincide", "same position", "triangulat")


def case_pure_rotation(env: Env) -> CaseResult:
    rot = random_rotation(np.random.default_rng(7))
    c2w_b = camera([-0.25, 0, 0], rot)
    scene = SyntheticScene()
    a, _ = scene.render(CAM_A, env.height, env.width)
    b, _ = scene.render(c2w_b, env.height, env.width)
    return must_refuse(env, "pure_rotation", (a, b), CAM_A, c2w_b, mentions=BASELINE_WORDS)


def case_identical(env: Env) -> CaseResult:
    a, _ = SyntheticScene().render(CAM_A, env.height, env.width)
    return must_refuse(env, "identical_cameras", (a, a.copy()), CAM_A, CAM_A.copy(), mentions=BASELINE_WORDS)


def case_rotation(env: Env, seed: int) -> CaseResult:
    rot = random_rotation(np.random.default_rng(seed))
    return same_image(env, f"global_rotation_{seed}", SyntheticScene(), lambda c: similarity(c, rot), "rotated")


def case_scale(env: Env, s: float) -> CaseResult:
    """Default near/far: the encoder must scale its sweep range with the baseline."""
    return same_image(env, f"global_scale_{s:g}", SyntheticScene(), lambda c: similarity(c, None, s), f"scaled x{s:g}", s)


def case_scale_explicit(env: Env, s: float) -> CaseResult:
    """Caller-scaled near/far: isolates the rest of the pipeline (sweep, head, renderer) from the defaults."""
    return same_image(env, f"global_scale_{s:g}_explicit_near_far", SyntheticScene(),
                      lambda c: similarity(c, None, s), f"scaled x{s:g}", s, near_far=(0.3, 20.0))


def case_constant(env: Env, name: str, value: float) -> CaseResult:
    img = np.full((env.height, env.width, 3), value, dtype=np.float32)

    def check(colour, alpha, m):
        covered = alpha > 0.5
        m["covered_fraction"] = float(covered.mean())
        if covered.mean() < 0.5:
            return [f"only {covered.mean():.0%} of the render covered (alpha > 0.5)"]
        err = float(np.abs(colour[covered] - value).mean())
        m["mean_abs_error"] = err
        return [] if err <= CONSTANT_TOL else [f"mean |colour - {value}| = {err:.3f} > {CONSTANT_TOL}"]

    gt = np.full((env.render_width // 2, env.render_width, 3), value, dtype=np.float32)
    res = reconstruct_and_score(env, name, SyntheticScene(), images=(img, img.copy(), gt), require_quality=False,
                                extra_check=check)
    res.criterion = f"finite and renders the input colour (mean error <= {CONSTANT_TOL})"
    return res


def case_overexposed(env: Env) -> CaseResult:
    """A real scene overexposed 2.5x: large clipped (saturated) areas in both views and the target."""
    a, b, t = (np.clip(x * 2.5, 0.0, 1.0) for x in pair(env, SyntheticScene()))
    return reconstruct_and_score(env, "overexposed_clipped", SyntheticScene(), images=(a, b, t))


def case_noise(env: Env) -> CaseResult:
    rng = np.random.default_rng(3)
    a = rng.random((env.height, env.width, 3), dtype=np.float32)
    b = rng.random((env.height, env.width, 3), dtype=np.float32)
    return reconstruct_and_score(env, "pure_noise", SyntheticScene(), images=(a, b, None), require_quality=False)


def case_near_far(env: Env, name: str, near, far, expect: str) -> CaseResult:
    """``expect``: "render" (finite and sane), "finite", "refuse", or "either" (finite or refusal)."""
    if expect == "refuse":
        a, b, _ = pair(env, SyntheticScene())
        return must_refuse(env, name, (a, b), CAM_A, CAM_B, mentions=("near", "far"), near=near, far=far)
    return reconstruct_and_score(env, name, SyntheticScene(), require_quality=expect == "render",
                                 allow_refusal=expect == "either", near=near, far=far)


def case_poles(env: Env) -> CaseResult:
    h = env.render_width // 2
    lat = np.pi / 2 - (np.arange(h) + 0.5) / h * np.pi
    mask = np.broadcast_to((np.abs(lat) > np.radians(55))[:, None], (h, env.render_width))
    return reconstruct_and_score(env, "texture_near_poles", SyntheticScene(texture="poles"), mask=mask)


def case_seam(env: Env) -> CaseResult:
    w = env.render_width
    lon = (np.arange(w) + 0.5) / w * 2 * np.pi - np.pi
    mask = np.broadcast_to((np.abs(lon) > np.radians(140))[None, :], (w // 2, w))

    h = w // 2
    band = np.abs(np.pi / 2 - (np.arange(h) + 0.5) / h * np.pi) < np.radians(20)  # rows of the textured patch

    def continuity(colour, alpha, m):
        c = colour[band]
        jump = float(np.abs(c[:, 0] - c[:, -1]).mean())
        inner = float(0.5 * (np.abs(c[:, 1] - c[:, 0]).mean() + np.abs(c[:, -1] - c[:, -2]).mean()))
        m["seam_jump"], m["neighbour_jump"] = jump, inner
        return [] if jump <= 2 * inner + 0.01 else [f"seam discontinuity {jump:.3f} > 2 x {inner:.3f} + 0.01"]

    res = reconstruct_and_score(env, "texture_across_seam", SyntheticScene(texture="seam"), mask=mask,
                                extra_check=continuity)
    res.criterion += " over the seam, and no jump at the seam"
    return res


def case_close_sphere(env: Env) -> CaseResult:
    scene = SyntheticScene(spheres=SyntheticScene().spheres + ((-0.25, 0.0, 0.06, 0.05),))
    return reconstruct_and_score(env, "geometry_1cm_from_camera", scene, require_quality=False)


def case_near_wall(env: Env) -> CaseResult:
    scene = SyntheticScene(room_lo=(-0.26, -1.4, -3.0))
    c2w_t = camera([0.0, 0.05, 0.15])
    return reconstruct_and_score(env, "camera_1cm_from_wall", scene, c2w_t=c2w_t, require_quality=False)


def _len_label(b: float) -> str:
    return f"{b * 1000:g}mm" if b < 1 else f"{b:g}m"


def cases(short: bool) -> list[tuple[str, Callable[[Env], CaseResult]]]:
    """(name, function) of every case; ``short`` trims the sweeps (baselines, rotations, scales)."""
    baselines = (1e-3, 1.0, 100.0) if short else (1e-3, 1e-2, 0.1, 1.0, 10.0, 100.0)
    seeds = (1,) if short else (1, 2, 3)
    scales = (1e-3, 1e3) if short else (1e-3, 1e-2, 1e-1, 10.0, 100.0, 1e3)
    out: list[tuple[str, Callable]] = []
    out += [(f"baseline_{_len_label(b)}", lambda e, b=b: case_baseline(e, b)) for b in baselines]
    out += [("pure_rotation", case_pure_rotation), ("identical_cameras", case_identical)]
    out += [(f"global_rotation_{s}", lambda e, s=s: case_rotation(e, s)) for s in seeds]
    out += [(f"global_scale_{s:g}", lambda e, s=s: case_scale(e, s)) for s in scales]
    out += [(f"global_scale_{s:g}_explicit_near_far", lambda e, s=s: case_scale_explicit(e, s)) for s in (1e-3, 1e3)]
    out += [("textureless_grey", lambda e: case_constant(e, "textureless_grey", 0.5)),
            ("black", lambda e: case_constant(e, "black", 0.0)),
            ("saturated_white", lambda e: case_constant(e, "saturated_white", 1.0)),
            ("overexposed_clipped", case_overexposed),
            ("pure_noise", case_noise)]
    out += [("near_far_wide", lambda e: case_near_far(e, "near_far_wide", 0.05, 1e3, "render")),
            ("near_far_extreme", lambda e: case_near_far(e, "near_far_extreme", 1e-4, 1e6, "finite")),
            ("near_far_beyond_scene", lambda e: case_near_far(e, "near_far_beyond_scene", 50.0, 100.0, "finite")),
            ("near_far_equal", lambda e: case_near_far(e, "near_far_equal", 2.0, 2.0, "refuse")),
            ("near_far_inverted", lambda e: case_near_far(e, "near_far_inverted", 5.0, 1.0, "refuse")),
            ("near_zero", lambda e: case_near_far(e, "near_zero", 0.0, 10.0, "refuse")),
            ("near_negative", lambda e: case_near_far(e, "near_negative", -1.0, 10.0, "refuse")),
            ("near_nan", lambda e: case_near_far(e, "near_nan", float("nan"), 10.0, "refuse")),
            ("far_inf", lambda e: case_near_far(e, "far_inf", 0.5, float("inf"), "either"))]
    out += [("texture_near_poles", case_poles), ("texture_across_seam", case_seam),
            ("geometry_1cm_from_camera", case_close_sphere), ("camera_1cm_from_wall", case_near_wall)]
    return out


def run_case(env: Env, name: str, fn: Callable[[Env], CaseResult]) -> CaseResult:
    """Run one case; an unexpected exception is a failed case with its type and message."""
    t0 = time.perf_counter()
    try:
        res = fn(env)
    except Exception as exc:  # noqa: BLE001 - any crash is a finding, reported as a failed row
        tb = traceback.format_exception_only(type(exc), exc)[-1].strip()
        fig = strip([("crash", None)], env.fig_dir / f"{name}.png", f"{name}: unexpected {tb}")
        res = CaseResult(name, False, "no unexpected exception", f"unexpected {tb}", str(fig))
    res.seconds = time.perf_counter() - t0
    return res


def make_env(*, short: bool, height: int, planes: int, downscale: int | None, models_dir: Path, fig_dir: Path,
             threads: int = 2, model: Path | None = None) -> Env:
    from service.encoder import OnnxEncoder

    path = model or bench_model(height, 2 * height, planes, False, downscale=downscale, models_dir=models_dir,
                                 threads=threads)
    return Env(OnnxEncoder(path, threads=threads), height, 2 * height, Path(fig_dir), short)


def run(env: Env, only: list[str] | None = None, log=None) -> list[CaseResult]:
    results = []
    for name, fn in cases(env.short):
        if only and name not in only:
            continue
        res = run_case(env, name, fn)
        if log:
            log(f"{'PASS' if res.passed else 'FAIL'} {name} ({res.seconds:.1f} s): {res.detail}")
        results.append(res)
    return results


def markdown(results: list[CaseResult], machine: str, model_line: str) -> str:
    n_pass = sum(r.passed for r in results)
    lines = ["# Stability: stiff and extreme cases", "", f"Machine: {machine}", "", f"Model: {model_line}", "",
             f"**{n_pass} passed, {len(results) - n_pass} failed.** Generated by `omnisplat-bench stability`; "
             "synthetic scenes from `bench/synthetic.py`.", "",
             "Criteria: *finite* = every Gaussian field, range map, confidence and rendered pixel finite, alpha in "
             f"[0, 1]; *sane render* = PSNR at the target >= the best constant image's PSNR - {SANE_MARGIN_DB:g} dB "
             "(shows the scene, not holes or garbage; quality is the quality bench's job); *same image* = PSNR "
             f"between the plain and the transformed render >= {SAME_IMAGE_DB:g} dB; constant inputs must render "
             f"their colour (mean error <= {CONSTANT_TOL} where alpha > 0.5, over >= 50% of pixels); *refuses* = "
             "`EncoderInputError` whose message names the problem.", "",
             "| case | result | criterion | detail | s | figure |", "|---|---|---|---|---|---|"]
    for r in results:
        fig = f"[png](stability/{Path(r.figure).name})" if r.figure else ""  # stability.md sits in out_dir
        detail = r.detail.replace("|", "/")[:300]
        lines.append(f"| {r.name} | {'pass' if r.passed else '**FAIL**'} | {r.criterion} | {detail} | {r.seconds:.1f} | {fig} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="omnisplat-bench stability", description=__doc__.split("\n\n")[0])
    p.add_argument("--short", action="store_true", help="CI mode: 64x128 model, fewer variants")
    p.add_argument("--json", action="store_true", help="print one JSON object (cases, passed, failed) on stdout")
    p.add_argument("--out", type=Path, default=None,
                   help="write stability.json/.md and figures here (default docs/bench; a temp dir with --short)")
    p.add_argument("--models-dir", type=Path, default=DEFAULT_MODELS_DIR)
    p.add_argument("--model", type=Path, default=None, help="use this ONNX model instead of building one")
    p.add_argument("--height", type=int, default=None, help="model input height (default 64 short, 128 full)")
    p.add_argument("--planes", type=int, default=None, help="depth candidates (default 16 short, 32 full)")
    p.add_argument("--downscale", type=int, default=None, help="feature downscale (default 1 short, 2 full)")
    p.add_argument("--case", action="append", default=None, help="run only this case (repeatable)")
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args(argv)

    height = args.height or (64 if args.short else 128)
    planes = args.planes or (16 if args.short else 32)
    downscale = args.downscale or (1 if args.short else 2)
    out = args.out or (Path(tempfile.mkdtemp(prefix="omnisplat_stability_")) if args.short else DEFAULT_OUT)
    log = (lambda m: print(f"[bench stability] {m}", file=sys.stderr, flush=True))
    env = make_env(short=args.short, height=height, planes=planes, downscale=downscale, models_dir=args.models_dir,
                   fig_dir=out / "stability", threads=args.threads, model=args.model)
    if not args.case:  # a full run replaces every figure; stale ones of renamed cases go
        for old in env.fig_dir.glob("*.png"):
            old.unlink()
    info = machine_info()
    results = run(env, args.case, log)
    n_pass = sum(r.passed for r in results)
    meta = getattr(env.encoder, "metadata", {}) or {}
    model_line = f"{height}x{2 * height} input, {planes} planes, features /{downscale}, Yin-Yang encoder; " + \
        ", ".join(f"{k}={meta[k]}" for k in ("name", "version", "sha256") if k in meta)
    cases_out = [asdict(r) for r in results]
    for c in cases_out:  # relative to out_dir, so the committed report has no machine paths
        c["figure"] = Path(c["figure"]).resolve().relative_to(out.resolve()).as_posix() if c["figure"] else None
    payload = {"cases": cases_out, "passed": n_pass, "failed": len(results) - n_pass, "out_dir": str(out),
               "short": args.short, "model": model_line, "machine": info, "same_image_db": SAME_IMAGE_DB}
    write_json(out / "stability.json", payload)
    (out / "stability.md").write_text(markdown(results, machine_line(info), model_line))
    if args.json:
        print(json.dumps(json.loads((out / "stability.json").read_text())))
    else:
        for r in results:
            print(f"{'PASS' if r.passed else 'FAIL'}  {r.name:28s} {r.detail}")
        print(f"{n_pass} passed, {len(results) - n_pass} failed; report in {out}")
    return 0 if n_pass == len(results) else 1


if __name__ == "__main__":
    raise SystemExit(main())
