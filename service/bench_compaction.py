"""Compaction, render-time culling and adaptive sweep range, measured on the dev scenes.

    python -m service.bench_compaction [--data DIR ...] [--out docs/bench] [--model M.onnx] [--no-gt] [--no-adaptive]

For every split and target: Gaussian count, PLY bytes, render seconds
(512x1024 ERP via Yin-Yang) and PSNR before and after each compaction step
and all together; render-time culling (ERP and a 90-degree perspective
view); and the two-pass adaptive near/far (seconds, PSNR, depth AbsRel on
m3d GT). Sources: the real encoder (a 512x1024, 32-plane model from the
bench model cache, :func:`service.bench_models.ensure_model`, or ``--model``) and, where a scene has depth, GT-depth
Gaussians in the same grid layout. Writes compaction.json / compaction.md.
Render timings are single runs: noisy; the report gives the load average.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from rasterizer import metrics
from rasterizer.compaction import CompactionOptions, Provenance, compact
from rasterizer.depth_gaussians import gaussians_from_depth
from rasterizer.gaussians import Gaussians
from rasterizer.ply import ply_bytes
from rasterizer.render import render
from rasterizer.render_cull import cull_for_camera
from rasterizer.splat import RenderLimitError
from rasterizer.scene_folder import load_scene
from rasterizer.yin_yang import erp_to_yin_yang

from .bench_models import ensure_model

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = [REPO.parent / "shared" / "data" / "m3d_bedroom", REPO.parent / "shared" / "data" / "zind_room09"]
RENDER_WIDTH = 1024


def _log(msg: str) -> None:
    print(f"[bench compaction] {msg}", file=sys.stderr, flush=True)


def variants(n: int) -> dict[str, CompactionOptions]:
    """Each step alone, all defaults, and a 60% count cap with and without the rest."""
    off = CompactionOptions.off()
    cap = int(0.6 * n)
    return {
        "none": off,
        "min_opacity": off.__class__(**{**off.to_dict(), "min_opacity": 1.0 / 255.0}),
        "overlap_split": off.__class__(**{**off.to_dict(), "resolve_overlap": "split"}),
        "overlap_yin": off.__class__(**{**off.to_dict(), "resolve_overlap": "yin"}),
        "duplicates": off.__class__(**{**off.to_dict(), "merge_duplicates": True}),
        "cap60": off.__class__(**{**off.to_dict(), "max_count": cap}),
        "all": CompactionOptions(),
        "all+cap60": CompactionOptions(max_count=cap),
    }


def gt_gaussians(scene, refs, opacity: float = 0.9) -> tuple[Gaussians, Provenance]:
    """GT-depth Gaussians in the encoder's layout ([view][yin, yang][row][col]; invalid depth skipped)."""
    parts, index, poses = [], [], []
    h = w = None
    for v, name in enumerate(refs):
        frame = scene.frames[name]
        imgs = erp_to_yin_yang(frame.image())
        depths = erp_to_yin_yang(frame.depth(), nearest=True)
        poses.append(frame.c2w)
        for g, kind in enumerate(("yin", "yang")):
            h, w = depths[g].shape
            ok = np.isfinite(depths[g]) & (depths[g] > 0)
            parts.append(gaussians_from_depth(imgs[g], depths[g], frame.c2w, kind, scale_factor=0.75,
                                              thickness=0.1, opacity=opacity))
            index.append((v * 2 + g) * h * w + np.flatnonzero(ok.ravel()))
    return Gaussians.concatenate(parts), Provenance(("yin", "yang"), h, w, np.stack(poses), np.concatenate(index))


def timed_render(g: Gaussians, c2w, **kw):
    """(RenderOutput or None when the renderer refuses (RenderLimitError), seconds)."""
    t = time.perf_counter()
    try:
        out = render(g, c2w, **kw)
    except RenderLimitError:
        out = None
    return out, time.perf_counter() - t


def evaluate(g: Gaussians, target, gt_img) -> dict:
    out, sec = timed_render(g, target.c2w, projection="erp", width=RENDER_WIDTH)
    return {"count": len(g), "ply_bytes": len(ply_bytes(g)), "render_s": round(sec, 3),
            "psnr": round(metrics.psnr(out.colour, gt_img), 4)}


