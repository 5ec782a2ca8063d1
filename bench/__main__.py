"""``omnisplat-bench NAME [options]`` (or ``python -m bench NAME``): run one benchmark.

Each benchmark is a module of this package with its own ``main(argv)`` and parser
(``omnisplat-bench NAME --help``); :data:`COMMANDS` is the one list of them.
"""

from __future__ import annotations

import argparse
import importlib
import sys

#: name -> (module whose ``main(argv)`` runs it, what it measures).
COMMANDS: dict[str, tuple[str, str]] = {
    "render": ("bench.render", "renderer timings (error against run time of the rasterizer)"),
    "quality": ("bench.quality", "reconstruction quality against run time on scene folders"),
    "stability": ("bench.stability", "stability of outputs under input perturbations"),
    "refine": ("bench.refine", "refinement: quality against iterations and seconds"),
    "compaction": ("bench.compaction", "Gaussian count, PLY bytes, render time and PSNR per compaction step"),
    "detail": ("bench.detail", "PSNR, sharpness and GMSD at the references' own poses and at targets; count, PLY size, "
                               "POST/render seconds, peak RSS per input size"),
    "coverage": ("bench.coverage", "accumulated alpha of the reconstructed Gaussians, quality plain vs V/A"),
    "layout": ("bench.layout", "the indoor layout prior before / after: PSNR per target, seconds, a picture"),
    "depth": ("bench.depth", "encoder depth error and ONNX run time on the dev scenes"),
    "service": ("bench.service", "HTTP service timings: ready, POST, render, peak memory"),
    "edit": ("bench.edit", "selection consistency across the references (mIoU vs baselines) and edit timings"),
    "reliability": ("bench.reliability", "the reliability audit against a live server: bad inputs, fuzzing, "
                                         "overload, idle clients, kill -9, full/read-only store"),
    "store": ("bench.store", "disk per scene, the store budget under an edit flood, server RSS after POSTs and renders"),
    "poses": ("bench.poses", "poses optional: estimated vs scene poses (errors) and PSNR with given/refined/estimated"),
}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="omnisplat-bench", description="Benchmarks of omnisplat (in the source tree, "
                                "not the runtime image); each forwards its options to its own parser.")
    p.add_argument("command", metavar="NAME", choices=list(COMMANDS),
                   help="; ".join(f"{k}: {v[1]}" for k, v in COMMANDS.items()))
    return p


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] not in COMMANDS:
        build_parser().parse_args(argv[:1])  # --help (exit 0), or the usage error (exit 2)
        return 2
    module, _ = COMMANDS[argv[0]]
    try:
        run = importlib.import_module(module).main
    except ModuleNotFoundError as exc:
        if exc.name == module:
            raise
        print(f"omnisplat-bench: error: {argv[0]} needs {exc.name!r}, which is not installed "
              "(pip install -e '.[bench]')", file=sys.stderr)
        return 2
    return int(run(argv[1:]) or 0)


if __name__ == "__main__":
    sys.exit(main())
