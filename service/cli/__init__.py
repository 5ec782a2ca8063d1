"""The ``omnisplat`` command line (one module per command group).

    omnisplat serve                       # HTTP API on 127.0.0.1:8000 (builds the model first if missing)
    omnisplat reconstruct SCENE_DIR -o scene.ply
    omnisplat reconstruct a.jpg b.jpg --poses poses.json -o scene.ply
    omnisplat render scene.ply --c2w 1,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1 -o view.png
    omnisplat export model.onnx           # build an ONNX model (needs the `export` extra, i.e. torch)

Heavy modules (onnxruntime, the renderer, torch for `export`) are imported only by the
sub-command that needs them, so `omnisplat --help` is instant. Benchmarks have their own
entry point, ``omnisplat-bench`` (``python -m bench``), in the source tree.
"""

from __future__ import annotations

import argparse
import logging
import sys

from . import edit, export, reconstruct, refine, render, serve
from .common import CliError

__all__ = ["CliError", "build_parser", "main"]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="omnisplat",
        description="Two 360-degree panoramas (equirectangular, width = 2 x height) and their camera poses "
                    "-> 3D Gaussians in one forward pass of an ONNX model on the CPU; render any view.",
        epilog="Poses are camera-to-world 4x4 (or 3x4) matrices, OpenCV axes: x right, y down, z forward; "
               "'opengl' (x right, y up, z backward) is accepted where a convention can be given. "
               "Run 'omnisplat COMMAND --help' for a command's options.",
    )
    sub = p.add_subparsers(dest="command", metavar="COMMAND", required=True)
    serve.add_parser(sub)
    reconstruct.add_parser(sub)
    render.add_parser(sub)
    export.add_parser(sub)
    refine.add_parser(sub)
    edit.add_parsers(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        args = build_parser().parse_args(argv)
        return int(args.func(args) or 0)
    except CliError as exc:
        print(f"omnisplat: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