def bench_source(g: Gaussians, prov: Provenance, targets, images, conf=None) -> dict:
    """All variants x targets for one set of Gaussians; plus culling on the 'all' set."""
    res: dict = {"variants": {}, "culling": {}}
    kept_all = None
    for name, opts in variants(len(g)).items():
        t = time.perf_counter()
        gc, stats = compact(g, prov, opts, confidence=conf)
        sec = time.perf_counter() - t
        per_t = {tn: evaluate(gc, targets[tn], images[tn]) for tn in targets}
        res["variants"][name] = {"compact_s": round(sec, 3), "removed": stats["removed"], "targets": per_t}
        _log(f"  {name}: {len(gc)} Gaussians, " + ", ".join(
            f"{tn} {r['render_s']:.2f}s {r['psnr']:.3f}dB" for tn, r in per_t.items()))
        if name == "all":
            kept_all = gc
    for tn, tgt in targets.items():
        t = time.perf_counter()
        idx = cull_for_camera(kept_all, tgt.c2w, "erp", width=RENDER_WIDTH)
        cull_s = time.perf_counter() - t
        erp = evaluate(kept_all.subset(idx), tgt, images[tn])
        # perspective 90 deg 512x512 looking along the target's +z: frustum cull matters here
        pk = dict(projection="perspective", width=512, fov_deg=90.0)
        ref, s_ref = timed_render(kept_all, tgt.c2w, **pk)
        t = time.perf_counter()
        pidx = cull_for_camera(kept_all, tgt.c2w, "perspective", width=512, fov_deg=90.0)
        pcull_s = time.perf_counter() - t
        got, s_got = timed_render(kept_all.subset(pidx), tgt.c2w, **pk)
        res["culling"][tn] = {
            "erp": {"culled": len(kept_all) - int(idx.size), "cull_s": round(cull_s, 3), **erp},
            "perspective": {"culled": len(kept_all) - int(pidx.size), "cull_s": round(pcull_s, 3),
                            "render_s_before": round(s_ref, 3) if ref is not None else "RenderLimitError",
                            "render_s_after": round(s_got, 3) if got is not None else "RenderLimitError",
                            "psnr_vs_unculled": (round(metrics.psnr(got.colour, ref.colour), 2)
                                                 if ref is not None and got is not None else None)},
        }
        _log(f"  cull {tn}: erp -{len(kept_all) - idx.size} {erp['render_s']:.2f}s {erp['psnr']:.3f}dB; "
             f"persp -{len(kept_all) - pidx.size} {s_ref:.2f}->{s_got:.2f}s (refused: {ref is None}, {got is None})")
    return res


def abs_rel(range_maps: np.ndarray, scene, refs) -> float:
    """Mean |pred - gt| / gt over valid pixels of both references' Yin/Yang grids."""
    errs = []
    for v, name in enumerate(refs):
        gts = erp_to_yin_yang(scene.frames[name].depth(), nearest=True)
        for g in range(2):
            gt = gts[g]
            pred = range_maps[v, g]
            if pred.shape != gt.shape:
                return float("nan")
            ok = gt > 0
            errs.append(np.abs(pred[ok] - gt[ok]) / gt[ok])
    return float(np.mean(np.concatenate(errs)))


