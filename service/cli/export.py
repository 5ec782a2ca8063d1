"""``omnisplat export``: build an ONNX model (needs the ``export`` extra, i.e. torch).

The user-facing options only (input size, preset, plane count, feature downscale); the encoder's
ablation switches stay in :func:`export.onnx_export.export_model` for the benchmarks.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from .common import CliError, check_output, forward_import

HINT = "the export extra: pip install -e '.[export]' (torch)"


def load_export_model():
    """:func:`export.onnx_export.export_model` (imports torch)."""
    from export.onnx_export import export_model

    return export_model


def cmd_export(args: argparse.Namespace) -> int:
    check_output(args.out, "out", (".onnx",), "an ONNX model")
    if args.downscale is not None and args.downscale < 1:
        raise CliError(f"--downscale: must be 1 or more, got {args.downscale}")
    export_model = forward_import(load_export_model, HINT)
    import onnx

    from ..model_files import build_whole

    try:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        build_whole(args.out, export_model, height=args.height, width=2 * args.height, num_planes=args.num_planes,
                    preset=args.preset, downscale=args.downscale)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    except OSError as exc:
        raise CliError(f"cannot write {args.out}: {exc.strerror or exc}") from None
    path = args.out
    meta = {p.key: p.value for p in onnx.load(str(path), load_external_data=False).metadata_props}
    print(json.dumps({"path": str(path), "bytes": path.stat().st_size,
                      **{k: meta[k] for k in ("name", "num_planes", "grids", "num_gaussians")}}))
    return 0


def add_parser(sub) -> None:
    x = sub.add_parser("export", help="build an ONNX model (needs torch: the export extra)",
                       description="Build the encoder as an ONNX model for one input size.")
    x.add_argument("out", type=Path, help="output .onnx path")
    x.add_argument("--height", type=int, default=512, help="ERP input height (width = 2 x height)")
    x.add_argument("--preset", default="quality", help="'fast' or 'quality' (default): plane count and feature size")
    x.add_argument("--num-planes", type=int, default=None, help="depth planes (default: the preset's)")
    x.add_argument("--downscale", type=int, default=None, help="feature grid = Gaussian grid / downscale")
    x.set_defaults(func=cmd_export)
