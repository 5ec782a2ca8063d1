"""Compaction, render-time culling and adaptive sweep range, measured on the dev scenes.

    python -m bench.compaction [--data DIR ...] [--out docs/bench] [--model M.onnx] [--no-gt] [--no-adaptive]
                                       [--readme README.md]

For every split and target: Gaussian count, PLY bytes, render seconds
(512x1024 ERP via Yin-Yang) and PSNR before and after each compaction step
and all together; render-time culling (ERP and a 90-degree perspective
view); and the two-pass adaptive near/far (seconds, PSNR, depth AbsRel on
m3d GT). Sources: the real encoder (the shipped 512x1024 "quality" preset from the
bench model cache, :func:`bench.models.bench_model`, or ``--model``) and, where a scene has depth, GT-depth
Gaussians in the same grid layout. Writes compaction.json / compaction.md and, with
``--readme``, the README's marked compaction block (the shipped default against none, per split).
Render timings are the best of RENDER_REPEATS round-robin runs over the variants (noisy on a shared
machine; the report gives the load average); render contributions are the load-free measure of render cost.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from bench import metrics
from bench.render_cull import cull_for_camera
from export.config import PRESETS
from rasterizer.compaction import CompactionOptions, Provenance, compact
from rasterizer.depth_gaussians import gaussians_from_depth
from rasterizer.gaussians import Gaussians
from rasterizer.ply import ply_bytes
from rasterizer.render import render
from rasterizer.scene_folder import load_scene
from rasterizer.splat import RenderLimitError
from rasterizer.yin_yang import erp_to_yin_yang

from .models import bench_model
from .quality import COMPOSITING_LABEL, composited
from .report import readme_markers, update_readme

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = [REPO.parent / "shared" / "data" / "m3d_bedroom", REPO.parent / "shared" / "data" / "zind_room09"]
RENDER_WIDTH = 1024


def _log(msg: str) -> None:
    print(f"[bench compaction] {msg}", file=sys.stderr, flush=True)


def variants(n: int) -> dict[str, CompactionOptions]:
    """Each step alone, the shipped default (also with 4x4 blocks), and a 60% count cap with and without the rest."""
    off = CompactionOptions.off()
    cap = int(0.6 * n)

    def only(**kw) -> CompactionOptions:
        return CompactionOptions(**{**off.to_dict(), **kw})

    return {
        "none": off,
        "min_opacity": only(min_opacity=1.0 / 255.0),
        "smooth": only(merge_smooth=True),
        "cap60": only(max_count=cap),
        "all": CompactionOptions(),
        "all_smooth4x4": CompactionOptions(smooth_levels=2),
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


#: Render timings are the best of this many runs (one run on a shared machine is noisy).
RENDER_REPEATS = 3


def timed_render(g: Gaussians, c2w, repeats: int = 1, **kw):
    """(RenderOutput or None when the renderer refuses (RenderLimitError), best seconds of ``repeats``)."""
    best = np.inf
    out = None
    for _ in range(max(1, repeats)):
        t = time.perf_counter()
        try:
            out = render(g, c2w, **kw)
        except RenderLimitError:
            return None, time.perf_counter() - t
        best = min(best, time.perf_counter() - t)
    return out, best


def contributions(g: Gaussians, c2w) -> int:
    """(pixel, Gaussian) pairs the ERP render's Yin and Yang cameras composite (render cost, load-free)."""
    from rasterizer.camera import Camera
    from rasterizer.splat import footprints

    h = RENDER_WIDTH // 4
    return sum(len(footprints(g, Camera(kind, 3 * h, h, c2w), opacity_bound=g.opacities)) for kind in ("yin", "yang"))


#: Compositing of the scored ERP renders (``--compositing``; bench.quality.COMPOSITING).
COMPOSITING = {"mode": "plain"}


def erp_colour(g: Gaussians, c2w, repeats: int = 1):
    """(colour in the chosen compositing or None, best seconds) of the Yin-Yang ERP render."""
    out, sec = timed_render(g, c2w, repeats, projection="erp", width=RENDER_WIDTH)
    if out is None:
        return None, sec
    return composited(out.colour, out.alpha, "yinyang", COMPOSITING["mode"]), sec