def bench_adaptive(encoder, coarse_encoder, scene, refs, targets, images) -> dict:
    """Default range vs two-pass adaptive (same model / smaller coarse model)."""
    from .scene_adaptive import AdaptiveRangeOptions, reconstruct_adaptive
    a, b = scene.frames[refs[0]], scene.frames[refs[1]]
    ia, ib = a.image(), b.image()
    runs = {"default": lambda: encoder.reconstruct(ia, ib, a.c2w, b.c2w),
            "adaptive_same_model": lambda: reconstruct_adaptive(encoder, ia, ib, a.c2w, b.c2w,
                                                                options=AdaptiveRangeOptions(enabled=True))}
    if coarse_encoder is not None:
        runs["adaptive_coarse_256"] = lambda: reconstruct_adaptive(
            encoder, ia, ib, a.c2w, b.c2w, options=AdaptiveRangeOptions(enabled=True), coarse_encoder=coarse_encoder)
    out = {}
    for name, fn in runs.items():
        t = time.perf_counter()
        rec = fn()
        sec = time.perf_counter() - t
        row = {"encoder_s": round(sec, 3), "near": round(rec.info["near"], 3), "far": round(rec.info["far"], 3),
               "psnr": {tn: evaluate(rec.gaussians, targets[tn], images[tn])["psnr"] for tn in targets}}
        if scene.has_depth:
            row["abs_rel"] = round(abs_rel(rec.range_maps, scene, refs), 4)
        out[name] = row
        _log(f"  adaptive {name}: {row}")
    return out


def run(data_dirs, model: Path | None, use_gt: bool, adaptive: bool) -> dict:
    from .encoder import OnnxEncoder
    encoder = OnnxEncoder(model or ensure_model(512, 1024, 32))
    coarse = OnnxEncoder(ensure_model(256, 512, 32)) if adaptive else None
    results: dict = {"model": encoder.metadata.get("name"), "model_sha256": encoder.metadata.get("sha256"),
                     "num_planes": encoder.num_planes, "render": f"ERP {RENDER_WIDTH}x{RENDER_WIDTH // 2} via Yin-Yang",
                     "cpu_count": os.cpu_count(), "load_avg_start": os.getloadavg(), "splits": []}
    for d in data_dirs:
        scene = load_scene(d)
        for split in scene.splits:
            refs = split.references
            targets = {tn: scene.frames[tn] for tn in split.targets}
            images = {tn: f.image() for tn, f in targets.items()}
            entry = {"scene": scene.name, "references": list(refs), "targets": list(targets), "sources": {}}
            _log(f"{scene.name} {refs} -> {list(targets)}")
            a, b = scene.frames[refs[0]], scene.frames[refs[1]]
            rec = encoder.reconstruct(a.image(), b.image(), a.c2w, b.c2w)
            prov = Provenance.from_reconstruction(rec, a.c2w, b.c2w)
            entry["encoder_s"] = round(rec.timings["total"], 3)
            _log(" encoder Gaussians")
            entry["sources"]["encoder"] = bench_source(rec.gaussians, prov, targets, images, rec.confidence)
            if use_gt and scene.has_depth:
                _log(" GT-depth Gaussians")
                g, p = gt_gaussians(scene, refs)
                entry["sources"]["gt_depth"] = bench_source(g, p, targets, images)
            if adaptive:
                entry["adaptive"] = bench_adaptive(encoder, coarse, scene, refs, targets, images)
            results["splits"].append(entry)
    results["load_avg_end"] = os.getloadavg()
    return results


def summary_rows(results: dict) -> list[dict]:
    """Per (split, source, variant): totals over targets, relative to 'none'."""
    rows = []
    for e in results["splits"]:
        for src, res in e["sources"].items():
            base = res["variants"]["none"]["targets"]
            for name, v in res["variants"].items():
                t = v["targets"]
                n0 = next(iter(base.values()))["count"]
                n = next(iter(t.values()))["count"]
                rows.append({
                    "split": f"{e['scene']} {'+'.join(e['references'])}", "source": src, "variant": name,
                    "count": n, "fewer_pct": round(100 * (1 - n / n0), 1),
                    "ply_mb": round(next(iter(t.values()))["ply_bytes"] / 1e6, 2),
                    "render_s": round(sum(r["render_s"] for r in t.values()), 2),
                    "render_less_pct": round(100 * (1 - sum(r["render_s"] for r in t.values())
                                                     / sum(r["render_s"] for r in base.values())), 1),
                    "dpsnr": round(float(np.mean([t[k]["psnr"] - base[k]["psnr"] for k in t])), 3),
                    "psnr": round(float(np.mean([r["psnr"] for r in t.values()])), 3),
                })
    return rows


