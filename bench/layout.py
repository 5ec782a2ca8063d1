"""``omnisplat-bench layout``: what the indoor layout prior changes, before / after, on every dev split.

For each split of the dev scenes: reconstruct with the shipped encoder (after) and with the same
encoder exported without the layout prior (before: ``layout_strength`` 0, export/layout.py), render
every target plain (direct ERP 1024x512, front to back over black, no division by alpha) and report
PSNR and WS-PSNR of both, the nearest reference rotated into the target's orientation (the floor a
reconstruction has to beat), the fraction of target pixels with accumulated alpha >= 0.99, and the
seconds of one reconstruction (second run of each model; the difference is the prior's cost).
Writes docs/bench/layout.{json,md}, a picture of one zind target (ground truth | before | after) and
the README block ``layout``.

    omnisplat-bench layout [--data DIR ...] [--out docs/bench] [--readme README.md]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from rasterizer.render import render
from rasterizer.scene_folder import load_scene
from rasterizer.yin_yang import resize_erp

from . import DEV_DATA
from .baselines import copy_nearest
from .coverage import COVERED
from .figures import strip
from .machine import machine_info, machine_line
from .metrics import psnr, ws_psnr
from .models import bench_model
from .report import readme_markers, update_readme, write_json

WIDTH = 1024
#: (scene, target) shown in the picture.
FIGURE = ("zind_room09", "pano_5")


def _log(msg: str) -> None:
    print(f"[bench layout] {msg}", file=sys.stderr, flush=True)


def run(data: list[Path], threads: int, out: Path) -> dict:
    """Per-target rows (see the module docstring) and the figure's path."""
    from export.config import PRESETS
    from service.encoder import OnnxEncoder

    planes = PRESETS["quality"]["num_planes"]
    encoders = {key: OnnxEncoder(bench_model(512, 1024, planes, layout=key == "after", log=_log), threads=threads)
                for key in ("before", "after")}
    rows, seconds, figure = [], [], None
    for folder in data:
        scene = load_scene(folder)
        for split in scene.splits:
            fa, fb = (scene.frames[n] for n in split.references)
            refs = [(fa.image(), fa.c2w), (fb.image(), fb.c2w)]  # decoded once, used by every run below
            (img_a, c2w_a), (img_b, c2w_b) = refs
            views, secs = {}, {}
            for key, enc in encoders.items():
                enc.reconstruct(img_a, img_b, c2w_a, c2w_b)  # warm-up
                t = time.perf_counter()
                rec = enc.reconstruct(img_a, img_b, c2w_a, c2w_b)
                secs[key] = time.perf_counter() - t
                for name in split.targets:
                    views[key, name] = render(rec.gaussians, scene.frames[name].c2w, projection="erp", width=WIDTH,
                                              method="direct")
            seconds.append({"scene": scene.name, "references": list(split.references), **secs})
            for name in split.targets:
                frame = scene.frames[name]
                gt = resize_erp(frame.image(), WIDTH // 2, WIDTH)
                copy = copy_nearest(refs, frame.c2w, WIDTH // 2, WIDTH)
                row = {"scene": scene.name, "references": list(split.references), "target": name,
                       "copy_psnr": psnr(copy, gt)}
                for key in encoders:
                    v = views[key, name]
                    row[key] = {"psnr": psnr(v.colour, gt), "ws_psnr": ws_psnr(v.colour, gt),
                                "covered": float((np.asarray(v.alpha) >= COVERED).mean())}
                rows.append(row)
                _log(f"{scene.name} {name}: {row['before']['psnr']:.2f} -> {row['after']['psnr']:.2f} dB")
                if (scene.name, name) == FIGURE:
                    figure = strip([(f"{name} (ground truth)", gt),
                                    (f"before: no layout prior, {row['before']['psnr']:.2f} dB", views["before", name].colour),
                                    (f"after: layout prior, {row['after']['psnr']:.2f} dB", views["after", name].colour)],
                                   out / "layout.png", panel_width=480,
                                   caption=f"{scene.name}, references {' + '.join(split.references)}, target {name}: "
                                           "plain compositing, direct ERP render 1024x512.")
    return {"machine": machine_info(), "rows": rows, "seconds": seconds,
            "figure": None if figure is None else str(figure)}


def markdown(res: dict, figure_link: str) -> str:
    """The README / docs table of :func:`run`'s result."""
    lines = [f"Machine: {machine_line(res['machine'])}.", "",
             "PSNR / WS-PSNR in dB at every target, plain compositing (direct ERP 1024x512 over black). "
             "before = the same encoder without the layout prior; copy = the nearest reference rotated "
             "into the target's orientation; f99 = fraction of target pixels with accumulated alpha >= 0.99.", "",
             "| scene | references | target | before | after | change | copy | f99 before / after |",
             "|---|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        b, a = r["before"], r["after"]
        lines.append(f"| {r['scene']} | {' + '.join(r['references'])} | {r['target']} | {b['psnr']:.2f} / {b['ws_psnr']:.2f} "
                     f"| {a['psnr']:.2f} / {a['ws_psnr']:.2f} | {a['psnr'] - b['psnr']:+.2f} | {r['copy_psnr']:.2f} "
                     f"| {b['covered']:.3f} / {a['covered']:.3f} |")
    lines.append("")
    for scene in dict.fromkeys(r["scene"] for r in res["rows"]):
        sel = [r for r in res["rows"] if r["scene"] == scene]
        mean = {k: float(np.mean([r[k]["psnr"] for r in sel])) for k in ("before", "after")}
        lines.append(f"- {scene}: mean PSNR of {len(sel)} targets {mean['before']:.2f} -> {mean['after']:.2f} dB "
                     f"(copy {float(np.mean([r['copy_psnr'] for r in sel])):.2f}).")
    for s in res["seconds"]:
        lines.append(f"- reconstruct {s['scene']} {' + '.join(s['references'])}: {s['before']:.2f} s before, "
                     f"{s['after']:.2f} s after.")
    if res["figure"]:
        lines += ["", f"![before / after the layout prior]({figure_link})"]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="omnisplat-bench layout", description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", nargs="+", type=Path, default=[DEV_DATA / "m3d_bedroom", DEV_DATA / "zind_room09"])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("docs/bench"))
    ap.add_argument("--readme", type=Path, default=None, help="README to update (marked block 'layout')")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    res = run(args.data, args.threads, args.out)
    write_json(args.out / "layout.json", res)
    (args.out / "layout.md").write_text("# Layout prior, before / after (bench layout)\n\n"
                                        + markdown(res, "layout.png") + "\n")
    if args.readme is not None:
        start, end = readme_markers("layout")
        block = "\n".join([start, "", markdown(res, "docs/bench/layout.png"), "", end])
        if not update_readme(args.readme, block, "layout"):
            _log(f"{args.readme} has no layout markers; not updated")
    print(markdown(res, "layout.png"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