def evaluate(g: Gaussians, target, gt_img, reference: np.ndarray | None = None, repeats: int = 1) -> dict:
    """Count, PLY bytes, render seconds, PSNR against the target image (and against ``reference``)."""
    colour, sec = erp_colour(g, target.c2w, repeats)
    row = {"count": len(g), "ply_bytes": len(ply_bytes(g)), "render_s": round(sec, 3),
           "psnr": round(metrics.psnr(colour, gt_img), 4), "contributions": contributions(g, target.c2w)}
    if reference is not None:
        row["psnr_vs_none"] = round(metrics.psnr(colour, reference), 2)
    return row


def bench_source(g: Gaussians, prov: Provenance, targets, images, conf=None) -> dict:
    """All variants x targets for one set of Gaussians; plus culling on the 'all' set."""
    res: dict = {"variants": {}, "culling": {}}
    kept_all = None
    uncompacted = {tn: erp_colour(g, targets[tn].c2w)[0] for tn in targets}
    sets = {}
    for name, opts in variants(len(g)).items():
        best = np.inf
        for _ in range(RENDER_REPEATS):  # best of a few: one run on a shared machine is noisy
            t = time.perf_counter()
            gc, stats = compact(g, prov, opts, confidence=conf)
            best = min(best, time.perf_counter() - t)
        per_t = {tn: evaluate(gc, targets[tn], images[tn], uncompacted[tn]) for tn in targets}
        res["variants"][name] = {"compact_s": round(best, 3), "removed": stats["removed"],
                                 "merge_smooth": stats.get("merge_smooth"), "seconds": stats.get("seconds"),
                                 "targets": per_t}
        sets[name] = gc
        _log(f"  {name}: {len(gc)} Gaussians, " + ", ".join(f"{tn} {r['psnr']:.3f}dB" for tn, r in per_t.items()))
        if name == "all":
            kept_all = gc
    # render timings round-robin over the variants, best of RENDER_REPEATS: a load change on the shared
    # machine then hits every variant alike instead of whichever happened to run during it
    best_s = {(name, tn): np.inf for name in sets for tn in targets}
    for _ in range(RENDER_REPEATS):
        for name, gc in sets.items():
            for tn, tgt in targets.items():
                best_s[name, tn] = min(best_s[name, tn], timed_render(gc, tgt.c2w, projection="erp",
                                                                      width=RENDER_WIDTH)[1])
    for (name, tn), sec in best_s.items():
        res["variants"][name]["targets"][tn]["render_s"] = round(sec, 3)
    _log("  render s (best of round-robin): " + ", ".join(
        f"{name} {sum(best_s[name, tn] for tn in targets):.2f}" for name in sets))
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
    from service.scene_adaptive import AdaptiveRangeOptions, reconstruct_adaptive
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
    from service.encoder import OnnxEncoder
    encoder = OnnxEncoder(model or bench_model(512, 1024, PRESETS["quality"]["num_planes"]))
    coarse = OnnxEncoder(bench_model(256, 512, 32)) if adaptive else None
    results: dict = {"model": encoder.metadata.get("name"), "model_sha256": encoder.metadata.get("sha256"),
                     "num_planes": encoder.num_planes, "render": f"ERP {RENDER_WIDTH}x{RENDER_WIDTH // 2} via Yin-Yang, "
                     f"{COMPOSITING_LABEL[COMPOSITING['mode']]}", "compositing": COMPOSITING["mode"],
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
                    "dpsnr_min": round(float(np.min([t[k]["psnr"] - base[k]["psnr"] for k in t])), 3),
                    "psnr": round(float(np.mean([r["psnr"] for r in t.values()])), 3),
                    "psnr_vs_none": round(float(np.mean([r.get("psnr_vs_none", np.inf) for r in t.values()])), 2),
                    "contrib_less_pct": round(100 * (1 - sum(r.get("contributions", 0) for r in t.values())
                                                     / max(1, sum(r.get("contributions", 0)
                                                                  for r in base.values()))), 1),
                    "compact_s": v.get("compact_s"),
                })
    return rows