def markdown(results: dict) -> str:
    rows = summary_rows(results)
    lines = ["# Compaction bench", "",
             f"Model {results['model']} ({results['num_planes']} planes), render {results['render']}, "
             f"{results['cpu_count']} CPUs, load average {results['load_avg_start'][0]:.1f} -> "
             f"{results['load_avg_end'][0]:.1f}. Render seconds are single runs: noisy, more so the higher "
             "the load average; read them as a trend.", "",
             "Per split and source, totals over the split's targets; ΔPSNR vs 'none', mean over targets.", "",
             "| split | source | variant | Gaussians | fewer % | PLY MB | render s | render less % | PSNR | ΔPSNR dB |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['split']} | {r['source']} | {r['variant']} | {r['count']:,} | {r['fewer_pct']} | "
                     f"{r['ply_mb']} | {r['render_s']} | {r['render_less_pct']} | {r['psnr']} | {r['dpsnr']:+.3f} |")
    lines += ["", "## Render-time culling (on the 'all' set)", "",
              "| split | source | target | ERP culled | ERP render s | ERP PSNR | persp culled | persp s before -> after | persp PSNR vs unculled |",
              "|---|---|---|---|---|---|---|---|---|"]
    for e in results["splits"]:
        for src, res in e["sources"].items():
            for tn, c in res["culling"].items():
                p = c["perspective"]
                lines.append(f"| {e['scene']} | {src} | {tn} | {c['erp']['culled']:,} | {c['erp']['render_s']} | "
                             f"{c['erp']['psnr']} | {p['culled']:,} | {p['render_s_before']} -> {p['render_s_after']} | "
                             f"{p['psnr_vs_unculled']} |")
    if any("adaptive" in e for e in results["splits"]):
        lines += ["", "## Adaptive near/far (uncompacted encoder Gaussians)", "",
                  "| split | run | encoder s | near | far | PSNR per target | AbsRel |", "|---|---|---|---|---|---|---|"]
        for e in results["splits"]:
            for name, r in e.get("adaptive", {}).items():
                ps = ", ".join(f"{k} {v:.3f}" for k, v in r["psnr"].items())
                lines.append(f"| {e['scene']} {'+'.join(e['references'])} | {name} | {r['encoder_s']} | {r['near']} | "
                             f"{r['far']} | {ps} | {r.get('abs_rel', '')} |")
    lines += ["", "## Notes", "",
              "* Steps: `min_opacity` (encoder opacities are >= 0.35, so 1/255 removes nothing there), "
              "`resolve_overlap` ('split' = larger domain margin keeps, the renderer's own merge rule; "
              "'yin' = Yin whole), `merge_duplicates` (other view's pixel at the same range within "
              "`duplicate_range_tol`, the Gaussian farther from its own camera goes), `max_count`/`max_bytes` cap.",
              "* `min_confidence` (off by default) and the cap punch holes with the training-free encoder: "
              "unconfident pixels are whole regions (walls without texture), not scattered noise.",
              "* Culling: `rasterizer.render_cull.cull_for_camera` (near, frustum/domain widened by 3 sigma, "
              "occlusion on a coarse ERP cell grid). A perspective render of the uncompacted or compacted set "
              "without it can hit the renderer's RenderLimitError (Gaussians just in front of the camera).",
              "* Adaptive near/far: the plane count is fixed per exported model (static shapes).",
              ]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="bench_compaction", description=__doc__.splitlines()[0])
    p.add_argument("--data", nargs="+", type=Path, default=DEFAULT_DATA)
    p.add_argument("--out", type=Path, default=REPO / "docs" / "bench")
    p.add_argument("--model", type=Path, default=None, help="512x1024 encoder .onnx (default: export into the cache)")
    p.add_argument("--no-gt", action="store_true", help="skip the GT-depth Gaussians")
    p.add_argument("--no-adaptive", action="store_true", help="skip the adaptive near/far runs")
    args = p.parse_args(argv)
    results = run(args.data, args.model, not args.no_gt, not args.no_adaptive)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "compaction.json").write_text(json.dumps(results, indent=1, default=float))
    (args.out / "compaction.md").write_text(markdown(results))
    _log(f"wrote {args.out / 'compaction.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
