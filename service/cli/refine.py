"""``omnisplat refine``: a PLY's colours refined on its two reference panoramas (the paper's +opt)."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from .common import CliError, as_flags, check_output, read_gaussians, write_output
from .reconstruct import load_pair


def cmd_refine(args: argparse.Namespace) -> int:
    """Colours of a PLY refined on its two references (L1 fit, cross-view guard); JSON summary to stdout."""
    from pydantic import ValidationError

    from rasterizer.refine import RefineOptions, reference_views, refine
    from rasterizer.splat import RenderLimitError

    from ..jobs import RefineRequest
    from ..options import describe_error

    given = {"iterations": args.iterations, "height": args.height, "sh_degree": args.sh_degree,
             "colour_reg": args.colour_reg, "holdout": args.holdout, "patience": args.patience}
    params = {**{k: v for k, v in given.items() if v is not None}, "cross_check": not args.no_cross_check}
    try:  # the API's bounds and defaults (POST /v1/scenes/{id}/refine): a NaN or a huge grid fails here, not in numpy
        req = RefineRequest.model_validate(params)
    except ValidationError as exc:
        raise CliError(as_flags(describe_error(exc, prefix="refine"), params, prefix="refine.")) from None
    check_output(args.out, "--out", (".ply", ".spz"), "a Gaussian PLY or SPZ", [args.ply, *args.inputs, args.poses])
    g = read_gaussians(args.ply)
    erp_a, erp_b, c2w_a, c2w_b, desc = load_pair(args)
    if c2w_a is None:
        raise CliError("refine needs the references' poses: give --poses FILE.json with two images, or a scene folder")
    t0 = time.perf_counter()
    opts = RefineOptions(iterations=req.iterations, sh_degree=req.sh_degree, colour_reg=req.colour_reg,
                         patience=req.patience, cross_check=req.cross_check)
    try:  # the footprints of the 2 x 2 Yin/Yang grids (h x 3h each) scale with --height squared
        views = reference_views(g, [erp_a, erp_b], [c2w_a, c2w_b], height=req.height, holdout=req.holdout)
        t_fp = time.perf_counter() - t0
        res = refine(g, views, opts)
    except RenderLimitError as exc:  # the API's job fails with render_too_large
        raise CliError(f"--height {req.height}: the reference views of these {len(g)} Gaussians are too large for "
                       f"the renderer ({exc}); give a smaller --height") from None
    write_output(args.out, res.gaussians)
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


def add_parser(sub) -> None:
    f = sub.add_parser("refine", help="refine a PLY's colours on its two reference views",
                       description="refine the colours of a PLY on its two "
                                   "reference panoramas (a scene folder, or two images + --poses), geometry fixed, "
                                   "behind the cross-view guard. A JSON summary goes to stdout.")
    f.add_argument("ply", type=Path, help="Gaussians to refine (3DGS PLY or SPZ, e.g. from 'omnisplat reconstruct')")
    f.add_argument("inputs", nargs="+", help="scene folder, or two ERP images")
    f.add_argument("--poses", help="JSON file {\"convention\": ..., \"c2w\": [A, B]} (with two images)")
    f.add_argument("--refs", help="scene folder: the two reference frame names, 'A,B'")
    f.add_argument("--split", type=int, help="scene folder: split whose references to use (default 0)")
    f.add_argument("--out", type=Path, required=True, help="refined PLY (or SPZ: a name ending in .spz)")
    # defaults (None here): the API's, service.jobs.RefineRequest
    f.add_argument("--iterations", type=int, help="conjugate-gradient steps (default 100)")
    f.add_argument("--height", type=int, help="Yin/Yang working height h (default 128)")
    f.add_argument("--sh-degree", type=int, choices=(0, 1), help="default 0")
    f.add_argument("--colour-reg", type=float, help="default 2.0")
    f.add_argument("--holdout", type=float, help="share of reference pixels held out for the early stop (default 0.1)")
    f.add_argument("--patience", type=int, help="steps without held-out gain before stopping (default 5; needs a "
                                                 "holdout)")
    f.add_argument("--no-cross-check", action="store_true",
                   help="skip the cross-view guard (fit each reference alone, score the other; reject if worse)")
    f.set_defaults(func=cmd_refine)