def markdown(results: dict) -> str:
    rows = summary_rows(results)
    lines = ["# Compaction bench", "",
             f"Model {results['model']} ({results['num_planes']} planes, sha256 {str(results.get('model_sha256'))[:12]}), "
             f"render {results['render']}, "
             f"{results['cpu_count']} CPUs, load average {results['load_avg_start'][0]:.1f} -> "
             f"{results['load_avg_end'][0]:.1f}. Render seconds are the best of {RENDER_REPEATS} runs, "
             "taken round-robin over the variants (culling: single runs): noisy, more so the higher the load average; "
             "read them as a trend, and "
             "the contributions as the load-free render cost.", "",
             "Per split and source, totals over the split's targets; ΔPSNR vs 'none' against the target images, "
             "mean (and worst) over targets; 'vs none' = PSNR between this variant's and the uncompacted render "
             "(mean over targets); contributions = (pixel, Gaussian) pairs the renderer composites (load-free "
             f"render cost); compact s = the compaction itself, best of {RENDER_REPEATS} runs.", "",
             "| split | source | variant | Gaussians | fewer % | PLY MB | compact s | render s | render less % | "
             "contrib. less % | PSNR | ΔPSNR dB (worst) | vs none dB |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['split']} | {r['source']} | {r['variant']} | {r['count']:,} | {r['fewer_pct']} | "
                     f"{r['ply_mb']} | {r['compact_s']} | {r['render_s']} | {r['render_less_pct']} | "
                     f"{r['contrib_less_pct']} | {r['psnr']} | {r['dpsnr']:+.3f} ({r['dpsnr_min']:+.3f}) | "
                     f"{r['psnr_vs_none']} |")
    lines += ["", "## Compaction run time and the smooth merge (encoder Gaussians)", "",
              "compact s: best of the runs; seconds per step: the last run.", "",
              "| split | variant | compact s | seconds per step | smooth merge: inputs merged -> added (blocks) |",
              "|---|---|---|---|---|"]
    for e in results["splits"]:
        res = e["sources"].get("encoder")
        if res is None:
            continue
        for name in ("smooth", "all", "all_smooth4x4"):
            v = res["variants"].get(name)
            if v is None:
                continue
            secs = ", ".join(f"{k} {x:.3f}" for k, x in (v.get("seconds") or {}).items())
            ms = v.get("merge_smooth") or {}
            blocks = ", ".join(f"{k}x{k}: {c:,}" for k, c in (ms.get("blocks") or {}).items())
            lines.append(f"| {e['scene']} {'+'.join(e['references'])} | {name} | {v['compact_s']} | {secs} | "
                         f"{ms.get('merged', 0):,} -> {ms.get('added', 0):,} ({blocks}) |")
    lines += ["", "## Render-time culling (on the 'all' set)", "",
              "| split | source | target | ERP culled | ERP render s | ERP PSNR | persp culled | persp s before -> after "
              "| persp PSNR vs unculled |",
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
              "* Steps: `min_opacity` (encoder opacities are >= 0.15, so 1/255 removes nothing there), "
              "`merge_smooth` (2x2 blocks "
              "of one grid, all present, texture under a tenth of the grid's contrast, DC colour within "
              "`smooth_colour_tol`, opacity within "
              "`smooth_opacity_tol`, on a plane within `smooth_plane_tol` x range seen at most "
              "`smooth_max_incidence_deg` off its normal -> one moment-matched Gaussian keeping the block's "
              "optical depth; `all_smooth4x4` = `all` with 4x4 blocks too), `max_count`/`max_bytes` cap. "
              "'all' = the shipped default (min opacity + smooth merge). Every reference keeps its own copies "
              "of a surface and both grids' overlap (docs/design.md, Compaction).",
              "* Smooth merge: the merged opacity keeps the block's optical depth (A' Li2(a') = sum A_i Li2(a_i), "
              "footprint areas with half the renderer's low-pass at the grid's pixel size); it saturates at 0.99 "
              "for opaque 2x2 blocks (about 93% coverage between merged Gaussians at the grid's resolution; the "
              "ERP and service renders divide colour by alpha). 4x4 blocks (`smooth_levels` 2) merge only where "
              "one Gaussian keeps the optical depth, widened in-plane to 0.45 of their size against lattice "
              "ripple. The incidence limit is what keeps the PSNR: on zind pano_5 (2x2 blocks, against the "
              "set without the merge, encoder 0.3.0 at 32 planes) 75 / 60 / 45 degrees cost -0.12 / "
              "-0.09 / -0.00 dB; opacity and colour tolerances mattered much less.",
              "* `min_confidence` (off by default) and the cap punch holes with the training-free encoder: "
              "unconfident pixels are whole regions (walls without texture), not scattered noise.",
              "* Culling: `bench.render_cull.cull_for_camera` (near, frustum/domain widened by 3 sigma, "
              "occlusion on a coarse ERP cell grid). A perspective render of the uncompacted or compacted set "
              "without it can hit the renderer's RenderLimitError (Gaussians just in front of the camera).",
              "* Adaptive near/far: the plane count is fixed per exported model (static shapes).",
              ]
    return "\n".join(lines) + "\n"


