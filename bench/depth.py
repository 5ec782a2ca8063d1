"""Depth and novel-view benchmark of exported encoders (not a test; prints JSON).

For every model and scene split: reconstruct the two references with
:class:`service.encoder.OnnxEncoder` (median of ``--repeats`` runs; the CPU
is shared, so timings are noisy), depth AbsRel / delta<1.25 of the range
maps against GT on valid GT pixels of each reference (Yin/Yang maps merged
to the ERP with :func:`rasterizer.yin_yang.yin_yang_to_erp`), and PSNR /
SSIM / WS-PSNR of ``rasterizer.render.render`` at every target.

    python -m bench.depth --export fast quality erp-fast --scene m3d_bedroom zind_room09
    python -m bench.depth --model a.onnx --scene m3d_bedroom
"""

from __future__ import annotations

import argparse
import json
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

from bench import DEV_DATA
from bench.metrics import psnr, ssim, ws_psnr
from rasterizer.scene_folder import load_scene
from rasterizer.yin_yang import resize_erp, yin_yang_to_erp

DATA = DEV_DATA


def depth_metrics(pred: np.ndarray, gt: np.ndarray) -> dict:
    """AbsRel and delta<1.25 on GT-valid pixels (gt > 0)."""
    ok = (gt > 0) & np.isfinite(gt)
    p, g = pred[ok].astype(np.float64), gt[ok].astype(np.float64)
    ratio = np.maximum(p / g, g / np.maximum(p, 1e-9))
    return {"absrel": float(np.mean(np.abs(p - g) / g)), "delta1": float(np.mean(ratio < 1.25))}


def range_to_erp(maps: np.ndarray, height: int, width: int) -> np.ndarray:
    """(G, h, w) range maps of one view -> (height, width) ERP range."""
    if maps.shape[0] == 1:
        return resize_erp(maps[0], height, width)
    return yin_yang_to_erp(maps[0], maps[1], height, width)


def evaluate(model: Path, scene_dir: Path, *, repeats: int = 3, render_width: int = 1024, do_render: bool = True) -> dict:
    from service.encoder import OnnxEncoder

    enc = OnnxEncoder(model, threads=2)
    scene = load_scene(scene_dir)
    result = {"model": str(model), "settings": enc.metadata["settings"], "scene": scene.name, "splits": []}
    for split in scene.splits:
        fa, fb = (scene.frames[n] for n in split.references)
        img_a, img_b = fa.image(), fb.image()
        runs = [enc.reconstruct(img_a, img_b, fa.c2w, fb.c2w) for _ in range(repeats)]
        rec = runs[-1]
        entry = {
            "references": list(split.references),
            "onnx_s_median": float(np.median([r.timings["onnx"] for r in runs])),
            "total_s_median": float(np.median([r.timings["total"] for r in runs])),
            "timings_last": rec.timings,
            "peak_rss_mb_after_encoder": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "near": rec.info["near"], "far": rec.info["far"], "baseline": rec.info["baseline"],
            "mean_confidence": rec.info["mean_confidence"],
        }
        for v, f in enumerate((fa, fb)):
            gt = f.depth()
            if gt is not None:
                entry[f"depth_{f.name}"] = depth_metrics(range_to_erp(rec.range_maps[v], *gt.shape), gt)
        if do_render:
            from rasterizer.render import render

            for name in split.targets:
                tgt = scene.frames[name]
                gt_img = tgt.image()
                if gt_img.shape[1] != render_width:
                    gt_img = resize_erp(gt_img, render_width // 2, render_width)
                t = time.perf_counter()
                out = render(rec.gaussians, tgt.c2w, projection="erp", width=render_width)
                entry[f"view_{name}"] = {"psnr": psnr(out.colour, gt_img), "ssim": ssim(out.colour, gt_img),
                                         "ws_psnr": ws_psnr(out.colour, gt_img),
                                         "render_s": time.perf_counter() - t}
        result["splits"].append(entry)
    return result


def main(argv: list[str] | None = None) -> int:
    from export.onnx_export import export_model

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", type=Path, nargs="*", default=[])
    p.add_argument("--export", nargs="*", default=[], help="presets to export first: fast, quality, erp-fast, ...")
    p.add_argument("--scene", nargs="+", default=["m3d_bedroom"])
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--no-render", action="store_true")
    p.add_argument("--set", action="append", default=[], help="extra EncoderConfig override key=json")
    args = p.parse_args(argv)
    models = list(args.model)
    tmp = Path(tempfile.mkdtemp(prefix="omnisplat-bench-"))
    overrides = {k: json.loads(v) for k, v in (s.split("=", 1) for s in args.set)}
    for name in args.export:
        erp = name.startswith("erp-")
        preset = name[4:] if erp else name
        models.append(export_model(tmp / f"{name}.onnx", preset=preset, erp_encoder=erp, **overrides))
    for model in models:
        for scene in args.scene:
            print(json.dumps(evaluate(model, DATA / scene, repeats=args.repeats, do_render=not args.no_render)), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
