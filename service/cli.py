"""The ``omnisplat`` command line.

    omnisplat serve                       # HTTP API on 127.0.0.1:8000 (builds the model first if missing)
    omnisplat reconstruct SCENE_DIR -o scene.ply
    omnisplat reconstruct a.jpg b.jpg --poses poses.json -o scene.ply
    omnisplat render scene.ply --c2w 1,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1 -o view.png
    omnisplat export --help               # build an ONNX model (needs the `export` extra, i.e. torch)
    omnisplat bench render --json         # renderer timings; `bench quality`, `bench stability`

Heavy modules (onnxruntime, the renderer, torch for `export`) are imported only by the
sub-command that needs them, so `omnisplat --help` is instant.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path


def _main_of_export():
    from export.onnx_export import main
    return main


# Loaders of the bench mains: the CLI is the only (lazy) door from service/ to bench/.
def _bench_render():
    from bench.render import main
    return main


def _bench_quality():
    from bench.quality import main
    return main


def _bench_stability():
    from bench.stability import main
    return main


def _bench_refine():
    from bench.refine import main
    return main


def _bench_compaction():
    from bench.compaction import main
    return main


def _bench_coverage():
    from bench.coverage import main
    return main


def _bench_layout():
    from bench.layout import main
    return main


def _bench_depth():
    from bench.depth import main
    return main


def _bench_service():
    from bench.service import main
    return main


def _bench_edit():
    from bench.edit import main
    return main


def _bench_reliability():
    from bench.reliability import main
    return main


def _bench_poses():
    from bench.poses import main
    return main


#: Sub-commands handled by another module's ``main(argv)``: name -> (loader, what to install if absent).
FORWARDED = {
    "export": (_main_of_export, "the export extra: pip install -e '.[export]' (torch)"),
}
#: ``omnisplat bench NAME``: name -> (loader, what it measures). bench/ ships with the source, not the image.
BENCH = {
    "render": (_bench_render, "renderer timings (error against run time of the rasterizer)"),
    "quality": (_bench_quality, "reconstruction quality against run time on scene folders"),
    "stability": (_bench_stability, "stability of outputs under input perturbations"),
    "refine": (_bench_refine, "+opt refinement: quality against iterations and seconds"),
    "compaction": (_bench_compaction, "Gaussian count, PLY bytes, render time and PSNR per compaction step"),
    "coverage": (_bench_coverage, "accumulated alpha of the reconstructed Gaussians, quality plain vs V/A"),
    "layout": (_bench_layout, "the indoor layout prior before / after: PSNR per target, seconds, a picture"),
    "depth": (_bench_depth, "encoder depth error and ONNX run time on the dev scenes"),
    "service": (_bench_service, "HTTP service timings: ready, POST, render, peak memory"),
    "edit": (_bench_edit, "selection consistency across the references (mIoU vs baselines) and edit timings"),
    "reliability": (_bench_reliability, "the reliability audit against a live server: bad inputs, fuzzing, "
                                        "overload, idle clients, kill -9, full/read-only store"),
    "poses": (_bench_poses, "poses optional: estimated vs scene poses (errors) and PSNR with given/refined/estimated"),
}


class CliError(Exception):
    """A user-facing error: printed as one line, exit status 2."""


def _say(msg: str) -> None:
    print(f"[omnisplat] {msg}", file=sys.stderr, flush=True)


def _forward(load, hint: str, argv: list[str]) -> int:
    try:
        main = load()
    except ModuleNotFoundError as exc:
        if exc.name and exc.name.split(".")[0] in ("bench", "export", "service"):
            raise CliError(f"not available: module {exc.name} is not installed here ({hint})") from None
        raise CliError(f"not available: needs {exc.name!r}, which is not installed ({hint})") from None
    result = main(argv)
    return int(result or 0)


# -- select / edit (scenes in a service store) ----------------------------------------

def _triple(text: str, name: str) -> list[float]:
    try:
        vals = [float(x) for x in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) != 3:
        raise CliError(f"{name}: expected three comma-separated numbers, got {text!r}")
    return vals


def _point(text: str) -> list[float]:
    try:
        u, v = (float(x) for x in text.split(","))
    except ValueError:
        raise CliError(f"point: expected u,v with both in [0, 1], got {text!r}") from None
    return [u, v]


def _edit_store(args: argparse.Namespace):
    from .config import Settings
    from .store import SceneStore

    return SceneStore(args.store or Settings().store_dir)


def _edit_call(fn, *a):
    from .errors import ServiceError
    from .store import json_safe

    try:
        out = fn(*a)
    except ServiceError as exc:
        raise CliError(f"{exc.code}: {exc.message}") from None
    print(json.dumps(json_safe(out), indent=1))
    return 0


def cmd_select(args: argparse.Namespace) -> int:
    from . import edits

    if args.segment is not None:
        request = {"segment": args.segment}
    else:
        if not args.point:
            raise CliError("give --point u,v (one or more) or --segment N")
        request = {"view": args.view, "points": [_point(p) for p in args.point],
                   "negative": [_point(p) for p in args.negative or []]}
        bad = [p for p in request["points"] + request["negative"] if not all(0.0 <= c <= 1.0 for c in p)]
        if bad:
            raise CliError(f"points must lie in [0, 1]: {bad}")
    return _edit_call(edits.create_selection, _edit_store(args), args.scene, request)


def cmd_edit(args: argparse.Namespace) -> int:
    from . import edits

    request = {"selection": args.selection, "op": args.op}
    if args.op == "recolor":
        request["color"] = _triple(args.color or "", "--color")
        if not all(0.0 <= c <= 1.0 for c in request["color"]):
            raise CliError("--color: each channel in [0, 1]")
    if args.op == "translate":
        request["offset"] = _triple(args.offset or "", "--offset")
    return _edit_call(lambda *a: edits.create_edit(*a)[0], _edit_store(args), args.scene, request)


# -- serve ----------------------------------------------------------------------

def cmd_serve(args: argparse.Namespace) -> int:
    import uvicorn

    from .app import create_app
    from .config import Settings
    from .model_files import ModelUnavailable, ensure_model
    from .server import server_config

    overrides = {k: v for k, v in {
        "host": args.host, "port": args.port, "store_dir": args.store, "model_path": args.model,
        "models_dir": args.models_dir, "ort_threads": args.threads,
        "max_upload_bytes": None if args.max_upload_mb is None else int(args.max_upload_mb * 1024 * 1024),
        "max_requests": args.max_requests,
    }.items() if v is not None}
    try:
        settings = Settings(**overrides)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    try:
        ensure_model(settings.resolved_model_path, build_if_missing=not args.no_build)
    except ModelUnavailable as exc:
        raise CliError(str(exc)) from None
    _say(f"model {settings.resolved_model_path}; scenes in {settings.store_dir}")
    if args.ray:
        return _serve_ray(args, settings.model_copy(update={"model_path": settings.resolved_model_path}))
    _say(f"serving on http://{settings.host}:{settings.port} (docs at /docs; /readyz turns 200 after warm-up)")
    uvicorn.Server(server_config(create_app(settings), settings, log_level=args.log_level)).run()
    return 0


def _serve_ray(args: argparse.Namespace, settings) -> int:
    try:
        import ray.serve  # noqa: F401  (the [ray] extra)

        from .serve_ray import RayOptions, run
    except ModuleNotFoundError as exc:
        raise CliError(f"--ray needs {exc.name!r}: pip install 'omnisplat[ray]'") from None
    opts = RayOptions(min_replicas=args.min_replicas, max_replicas=max(args.min_replicas, args.max_replicas),
                      replica_cpus=args.replica_cpus)
    _say(f"Ray Serve: {opts.min_replicas}-{opts.max_replicas} replicas of {opts.replica_cpus:g} CPU "
         f"on http://{settings.host}:{settings.port}")
    return run(settings, opts, address=args.ray_address)


# -- reconstruct -------------------------------------------------------------------

def _load_pair(args: argparse.Namespace):
    """(erp_a, erp_b, c2w_a, c2w_b, description) from a scene folder or two images (+ poses JSON).

    Two images without ``--poses`` give ``c2w_a = c2w_b = None``: the poses are estimated.
    """
    from rasterizer.geometry import PoseError
    from rasterizer.scene_folder import load_image, load_scene

    from .inputs import parse_poses

    inputs = [Path(p) for p in args.inputs]
    if len(inputs) == 1:
        if not (inputs[0] / "scene.json").is_file():
            raise CliError(f"{inputs[0]} is not a scene folder (no scene.json); pass a folder or two images")
        try:
            scene = load_scene(inputs[0])
        except (PoseError, ValueError, KeyError) as exc:
            raise CliError(f"{inputs[0]}: {exc}") from None
        if args.refs:
            refs = tuple(args.refs.split(","))
        elif scene.splits:
            refs = scene.splits[min(args.split, len(scene.splits) - 1)].references
        else:
            refs = tuple(list(scene.frames)[:2])
        if len(refs) != 2 or any(r not in scene.frames for r in refs):
            raise CliError(f"references {refs} are not two frames of {inputs[0]} (frames: {list(scene.frames)})")
        fa, fb = scene.frames[refs[0]], scene.frames[refs[1]]
        return fa.image(), fb.image(), fa.c2w, fb.c2w, {"scene": str(inputs[0]), "references": list(refs)}
    if len(inputs) == 2:
        from .errors import ServiceError

        try:
            poses = parse_poses(Path(args.poses).read_bytes()) if args.poses is not None else None
        except ServiceError as exc:
            raise CliError(f"{args.poses}: {exc.message}") from None
        except OSError as exc:
            raise CliError(f"cannot read {args.poses}: {exc}") from None
        try:
            a, b = load_image(inputs[0]), load_image(inputs[1])
        except OSError as exc:
            raise CliError(f"cannot read image: {exc}") from None
        if poses is None:
            return a, b, None, None, {"images": [str(p) for p in inputs]}
        return a, b, poses.c2w_a, poses.c2w_b, {"images": [str(p) for p in inputs]}
    raise CliError("reconstruct takes a scene folder, or two images (with --poses, or poses are estimated)")


def _pipeline_options(args: argparse.Namespace):
    """The API's options object, from reconstruct's flags (validated here, before any work)."""
    from .pipeline import PipelineOptions

    compaction: dict | bool = {}
    if args.no_compaction:
        compaction = False
    else:
        for flag, key in (("resolve_overlap", "resolve_overlap"), ("max_gaussians", "max_count"),
                          ("max_bytes", "max_bytes"), ("min_opacity", "min_opacity")):
            if getattr(args, flag) is not None:
                compaction[key] = getattr(args, flag)
        if args.merge_duplicates:
            compaction["merge_duplicates"] = True
        if args.no_merge_smooth:
            compaction["merge_smooth"] = False
        elif args.smooth_levels is not None:
            compaction["smooth_levels"] = args.smooth_levels
    try:
        return PipelineOptions.from_dict({"near": args.near, "far": args.far, "compaction": compaction,
                                          "adaptive_range": args.adaptive_range, "sh_degree": args.sh_degree,
                                          "rig_cap_deg": args.rig_cap_deg})
    except ValueError as exc:
        raise CliError(str(exc)) from None


def cmd_reconstruct(args: argparse.Namespace) -> int:
    from rasterizer.ply import write_ply

    from .config import Settings
    from .model_files import ModelUnavailable, ensure_model
    from .pipeline import build_scene

    erp_a, erp_b, c2w_a, c2w_b, source = _load_pair(args)  # bad inputs fail before any model build
    options = _pipeline_options(args)
    from .errors import ServiceError
    from .inputs import Poses
    from .poses import PoseOptions, poses_for_scene

    try:
        pose_options = PoseOptions.pop_from({"camera_height": args.camera_height, "baseline": args.baseline,
                                             "refine_poses": args.refine_poses})
    except ServiceError as exc:
        raise CliError(exc.message) from None
    for name, img in (("image A", erp_a), ("image B", erp_b)):
        if img.shape[1] != 2 * img.shape[0]:
            raise CliError(f"{name} is {img.shape[1]}x{img.shape[0]}; an ERP panorama must be exactly 2:1")
    t0 = time.perf_counter()
    given = None if c2w_a is None else Poses("opencv", c2w_a, c2w_b)
    if given is None:
        _say("estimating the relative pose from the images")
    try:
        c2w_a, c2w_b, poses_json = poses_for_scene(erp_a, erp_b, given, pose_options)
    except ServiceError as exc:
        raise CliError(exc.message) from None
    poses_s = time.perf_counter() - t0
    settings = Settings(**({"model_path": args.model} if args.model else {}))
    try:
        model = ensure_model(settings.resolved_model_path, build_if_missing=not args.no_build)
    except ModelUnavailable as exc:
        raise CliError(str(exc)) from None
    _say(f"loading model {model}")
    from .encoder import EncoderInputError, OnnxEncoder

    t0 = time.perf_counter()
    encoder = OnnxEncoder(model, threads=args.threads)
    load_s = time.perf_counter() - t0
    _say(f"reconstructing {erp_a.shape[1]}x{erp_a.shape[0]} + {erp_b.shape[1]}x{erp_b.shape[0]} panoramas")
    t0 = time.perf_counter()
    try:
        rec = build_scene(encoder, erp_a, erp_b, c2w_a, c2w_b, options)
    except EncoderInputError as exc:
        raise CliError(str(exc)) from None
    total = time.perf_counter() - t0
    out = Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_ply(out, rec.gaussians)
    from .store import json_safe

    summary = json_safe({
        "ply": str(out), "num_gaussians": len(rec.gaussians), "source": source,
        "model": {k: encoder.metadata.get(k) for k in ("name", "version", "sha256")},
        "timings": {**rec.timings, "poses": poses_s, "model_load": load_s, "total": total}, "info": rec.info,
        "poses": poses_json,
    })
    text = json.dumps(summary, indent=2)
    if args.json:
        Path(args.json).write_text(text + "\n")
    print(text)
    _say(f"wrote {len(rec.gaussians)} Gaussians to {out} in {total:.2f} s")
    return 0


# -- render -------------------------------------------------------------------

def _pose_from_args(args: argparse.Namespace):
    from .errors import ServiceError
    from .inputs import parse_c2w_query

    if (args.c2w is None) == (args.pose is None):
        raise CliError("give exactly one of --c2w '16 numbers' or --pose FILE.json")
    try:
        if args.c2w is not None:
            return parse_c2w_query(args.c2w)
        from rasterizer.geometry import PoseError, as_c2w

        obj = json.loads(Path(args.pose).read_text())
        matrix = obj["c2w"] if isinstance(obj, dict) else obj
        convention = obj.get("convention", "opencv") if isinstance(obj, dict) else "opencv"
        try:
            return as_c2w(matrix, convention)
        except PoseError as exc:
            raise CliError(f"{args.pose}: {exc}") from None
    except ServiceError as exc:
        raise CliError(exc.message) from None
    except (OSError, ValueError, KeyError) as exc:
        raise CliError(f"cannot read pose: {exc}") from None


def _rig_layer_from_args(args: argparse.Namespace):
    """The capture rig of ``--rig IMAGE_A IMAGE_B`` (rasterizer.rig), or None without the flag."""
    if not args.rig:
        return None
    from rasterizer.rig import NoRigError, require_rig_layer
    from rasterizer.scene_folder import load_image

    try:
        images = [load_image(Path(p)) for p in args.rig]
    except OSError as exc:
        raise CliError(f"--rig: cannot read image: {exc}") from None
    if images[0].shape != images[1].shape or images[0].shape[1] != 2 * images[0].shape[0]:
        raise CliError(f"--rig: need two 2:1 panoramas of one size, got {images[0].shape[1]}x{images[0].shape[0]} "
                       f"and {images[1].shape[1]}x{images[1].shape[0]}")
    try:
        return require_rig_layer(*images)
    except NoRigError as exc:
        raise CliError(f"--rig: {exc}; render without --rig") from None


def cmd_render(args: argparse.Namespace) -> int:
    c2w = _pose_from_args(args)
    from rasterizer.ply import read_ply
    from rasterizer.render import render, to_uint8

    from .images import encode

    try:
        gaussians = read_ply(args.ply)
    except (OSError, ValueError) as exc:
        raise CliError(f"cannot read {args.ply}: {exc}") from None
    fmt = "jpeg" if Path(args.output).suffix.lower() in (".jpg", ".jpeg") else "png"
    # as the API renders: plain compositing unless --compositing va
    kwargs = {"projection": args.projection, "width": args.width, "normalize": args.compositing == "va"}
    if args.projection == "perspective":
        kwargs.update(height=args.height, fov_deg=args.fov_deg)
    layer = _rig_layer_from_args(args)
    _say(f"rendering {len(gaussians)} Gaussians, {args.projection} {args.width} px wide")
    t0 = time.perf_counter()
    out = render(gaussians, c2w, **kwargs)
    colour = out.colour
    if layer is not None:
        from rasterizer.camera import camera_directions
        from rasterizer.rig import overlay_rig

        h, w = colour.shape[:2]
        colour = overlay_rig(colour, camera_directions(args.projection, h, w, args.fov_deg), layer)
    data = encode(to_uint8(colour), fmt)
    Path(args.output).write_bytes(data)
    _say(f"wrote {args.output} in {time.perf_counter() - t0:.2f} s")
    return 0


# -- refine ---------------------------------------------------------------------

def cmd_refine(args: argparse.Namespace) -> int:
    """+opt: colours (and optionally opacities) of a PLY refined on its two references; JSON summary to stdout."""
    from rasterizer.ply import read_ply, write_ply
    from rasterizer.refine import RefineOptions, reference_views, refine

    if not 0 <= args.holdout < 1 or args.iterations < 0 or args.height < 8:
        raise CliError("need 0 <= --holdout < 1, --iterations >= 0, --height >= 8")
    try:
        g = read_ply(args.ply)
    except (OSError, ValueError) as exc:
        raise CliError(f"cannot read {args.ply}: {exc}") from None
    erp_a, erp_b, c2w_a, c2w_b, desc = _load_pair(args)
    t0 = time.perf_counter()
    views = reference_views(g, [erp_a, erp_b], [c2w_a, c2w_b], height=args.height, holdout=args.holdout)
    t_fp = time.perf_counter() - t0
    opts = RefineOptions(iterations=args.iterations, sh_degree=args.sh_degree, colour_reg=args.colour_reg,
                         optimise_opacity=args.optimise_opacity, opacity_lr=args.opacity_lr, patience=args.patience,
                         cross_check=not args.no_cross_check, **({} if args.loss is None else {"loss": args.loss}))
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


# -- parser ---------------------------------------------------------------------

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

    s = sub.add_parser("serve", help="run the HTTP API (builds the default model first if it is missing)",
                       description="Run the HTTP API. Settings come from OMNISPLAT_* environment variables "
                                   "(see service/config.py); these flags override them.")
    s.add_argument("--host", help="interface to bind (default 127.0.0.1; 0.0.0.0 in containers)")
    s.add_argument("--port", type=int, help="port (default 8000)")
    s.add_argument("--store", type=Path, help="scene store folder (default ~/.omnisplat/scenes)")
    s.add_argument("--model", type=Path, help="ONNX model file (default <models-dir>/omnisplat-default-<exporter hash>.onnx)")
    s.add_argument("--models-dir", type=Path, help="where the default model is built (default ~/.omnisplat/models)")
    s.add_argument("--no-build", action="store_true", help="fail instead of building a missing model")
    s.add_argument("--threads", type=int, help="onnxruntime threads (default 2)")
    s.add_argument("--max-upload-mb", type=float, help="request body limit in MiB (default 100)")
    s.add_argument("--max-requests", type=int,
                   help="requests in progress before 503 + Retry-After (default 256; health exempt)")
    s.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"])
    ray = s.add_argument_group("Ray Serve (pip install 'omnisplat[ray]'; see README 'Scale-out on Ray Serve')")
    ray.add_argument("--ray", action="store_true", help="serve on Ray Serve replicas instead of one uvicorn process")
    ray.add_argument("--ray-address", help="join this Ray cluster (e.g. 'auto'); default: start a local one")
    ray.add_argument("--min-replicas", type=int, default=1, help="autoscaling lower bound (default 1)")
    ray.add_argument("--max-replicas", type=int, default=2, help="autoscaling upper bound (default 2)")
    ray.add_argument("--replica-cpus", type=float, default=1.0,
                     help="CPUs per replica, also its onnxruntime threads (default 1)")
    s.set_defaults(func=cmd_serve)

    r = sub.add_parser("reconstruct", help="scene folder or two images + poses -> Gaussian PLY and a JSON summary",
                       description="Reconstruct 3D Gaussians from two ERP panoramas, without the HTTP service.")
    r.add_argument("inputs", nargs="+", help="a scene folder (scene.json), or two image files")
    r.add_argument("--poses", help='with two images: JSON file {"convention": "opencv"|"opengl", "c2w": [A, B]}; '
                                   "without it the poses are estimated from the images (world = camera A)")
    r.add_argument("--camera-height", type=float, help="estimated poses: metres of camera A above the floor (sets the scale)")
    r.add_argument("--baseline", type=float, help="estimated poses: metres between the cameras (sets the scale)")
    r.add_argument("--refine-poses", action="store_true", help="refine given poses against the images (upright model)")
    r.add_argument("--split", type=int, default=0, help="scene folder: which split's references (default 0)")
    r.add_argument("--refs", help="scene folder: two frame names, e.g. 00,02 (overrides --split)")
    r.add_argument("-o", "--output", default="scene.ply", help="output PLY (default scene.ply)")
    r.add_argument("--json", help="also write the summary JSON to this file")
    r.add_argument("--model", type=Path, help="ONNX model (default: the one `serve` uses, built if missing)")
    r.add_argument("--no-build", action="store_true", help="fail instead of building a missing model")
    r.add_argument("--near", type=float, help="nearest depth in metres (default from the baseline)")
    r.add_argument("--far", type=float, help="farthest depth in metres")
    r.add_argument("--threads", type=int, default=2, help="onnxruntime threads (default 2)")
    c = r.add_argument_group("leave out what the scene does not need (default: min opacity and the smooth merge)")
    c.add_argument("--no-compaction", action="store_true", help="keep every pixel-aligned Gaussian")
    c.add_argument("--resolve-overlap", choices=["split", "yin", "off"],
                   help="Yin/Yang overlap: keep each direction once (split, yin) or keep all (off, default)")
    c.add_argument("--merge-duplicates", action="store_true",
                   help="keep one of the two references' copies of a surface point (default: keep both)")
    c.add_argument("--no-merge-smooth", action="store_true",
                   help="keep flat, evenly coloured regions at one Gaussian per pixel (default: merge 2x2 blocks)")
    c.add_argument("--smooth-levels", type=int, help="largest merged block is 2^N pixels a side (default 1: 2x2)")
    c.add_argument("--min-opacity", type=float, help="drop Gaussians below this opacity (default 1/255)")
    c.add_argument("--max-gaussians", type=int, help="cap the count (drops the least visible first)")
    c.add_argument("--max-bytes", type=int, help="cap the PLY size in bytes")
    c.add_argument("--adaptive-range", action="store_true",
                   help="choose near/far from a coarse pass (slower: two encoder runs)")
    c.add_argument("--sh-degree", type=int,
                   help="1 (default): view-dependent colour, each reference sees its own image; "
                        "0: one colour per Gaussian (smaller PLY)")
    c.add_argument("--rig-cap-deg", type=float,
                   help="degrees around each camera's nadir where a tripod capture shows the rig: those pixels "
                        "take the other panorama's colour (0: off; default: 20 where both panoramas show a rig at "
                        "their nadir, else 0)")
    r.set_defaults(func=cmd_reconstruct)

    v = sub.add_parser("render", help="Gaussian PLY + camera pose -> image",
                       description="Render a view of a Gaussian PLY with the CPU rasterizer.")
    v.add_argument("ply", help="3DGS PLY file")
    v.add_argument("--c2w", help="camera-to-world as 16 (or 12) comma-separated numbers, row-major, OpenCV "
                   "(write --c2w=-0.8,... when the first number is negative)")
    v.add_argument("--pose", help='JSON file with a 4x4 matrix or {"convention": ..., "c2w": M}')
    v.add_argument("--projection", default="erp", choices=["erp", "perspective", "yin", "yang"])
    v.add_argument("--width", type=int, default=1024, help="image width (ERP height = width/2)")
    v.add_argument("--height", type=int, help="perspective only (default = width)")
    v.add_argument("--fov-deg", type=float, default=90.0, help="perspective only: horizontal field of view")
    v.add_argument("--compositing", default="plain", choices=["plain", "va"],
                   help="plain (default): front-to-back over black, what 3DGS viewers show of the PLY; "
                        "va: colour / accumulated alpha, the OmniSplat paper's normalisation")
    v.add_argument("--rig", nargs=2, metavar=("IMAGE_A", "IMAGE_B"),
                   help="the two reference panoramas: composite the capture rig (tripod) both show at their "
                        "nadir over the render, at its camera's nadir, as a capture from that pose would show it")
    v.add_argument("-o", "--output", default="view.png", help="output .png or .jpg (default view.png)")
    v.set_defaults(func=cmd_render)

    sub.add_parser("export", help="build an ONNX model (needs torch: the export extra); see 'export --help'",
                   add_help=False)
    f = sub.add_parser("refine", help="refine a PLY's colours/opacities on its two reference views (+opt)",
                       description="+opt: refine the colours (and optionally opacities) of a PLY on its two "
                                   "reference panoramas (a scene folder, or two images + --poses), geometry fixed, "
                                   "behind the cross-view guard. A JSON summary goes to stdout.")
    f.add_argument("ply", type=Path, help="Gaussians to refine (3DGS PLY, e.g. from 'omnisplat reconstruct')")
    f.add_argument("inputs", nargs="+", help="scene folder, or two ERP images")
    f.add_argument("--poses", help="JSON file {\"convention\": ..., \"c2w\": [A, B]} (with two images)")
    f.add_argument("--refs", help="scene folder: the two reference frame names, 'A,B'")
    f.add_argument("--split", type=int, default=0, help="scene folder: split whose references to use")
    f.add_argument("--out", type=Path, required=True, help="refined PLY")
    f.add_argument("--iterations", type=int, default=100)
    f.add_argument("--height", type=int, default=128, help="Yin/Yang working height h")
    f.add_argument("--sh-degree", type=int, default=0, choices=(0, 1))
    f.add_argument("--colour-reg", type=float, default=2.0)
    f.add_argument("--optimise-opacity", action="store_true")
    f.add_argument("--opacity-lr", type=float, default=0.01)
    f.add_argument("--holdout", type=float, default=0.1)
    f.add_argument("--patience", type=int, default=5)
    f.add_argument("--no-cross-check", action="store_true",
                   help="skip the cross-view guard (fit each reference alone, score the other; reject if worse)")
    f.add_argument("--loss", choices=("l2", "huber", "l1"), help="colour fit loss (default: RefineOptions.loss, l1)")
    f.set_defaults(func=cmd_refine)
    e = sub.add_parser("select", help="select an object (points on a reference, or a segment) of a stored scene")
    e.add_argument("scene", help="scene id in the store")
    e.add_argument("--store", type=Path, help="scene store folder (default ~/.omnisplat/scenes)")
    e.add_argument("--view", choices=["a", "b"], default="a")
    e.add_argument("--point", action="append", help="u,v in [0, 1] on that reference's ERP (repeatable)")
    e.add_argument("--negative", action="append", help="u,v of a negative point (repeatable)")
    e.add_argument("--segment", type=int, help="take a whole automatic segment instead")
    e.set_defaults(func=cmd_select)
    d = sub.add_parser("edit", help="remove / keep / recolor / translate a selection; the result is a new scene")
    d.add_argument("scene", help="scene id in the store")
    d.add_argument("--store", type=Path, help="scene store folder (default ~/.omnisplat/scenes)")
    d.add_argument("--selection", required=True, help="selection id from 'omnisplat select'")
    d.add_argument("--op", required=True, choices=["remove", "keep", "recolor", "translate"])
    d.add_argument("--color", help="recolor: r,g,b in [0, 1]")
    d.add_argument("--offset", help="translate: dx,dy,dz in world units")
    d.set_defaults(func=cmd_edit)
    b = sub.add_parser("bench", help="benchmarks: " + ", ".join(f"'bench {k}'" for k in BENCH),
                       description="Benchmarks; each forwards its options to its own parser.")
    b.add_argument("which", choices=list(BENCH), help="; ".join(f"{k}: {v[1]}" for k, v in BENCH.items()))
    return p


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        if argv and argv[0] in FORWARDED:
            load, hint = FORWARDED[argv[0]]
            return _forward(load, hint, argv[1:])
        if len(argv) >= 2 and argv[0] == "bench" and argv[1] in BENCH:
            return _forward(BENCH[argv[1]][0], f"bench {argv[1]} is provided by bench.{argv[1]}, in the source tree",
                            argv[2:])
        args = build_parser().parse_args(argv)
        return int(args.func(args) or 0)
    except CliError as exc:
        print(f"omnisplat: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