README_VARIANTS = ("none", "all")


def readme_block(results: dict, report_path: str) -> str:
    """The README's compaction table: per split, no compaction and the shipped default."""
    start, end = readme_markers("compaction")
    lines = [start, "",
             f"Model {results['model']} ({results['num_planes']} planes), render {results['render']}, load average "
             f"{results['load_avg_start'][0]:.1f} -> {results['load_avg_end'][0]:.1f}; 'default' is what the service "
             f"and CLI do. Full report: [{report_path}]({report_path}).", "",
             "| split | source | variant | Gaussians | fewer % | contributions less % | render s | render less % | "
             f"ΔPSNR dB {COMPOSITING_LABEL[results.get('compositing', 'va')]} (worst target) | compact s |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    names = {"none": "none", "all": "default (smooth merge)"}
    for r in summary_rows(results):
        if r["variant"] in README_VARIANTS:
            lines.append(f"| {r['split']} | {r['source']} | {names[r['variant']]} | {r['count']:,} | {r['fewer_pct']} | "
                         f"{r['contrib_less_pct']} | {r['render_s']} | {r['render_less_pct']} | "
                         f"{r['dpsnr']:+.3f} ({r['dpsnr_min']:+.3f}) | {r['compact_s']} |")
    return "\n".join(lines + ["", end])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="bench_compaction", description=__doc__.splitlines()[0])
    p.add_argument("--data", nargs="+", type=Path, default=DEFAULT_DATA)
    p.add_argument("--out", type=Path, default=REPO / "docs" / "bench")
    p.add_argument("--model", type=Path, default=None, help="512x1024 encoder .onnx (default: export into the cache)")
    p.add_argument("--no-gt", action="store_true", help="skip the GT-depth Gaussians")
    p.add_argument("--no-adaptive", action="store_true", help="skip the adaptive near/far runs")
    p.add_argument("--readme", type=Path, default=None, help="also rewrite this README's marked compaction block")
    p.add_argument("--compositing", choices=tuple(COMPOSITING_LABEL), default="plain",
                   help="plain: over black, no division (default, what viewers show); va: divided by alpha")
    args = p.parse_args(argv)
    COMPOSITING["mode"] = args.compositing
    results = run(args.data, args.model, not args.no_gt, not args.no_adaptive)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "compaction.json").write_text(json.dumps(results, indent=1, default=float))
    (args.out / "compaction.md").write_text(markdown(results))
    _log(f"wrote {args.out / 'compaction.md'}")
    if args.readme is not None:
        rel = os.path.relpath(args.out / "compaction.md", args.readme.resolve().parent)
        if not update_readme(args.readme, readme_block(results, rel), "compaction"):
            _log(f"{args.readme} has no compaction markers; left unchanged")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
