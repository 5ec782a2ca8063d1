"""``omnisplat refine``: +opt on the command line (PLY + the two reference panoramas -> refined PLY).

    omnisplat refine scene.ply ../shared/data/m3d_bedroom --out refined.ply
    omnisplat refine scene.ply a.png b.png --poses poses.json --out refined.ply --iterations 100

The references are a scene folder (its first split, or ``--refs A,B``) or two ERP images +
``--poses`` JSON (same forms as ``omnisplat reconstruct``). Colour (and optionally opacity)
is refined on their Yin/Yang images, geometry fixed (:mod:`rasterizer.refine`), behind the
cross-view guard (unrefined colours come back when a fit on one reference makes the other
worse; ``--no-cross-check`` skips it); a JSON summary (losses, guard, best iteration,
seconds) goes to stdout.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="omnisplat refine", description=__doc__.splitlines()[0])
    p.add_argument("ply", type=Path, help="Gaussians to refine (3DGS PLY, e.g. from 'omnisplat reconstruct')")
    p.add_argument("inputs", nargs="+", help="scene folder, or two ERP images")
    p.add_argument("--poses", help="JSON file {\"convention\": ..., \"c2w\": [A, B]} (with two images)")
    p.add_argument("--refs", help="scene folder: the two reference frame names, 'A,B'")
    p.add_argument("--split", type=int, default=0, help="scene folder: split whose references to use")
    p.add_argument("--out", type=Path, required=True, help="refined PLY")
    p.add_argument("--iterations", type=int, default=100)
    p.add_argument("--height", type=int, default=128, help="Yin/Yang working height h")
    p.add_argument("--sh-degree", type=int, default=0, choices=(0, 1))
    p.add_argument("--colour-reg", type=float, default=2.0)
    p.add_argument("--optimise-opacity", action="store_true")
    p.add_argument("--opacity-lr", type=float, default=0.01)
    p.add_argument("--holdout", type=float, default=0.1)
    p.add_argument("--patience", type=int, default=5)
    p.add_argument("--no-cross-check", action="store_true",
                   help="skip the cross-view guard (fit each reference alone, score the other; reject if worse)")
    p.add_argument("--loss", default="l2", choices=("l2", "huber", "l1"), help="colour fit loss (l2 measured best)")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from rasterizer.ply import read_ply, write_ply
    from rasterizer.refine import RefineOptions, reference_views, refine

    from .cli import CliError, _load_pair

    try:
        if not 0 <= args.holdout < 1 or args.iterations < 0 or args.height < 8:
            raise CliError("need 0 <= --holdout < 1, --iterations >= 0, --height >= 8")
        try:
            g = read_ply(args.ply)
        except (OSError, ValueError) as exc:
            raise CliError(f"cannot read {args.ply}: {exc}") from None
        erp_a, erp_b, c2w_a, c2w_b, desc = _load_pair(args)
    except CliError as exc:
        print(f"[omnisplat] error: {exc}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    views = reference_views(g, [erp_a, erp_b], [c2w_a, c2w_b], height=args.height, holdout=args.holdout)
    t_fp = time.perf_counter() - t0
    opts = RefineOptions(iterations=args.iterations, sh_degree=args.sh_degree, colour_reg=args.colour_reg,
                         optimise_opacity=args.optimise_opacity, opacity_lr=args.opacity_lr, patience=args.patience,
                         cross_check=not args.no_cross_check, loss=args.loss)
    res = refine(g, views, opts)
    write_ply(args.out, res.gaussians)
    first = res.history[0]
    best = res.history[min(res.best_iteration, len(res.history) - 1)]
    print(json.dumps({"out": str(args.out), "inputs": desc, "num_gaussians": len(res.gaussians),
                      "best_iteration": res.best_iteration, "iterations_run": res.history[-1]["iteration"],
                      "held_loss_start": first["held_loss"], "held_loss_best": best["held_loss"],
                      "cross_check": None if res.cross is None else
                      {"accepted": res.cross["accepted"], "steps": res.cross["steps"], "scale": res.cross["scale"],
                       "mse_start": res.cross["total"][0][0], "mse_best": min(map(min, res.cross["total"])),
                       "seconds": res.cross["seconds"]},
                      "seconds": {"footprints": t_fp, "refine": res.seconds}}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
