"""``omnisplat bench refine``: +opt quality against iterations and seconds (not a timed test).

For each scene folder (first split; references A, B; every target): reconstruct with the
ONNX encoder, build the reference Yin/Yang footprints once, run the colour refinement
(:mod:`rasterizer.refine`) without early stop and score the target views (PSNR, SSIM,
conventions section 6) at the requested iteration counts, plus the default early-stopped
result. Writes ``refine.json`` and ``refine.md`` into ``--out`` (default ``docs/bench``).

    python -c "from service.bench_refine import main; main([])"
    ... main(["--data", "../shared/data/m3d_bedroom", "--iterations", "0", "1", "2", "5"])
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from rasterizer import metrics
from rasterizer.refine import RefineOptions, reference_views, refine
from rasterizer.render import render
from rasterizer.scene_folder import load_scene

from .bench_machine import machine_info, machine_line

REPO = Path(__file__).resolve().parents[1]
DEFAULT_OUT = REPO / "docs" / "bench"
DEFAULT_DATA = [REPO.parent / "shared" / "data" / "m3d_bedroom", REPO.parent / "shared" / "data" / "zind_room09"]
DEFAULT_ITERATIONS = (0, 1, 2, 5, 25, 50, 100, 200, 400)


def _log(msg: str) -> None:
    print(f"[bench refine] {msg}", file=sys.stderr, flush=True)


def _score(g, targets) -> dict:
    ps, ss = [], []
    for c2w, gt in targets:
        out = np.clip(np.nan_to_num(render(g, c2w, projection="erp", width=gt.shape[1]).colour), 0, 1)
        ps.append(metrics.psnr(out, gt))
        ss.append(metrics.ssim(out, gt))
    return {"psnr": float(np.mean(ps)), "ssim": float(np.mean(ss))}


def bench_scene(encoder, folder: Path, iterations, height: int, options: dict) -> dict:
    scene = load_scene(folder)
    split = scene.splits[0]
    fa, fb = (scene.frames[n] for n in split.references)
    targets = [(scene.frames[n].c2w, scene.frames[n].image()) for n in split.targets]
    t0 = time.perf_counter()
    rec = encoder.reconstruct(fa.image(), fb.image(), fa.c2w, fb.c2w)
    t_enc = time.perf_counter() - t0
    g = rec.gaussians
    t0 = time.perf_counter()
    views = reference_views(g, [fa.image(), fb.image()], [fa.c2w, fb.c2w], height=height)
    t_fp = time.perf_counter() - t0
    _log(f"{scene.name}: {len(g)} Gaussians, encoder {t_enc:.1f} s, footprints {t_fp:.1f} s, "
         f"{sum(len(v.footprints) for v in views)} contributions")
    n_max = max(iterations)
    res = refine(g, views, RefineOptions(iterations=n_max, patience=0, **options), snapshot_at=iterations)
    secs = {h["iteration"]: h["seconds"] for h in res.history}
    held = {h["iteration"]: h["held_loss"] for h in res.history}
    rows = []
    for it in sorted(res.snapshots):
        s = _score(res.snapshots[it], targets)
        rows.append({"iteration": it, **s, "refine_s": secs.get(it, 0.0), "total_s": t_fp + secs.get(it, 0.0),
                     "held_loss": held.get(it)})
        _log(f"{scene.name} it {it}: PSNR {s['psnr']:.3f} SSIM {s['ssim']:.4f} ({rows[-1]['total_s']:.1f} s)")
    t0 = time.perf_counter()
    default = refine(g, views, RefineOptions(**options))
    t_def = time.perf_counter() - t0
    s = _score(default.gaussians, targets)
    early = {"best_iteration": default.best_iteration, "iterations_run": default.history[-1]["iteration"],
             **s, "refine_s": t_def, "total_s": t_fp + t_def}
    _log(f"{scene.name} default (early stop at {default.best_iteration}): PSNR {s['psnr']:.3f} ({early['total_s']:.1f} s)")
    return {"scene": scene.name, "references": list(split.references), "targets": list(split.targets),
            "num_gaussians": len(g), "contributions": int(sum(len(v.footprints) for v in views)),
            "encoder_s": t_enc, "footprints_s": t_fp, "rows": rows, "early_stop": early}


def markdown(result: dict) -> str:
    lines = ["# +opt refinement: quality against iterations", "",
             f"Machine: {result['machine']}. **The CPU was shared with other engineers while this ran: "
             "seconds are noisy (likely 2-4x slower than on an idle machine).**", "",
             f"Method: {result['method']}", "",
             f"Working size: Yin/Yang h = {result['height']} (two grids of h x 3h per reference); "
             f"model `{result['model']}`. Seconds = footprints (once) + refinement; encoder not included.", ""]
    for sc in result["scenes"]:
        base = sc["rows"][0]["psnr"] if sc["rows"] else float("nan")
        lines += [f"## {sc['scene']} (references {', '.join(sc['references'])}; targets {', '.join(sc['targets'])})",
                  "", f"{sc['num_gaussians']} Gaussians, {sc['contributions']} contributions; encoder "
                  f"{sc['encoder_s']:.1f} s, footprints {sc['footprints_s']:.1f} s.", "",
                  "| CG iterations | PSNR | dPSNR | SSIM | held-out MSE | seconds |", "|---:|---:|---:|---:|---:|---:|"]
        for r in sc["rows"]:
            hl = "" if r["held_loss"] is None else f"{r['held_loss']:.5f}"
            lines.append(f"| {r['iteration']} | {r['psnr']:.2f} | {r['psnr'] - base:+.2f} | {r['ssim']:.4f} | {hl} | "
                         f"{r['total_s']:.1f} |")
        e = sc["early_stop"]
        lines += ["", f"Default (early stop on held-out reference pixels): best iteration {e['best_iteration']}, "
                  f"PSNR {e['psnr']:.2f} ({e['psnr'] - base:+.2f} dB), SSIM {e['ssim']:.4f}, {e['total_s']:.1f} s.", ""]
    lines += result.get("notes", [])
    return "\n".join(lines) + "\n"


NOTES = [
    "## Notes", "",
    "* Iteration = one Jacobi-preconditioned CG step on the normal equations of the L2 colour fit "
    "(colour_reg = 2 x the mean data weight). The first step is a per-Gaussian weighted back-projection of "
    "the residual; later steps sharpen (deconvolve) the colours and converge by ~25 steps.",
    "* m3d: +1.62 dB at step 1, the held-out reference pixels pick it; later steps overfit (target and "
    "held-out agree). Refinement itself takes ~3 s here; the once-per-scene footprints (4 grids) take 16 s "
    "on the loaded machine, so the 15 s target is met for the refinement but not for footprints + refinement "
    "while the CPU is shared.",
    "* zind_room09: refinement **hurts** the targets (-0.85 dB at step 1) while the held-out reference "
    "loss drops 10x: the encoder's geometry is poor here (wide baseline), so colours that fit both "
    "references are baked onto wrong surfaces. Held-out *pixels* of the reference views cannot see this. "
    "A stronger colour_reg only shrinks the change (reg 20: 17.74 dB, reg 100: 17.85 dB vs 17.82 "
    "unrefined, step 1). A guard that would see it: validate on the *other* reference view (fit A, "
    "check B) before accepting a refinement (not implemented yet).",
    "* Opacity (Adam on logit opacity with the exact numpy compositing backward) was measured on m3d "
    "(h = 128): it did not improve the held-out loss or the target beyond the colour step "
    "(24.76 dB with or without 15 Adam steps at lr 0.01/0.03; 22.70 dB with lr 0.05 and 10-step CG solves) "
    "and costs ~3 s per iteration on this machine, so it is off by default (`optimise_opacity`).",
    "* h = 256 (full reference resolution) on m3d: step 2 best, 24.76 dB / SSIM 0.7247 (vs 0.7152 at h = 128) "
    "for 21.5 s footprints + 15 s refinement; h = 128 is the default for speed.",
]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="omnisplat bench refine", description=__doc__.splitlines()[0])
    ap.add_argument("--data", nargs="+", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--model", type=Path, default=None, help="ONNX model (default: a 512x1024 bench model)")
    ap.add_argument("--iterations", nargs="+", type=int, default=list(DEFAULT_ITERATIONS))
    ap.add_argument("--height", type=int, default=128, help="Yin/Yang working height")
    ap.add_argument("--colour-reg", type=float, default=2.0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)
    from .encoder import OnnxEncoder

    model = args.model
    if model is None:
        from .bench_models import ensure_model
        model = ensure_model(512, 1024, 32, log=_log)
    encoder = OnnxEncoder(model, threads=args.threads)
    options = {"colour_reg": args.colour_reg}
    scenes = [bench_scene(encoder, Path(d), sorted(set(args.iterations)), args.height, options) for d in args.data]
    result = {"machine": machine_line(machine_info()), "model": str(Path(model).name), "height": args.height,
              "method": "colour-only PCG on the alpha-normalised L2 fit, opacity fixed, early stop on 10% "
                        "held-out reference pixels", "options": options, "scenes": scenes, "notes": NOTES}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "refine.json").write_text(json.dumps(result, indent=1))
    (args.out / "refine.md").write_text(markdown(result))
    _log(f"wrote {args.out / 'refine.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
