"""Render speed benchmark: ``python -m bench.render [--json] [--quick]``.

Builds pixel-aligned Gaussians from the m3d_bedroom reference panoramas and
their GT range maps, through the Yin and Yang grids (h x 3h per grid and per
reference; h = 256 gives 4 * 256 * 768 = 786,432 Gaussians, minus pixels
without depth), renders the target pose as a 512 x 1024 ERP through
Yin-Yang and directly, and reports median wall seconds, peak RSS, and the
scaling with the number of Gaussians and with the output width. Without the
data set it falls back to a synthetic room of the same structure.

Timings are wall-clock on whatever else the machine is doing; say so when
reporting them.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

import numpy as np

from bench import DEV_DATA
from rasterizer.depth_gaussians import gaussians_from_depth
from rasterizer.gaussians import Gaussians
from rasterizer.render import render
from rasterizer.scene_folder import load_scene
from rasterizer.yin_yang import erp_to_yin_yang, resize_erp

DEFAULT_SCENE = DEV_DATA / "m3d_bedroom"


def _synthetic_refs(height: int):
    """Two panoramas of a 4 x 3 x 2.5 m box room (range maps exact), for when no data is present."""
    from rasterizer import geometry as geo

    refs = []
    for z in (-0.5, 0.5):
        d = geo.grid_directions("erp", 2 * height, 4 * height)
        c = np.array([0.3, 0.2, z])
        half = np.array([2.0, 1.25, 1.5])
        with np.errstate(divide="ignore"):
            t = np.min(np.where(d != 0, (np.sign(d) * half - c) / d, np.inf), axis=-1)
        img = 0.5 + 0.4 * np.sin(7 * d + np.array([0, 1, 2]))
        c2w = np.eye(4)
        c2w[:3, 3] = c
        refs.append((img.astype(np.float32), t.astype(np.float32), c2w))
    target = np.eye(4)
    return refs, target


def build_benchmark_gaussians(scene_dir: str | Path | None = DEFAULT_SCENE, height: int = 256,
                              scale_factor: float | None = None):
    """(Gaussians, target c2w, source name): Yin+Yang pixel-aligned Gaussians of both references."""
    kw = {} if scale_factor is None else {"scale_factor": scale_factor}
    if scene_dir is not None and (Path(scene_dir) / "scene.json").exists():
        scene = load_scene(scene_dir)
        split = scene.splits[0]
        refs = []
        for name in split.references:
            f = scene.frames[name]
            refs.append((f.image(), f.depth(), f.c2w))
        target = scene.frames[split.targets[0]].c2w
        source = scene.name
    else:
        refs, target = _synthetic_refs(height)
        source = "synthetic"
    parts = []
    for img, depth, c2w in refs:
        if img.shape[0] != 2 * height:
            img = resize_erp(img, 2 * height, 4 * height)
        yi, ya = erp_to_yin_yang(img, height=height)
        di, da = erp_to_yin_yang(depth, height=height, nearest=True)
        parts += [gaussians_from_depth(yi, di, c2w, "yin", **kw), gaussians_from_depth(ya, da, c2w, "yang", **kw)]
    return Gaussians.concatenate(parts), target, source


def _median_time(fn, runs: int) -> float:
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_render_benchmark(scene_dir: str | Path | None = DEFAULT_SCENE, *, width: int = 1024, runs: int = 5,
                         sweep: bool = True, sweep_runs: int = 2, quick: bool = False) -> dict:
    """Run the benchmark; returns a JSON-able dict (see the module docstring).

    Keys: yinyang_erp_median_s, direct_erp_median_s, gaussians, width,
    height, peak_rss_mb, source, runs, scaling_gaussians (list of
    {gaussians, yinyang_s, direct_s}), scaling_width (list of {width,
    yinyang_s, direct_s}).
    """
    if quick:
        width, runs, sweep_runs = min(width, 256), min(runs, 3), 1
    g, target, source = build_benchmark_gaussians(scene_dir, height=width // 4)
    render(g, target, projection="erp", width=width)  # warm the grid caches
    result = {
        "source": source,
        "gaussians": len(g),
        "width": width,
        "height": width // 2,
        "runs": runs,
        "yinyang_erp_median_s": _median_time(lambda: render(g, target, projection="erp", width=width), runs),
        "direct_erp_median_s": _median_time(
            lambda: render(g, target, projection="erp", width=width, method="direct"), runs),
    }
    if sweep:
        rng = np.random.default_rng(0)
        counts = [10_000, 100_000, 300_000, len(g)] if not quick else [1_000, len(g)]
        big = g
        if not quick and len(g) < 1_000_000:
            # 1e6: add a jittered copy of part of the set
            extra = g.subset(rng.choice(len(g), 1_000_000 - len(g), replace=False))
            extra = extra.with_(means=extra.means + rng.normal(scale=0.01, size=extra.means.shape))
            big = Gaussians.concatenate([g, extra])
            counts.append(len(big))
        scaling = []
        for n in counts:
            sub = big.subset(rng.choice(len(big), n, replace=False)) if n < len(big) else big
            scaling.append({
                "gaussians": n,
                "yinyang_s": _median_time(lambda: render(sub, target, projection="erp", width=width), sweep_runs),
                "direct_s": _median_time(
                    lambda: render(sub, target, projection="erp", width=width, method="direct"), sweep_runs),
            })
        result["scaling_gaussians"] = scaling
        widths = [256, 512, 1024, 2048] if not quick else [128, 256]
        result["scaling_width"] = [{
            "width": w,
            "yinyang_s": _median_time(lambda: render(g, target, projection="erp", width=w), sweep_runs),
            "direct_s": _median_time(lambda: render(g, target, projection="erp", width=w, method="direct"),
                                     sweep_runs),
        } for w in widths]
    result["peak_rss_mb"] = _peak_rss_mb()
    return result


def main(argv: list[str] | None = None) -> int:
    """CLI: print the benchmark as one JSON object (--json) or a short table."""
    ap = argparse.ArgumentParser(prog="omnisplat-bench render", description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--scene", default=str(DEFAULT_SCENE), help="scene folder with depth (default m3d_bedroom)")
    ap.add_argument("--width", type=int, default=1024)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--no-sweep", action="store_true", help="skip the scaling sweeps")
    ap.add_argument("--quick", action="store_true", help="tiny sizes (smoke test)")
    args = ap.parse_args(argv)
    res = run_render_benchmark(args.scene, width=args.width, runs=args.runs, sweep=not args.no_sweep,
                               quick=args.quick)
    if args.json:
        print(json.dumps(res))
    else:
        print(f"{res['gaussians']} Gaussians -> {res['height']}x{res['width']} ERP ({res['source']}): "
              f"yinyang {res['yinyang_erp_median_s']:.3f} s, direct {res['direct_erp_median_s']:.3f} s, "
              f"peak RSS {res['peak_rss_mb']:.0f} MB")
        for row in res.get("scaling_gaussians", []):
            print(f"  N={row['gaussians']:>8}: yinyang {row['yinyang_s']:.3f} s  direct {row['direct_s']:.3f} s")
        for row in res.get("scaling_width", []):
            print(f"  W={row['width']:>5}: yinyang {row['yinyang_s']:.3f} s  direct {row['direct_s']:.3f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
