"""Detail at a capture point: PSNR, sharpness and GMSD of renders at the references' own poses and at targets.

``omnisplat-bench detail`` runs one split of each scene folder through the service's path
(:func:`service.pipeline.build_scene`, the PLY the API stores, the API's ERP render) and scores every
view with the metrics of conventions section 6 (:mod:`bench.metrics`): PSNR, sharpness (1 = as sharp as
the captured image) and GMSD (0 = identical structure), which see the blur and ghosting PSNR misses.
Synthetic scenes (with depth) are scored on the whole image, real captures above the nadir cap
(:data:`bench.metrics.NADIR_CAP_DEG`: their rig shows below it). Per scene it also reports the Gaussian
count, PLY and SPZ size, POST seconds and the process's peak RSS, per input size (``--width``).
"""

from __future__ import annotations

import sys

import numpy as np

from .metrics import NADIR_CAP_DEG, gmsd, psnr_above_nadir, sharpness

#: Default scene folders (under ``bench.DEV_DATA``): one synthetic with exact depth, one real 2k capture.
DEFAULT_SCENES = ("m3d_bedroom", "zind_room09_2k")


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _peak_rss_mb() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def view_metrics(render: np.ndarray, reference: np.ndarray, cap_deg: float) -> dict:
    """PSNR (dB), sharpness and GMSD of one (H, W, 3) render against its captured image, over the rows
    above ``cap_deg`` degrees around the nadir (0: every row)."""
    return {"psnr": round(psnr_above_nadir(render, reference, cap_deg), 3),
            "sharpness": round(sharpness(render, reference, cap_deg), 4),
            "gmsd": round(gmsd(render, reference, cap_deg), 4)}


def measure_split(encoder, scene, split_index: int = 0, options: dict | None = None, width: int | None = None,
                  render_width: int | None = None) -> dict:
    """One split of a scene folder: build the scene as a POST does, store it as the PLY, render it as the
    render route does (ERP, plain compositing) at each reference's and target's pose, and score each view.

    width: resize the inputs to this ERP width first (bilinear: a larger copy has no more detail, it
    measures cost). render_width: render (and score against the images resized to) this width instead
    of the input's. Returns a JSON-able row: counts, PLY and SPZ MB, seconds, peak RSS MB and one entry per view.
    """
    import time

    from rasterizer.ply import ply_bytes, read_ply
    from rasterizer.render import render
    from rasterizer.spz import spz_bytes
    from rasterizer.yin_yang import resize_erp
    from service.pipeline import PipelineOptions, build_scene

    split = scene.splits[split_index]
    frames = {name: scene.frames[name] for name in split.references + split.targets}
    images = {name: f.image() for name, f in frames.items()}
    if width is not None:
        images = {k: resize_erp(v, int(width) // 2, int(width)) for k, v in images.items()}
    ra, rb = split.references
    cap_deg = 0.0 if scene.has_depth else NADIR_CAP_DEG
    t0 = time.perf_counter()
    built = build_scene(encoder, images[ra], images[rb], frames[ra].c2w, frames[rb].c2w,
                        PipelineOptions.from_dict(options))
    ply = ply_bytes(built.gaussians)
    post_s = time.perf_counter() - t0
    gaussians = read_ply(ply)  # what the store serves
    row = {"scene": scene.name, "split": f"{ra}+{rb}", "input": list(images[ra].shape[:2]), "cap_deg": cap_deg,
           "gaussians": len(gaussians), "ply_mb": round(len(ply) / 2**20, 2),
           "spz_mb": round(len(spz_bytes(gaussians)) / 2**20, 2), "post_s": round(post_s, 3),
           "timings": {k: round(v, 3) for k, v in built.timings.items()}, "views": []}
    for name in split.references + split.targets:
        ref = images[name]
        if render_width is not None and render_width != ref.shape[1]:
            ref = resize_erp(ref, int(render_width) // 2, int(render_width))
        t = time.perf_counter()
        out = render(gaussians, frames[name].c2w, projection="erp", width=ref.shape[1], normalize=False).colour
        seconds = time.perf_counter() - t
        role = "reference" if name in split.references else "target"
        row["views"].append({"view": name, "role": role, "render_s": round(seconds, 3),
                             **view_metrics(out, ref, cap_deg)})
    row["peak_rss_mb"] = round(_peak_rss_mb(), 1)
    return row


def build_parser():
    import argparse

    ap = argparse.ArgumentParser(prog="omnisplat-bench detail", description=(
        "PSNR, sharpness and GMSD of renders at the references' own poses and at the targets; per scene "
        "its Gaussian count, PLY and SPZ size, POST seconds and peak RSS."))
    ap.add_argument("--scene", action="append",
                    help=f"dev scene folder name, repeatable (default: {', '.join(DEFAULT_SCENES)})")
    ap.add_argument("--split", type=int, default=0, help="split index of each scene (default 0)")
    ap.add_argument("--width", type=int, default=None, help="resize the inputs to this ERP width first")
    ap.add_argument("--render-width", type=int, default=None, help="render width (default: the input's)")
    ap.add_argument("--options", default="{}", help="the API's options JSON object")
    ap.add_argument("--model", default=None, help="ONNX model (default: the service's configured model, built "
                                                   "if missing)")
    ap.add_argument("--json", default=None, help="write the rows to this file")
    return ap


def main(argv: list[str] | None = None) -> int:
    """Print one line per scene, then one per view; ``--json`` writes the rows."""
    import json

    from rasterizer.scene_folder import load_scene
    from service.config import Settings
    from service.encoder import OnnxEncoder
    from service.model_files import ensure_model

    from . import DEV_DATA

    args = build_parser().parse_args(argv)
    options = json.loads(args.options)
    encoder = OnnxEncoder(args.model or ensure_model(Settings().resolved_model_path, build_if_missing=True))
    rows = []
    for name in args.scene or DEFAULT_SCENES:
        _log(f"[detail] {name}")
        row = measure_split(encoder, load_scene(DEV_DATA / name), args.split, options, args.width, args.render_width)
        rows.append(row)
        h, w = row["input"]
        scored = f"above {row['cap_deg'] - 90:g} deg latitude" if row["cap_deg"] else "every row"
        print(f"{row['scene']} {row['split']} {w}x{h}: {row['gaussians']} Gaussians, PLY {row['ply_mb']} MB, "
              f"SPZ {row['spz_mb']} MB, POST {row['post_s']} s, peak RSS {row['peak_rss_mb']} MB (scored: {scored})", flush=True)
        for v in row["views"]:
            print(f"  {v['role']:9s} {v['view']:7s} PSNR {v['psnr']:6.2f}  sharpness {v['sharpness']:.3f}  "
                  f"GMSD {v['gmsd']:.4f}  render {v['render_s']:.2f} s", flush=True)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
