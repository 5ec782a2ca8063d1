"""``omnisplat reconstruct``: two panoramas (a scene folder, or two images + poses) -> Gaussian PLY + summary."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from .common import (
    CliError,
    as_flags,
    check_output,
    cli_settings,
    load_encoder,
    model_file,
    read_panorama,
    say,
    write_output,
)

#: the layout of a scene folder's scene.json (rasterizer.scene_folder), as an error message shows it
SCENE_LAYOUT = ('{"convention": "opencv"|"opengl", "frames": [{"name": N, "image": FILE, "c2w": 4x4}, ...], '
                '"splits": [{"references": [N, N], "targets": [N, ...]}, ...]}')


def load_pair(args: argparse.Namespace, min_width: int | None = None):
    """(erp_a, erp_b, c2w_a, c2w_b, description) from a scene folder or two images (+ poses JSON); JPEGs wider
    than twice ``min_width`` are decoded at a reduced scale (:func:`.common.read_panorama`).

    Two images without ``--poses`` give ``c2w_a = c2w_b = None``: the poses are estimated. The description names
    the inputs and, with poses, the ``convention`` they were written in (the poses returned are OpenCV c2w).
    A flag the inputs do not use is refused, not dropped: ``--poses`` with a scene folder (its poses are in
    scene.json), ``--refs`` / ``--split`` with two images, and an empty ``--poses`` file (an empty API field
    means "estimate them"; a file named on the command line that holds nothing is a mistake).
    """
    from rasterizer.geometry import PoseError
    from rasterizer.scene_folder import load_scene

    from ..inputs import parse_poses, without_bom

    inputs = [Path(p) for p in args.inputs]
    refs, split = getattr(args, "refs", None), getattr(args, "split", None)
    if len(inputs) == 1 and getattr(args, "poses", None) is not None:
        raise CliError(f"--poses: {inputs[0]} is a scene folder, whose poses are its scene.json's; "
                       "give --poses with two images")
    if len(inputs) == 2 and (refs is not None or split is not None):
        raise CliError(f"{'--refs' if refs is not None else '--split'}: chooses the references of a scene folder; "
                       "with two images, they are the references")
    if len(inputs) == 1:
        if not (inputs[0] / "scene.json").is_file():
            raise CliError(f"{inputs[0]} is not a scene folder (no scene.json); pass a folder or two images")
        try:
            scene = load_scene(inputs[0])
        except (PoseError, ValueError) as exc:  # each names the scene.json (and the frame)
            raise CliError(str(exc)) from None
        except OSError as exc:
            raise CliError(f"cannot read {inputs[0] / 'scene.json'}: {exc.strerror or exc}") from None
        except (KeyError, TypeError, AttributeError) as exc:  # a JSON value of another shape than the layout's
            what = f"lacks the key {exc}" if isinstance(exc, KeyError) else f"holds a value of the wrong type ({exc})"
            raise CliError(f"{inputs[0] / 'scene.json'}: {what}; expected {SCENE_LAYOUT}") from None
        split = split or 0
        if split < 0 or (not refs and split and split >= len(scene.splits)):
            have = f"splits 0-{len(scene.splits) - 1}" if scene.splits else "no splits (its first two frames are used)"
            raise CliError(f"--split {split}: {inputs[0]} has {have}")
        if refs:
            refs = tuple(refs.split(","))
        elif scene.splits:
            refs = scene.splits[split].references
        else:
            refs = tuple(list(scene.frames)[:2])
        if len(refs) != 2 or any(r not in scene.frames for r in refs):
            raise CliError(f"references {refs} are not two frames of {inputs[0]} (frames: {list(scene.frames)})")
        fa, fb = scene.frames[refs[0]], scene.frames[refs[1]]
        return (read_panorama(fa.image_path, min_width), read_panorama(fb.image_path, min_width), fa.c2w, fb.c2w,
                {"scene": str(inputs[0]), "references": list(refs), "convention": scene.convention})
    if len(inputs) == 2:
        from ..errors import ServiceError

        try:
            text = Path(args.poses).read_bytes() if args.poses is not None else None
            if text is not None and not without_bom(text).strip():
                raise CliError(f"--poses {args.poses}: the file is empty; leave --poses out to estimate the poses")
            poses = parse_poses(text)
        except ServiceError as exc:
            raise CliError(f"{args.poses}: {exc.message}") from None
        except OSError as exc:
            raise CliError(f"cannot read {args.poses}: {exc}") from None
        a, b = read_panorama(inputs[0], min_width), read_panorama(inputs[1], min_width)
        if poses is None:
            return a, b, None, None, {"images": [str(p) for p in inputs]}
        return a, b, poses.c2w_a, poses.c2w_b, {"images": [str(p) for p in inputs], "convention": poses.convention}
    raise CliError("reconstruct takes a scene folder, or two images (with --poses, or poses are estimated)")


#: reconstruct's compaction flags (argparse dests) and the API's ``options.compaction`` keys they set
COMPACTION_FLAGS = (("max_gaussians", "max_count"), ("max_bytes", "max_bytes"), ("min_opacity", "min_opacity"))


def pipeline_options(args: argparse.Namespace):
    """The API's options object, from reconstruct's flags (validated here, before any work)."""
    from ..pipeline import PipelineOptions

    compaction: dict | bool = {key: getattr(args, flag) for flag, key in COMPACTION_FLAGS
                               if getattr(args, flag) is not None}
    if args.no_merge_smooth:
        compaction["merge_smooth"] = False
    if args.no_compaction:
        if compaction:  # refused, not dropped, as the API refuses options that another overrides
            unused = [f"--{flag.replace('_', '-')}" for flag, key in (*COMPACTION_FLAGS, ("no_merge_smooth", "merge_smooth"))
                      if key in compaction]
            raise CliError(f"--no-compaction keeps every Gaussian; {', '.join(unused)} would do nothing with it")
        compaction = False
    try:
        return PipelineOptions.from_dict({"near": args.near, "far": args.far, "compaction": compaction,
                                          "adaptive_range": args.adaptive_range, "sh_degree": args.sh_degree,
                                          "rig_cap_deg": args.rig_cap_deg})
    except ValueError as exc:
        raise CliError(option_message(as_flags(str(exc), ("near", "far", "adaptive_range", "sh_degree", "rig_cap_deg"),
                                               prefix="options.", renamed=OPTION_FLAGS))) from None


def option_message(message: str) -> str:
    """An API message about the ``options`` object in the CLI's words: no ``options:`` prefix (the CLI has
    no such object), ``near=`` / ``far=`` as the flags ``--near`` / ``--far``."""
    message = message.removeprefix("options: ")
    return message.replace("near=", "--near ").replace("far=", "--far ")


#: the API's compaction options whose flag has another name or place (``options.compaction.max_count``)
OPTION_FLAGS = {"compaction.max_count": "max-gaussians", "compaction.max_bytes": "max-bytes",
                "compaction.min_opacity": "min-opacity"}

#: compaction steps (``info["compaction"]["removed"]``) and the flags that set them
STEP_FLAGS = {"min_opacity": "--min-opacity", "cap": "--max-gaussians / --max-bytes"}


def cmd_reconstruct(args: argparse.Namespace) -> int:
    from ..photometric import MAX_ERP_WIDTH
    from ..pipeline import build_scene
    from ..scenes import read_width

    inputs = [*args.inputs, args.poses, *(Path(p) / "scene.json" for p in args.inputs if Path(p).is_dir())]
    check_output(args.output, "-o", (".ply", ".spz"), "a Gaussian PLY or SPZ", inputs)
    if args.json is not None:
        check_output(args.json, "--json", (".json",), "the summary", inputs, outputs=[args.output])
    # the model and its threads are checked as serve checks them (1-256 threads), before any work
    settings = cli_settings(args, {"model_path": ("model", "--model"), "ort_threads": ("threads", "--threads")})
    # wide JPEGs at a reduced scale, as the API reads them for a model no wider than the pose features read; bad
    # inputs fail before any model build
    erp_a, erp_b, c2w_a, c2w_b, source = load_pair(args, MAX_ERP_WIDTH)
    options = pipeline_options(args)
    from ..errors import ServiceError
    from ..inputs import Poses, check_scale_options
    from ..poses import PoseOptions, poses_for_scene

    try:
        pose_options = PoseOptions.pop_from({"camera_height": args.camera_height, "baseline": args.baseline,
                                             "refine_poses": args.refine_poses})
        check_scale_options(c2w_a is not None, pose_options)
    except ServiceError as exc:
        raise CliError(as_flags(exc.message, ("camera_height", "baseline", "refine_poses"), prefix="options.")) from None
    for name, img in (("image A", erp_a), ("image B", erp_b)):
        if img.shape[1] != 2 * img.shape[0]:
            raise CliError(f"{name} is {img.shape[1]}x{img.shape[0]}; an ERP panorama must be exactly 2:1")
    t0 = time.perf_counter()
    given = None if c2w_a is None else Poses("opencv", c2w_a, c2w_b)
    if given is None:
        say("estimating the relative pose from the images")
    try:
        files = source.get("images", [None, None])  # their XMP may hold the cameras' tilt
        data = tuple(Path(f).read_bytes() if f is not None else None for f in files)
        c2w_a, c2w_b, poses_json = poses_for_scene(erp_a, erp_b, given, pose_options, data=data)
    except ServiceError as exc:
        raise CliError(exc.message) from None
    poses_s = time.perf_counter() - t0
    from ..inputs import check_sweep_range

    try:  # the API's 422 for a near/far that does not fit these cameras, before the model loads
        check_sweep_range(c2w_a, c2w_b, {"near": args.near, "far": args.far})
    except ServiceError as exc:
        raise CliError(option_message(exc.message)) from None
    model = model_file(settings, args.no_build)
    say(f"loading model {model}")
    from ..encoder import EncoderInputError

    t0 = time.perf_counter()
    encoder = load_encoder(model, settings.ort_threads)
    load_s = time.perf_counter() - t0
    if read_width(encoder.height) > MAX_ERP_WIDTH:  # a wider model reads more columns
        erp_a, erp_b, *_ = load_pair(args, read_width(encoder.height))
    say(f"reconstructing {erp_a.shape[1]}x{erp_a.shape[0]} + {erp_b.shape[1]}x{erp_b.shape[0]} panoramas")
    t0 = time.perf_counter()
    try:
        rec = build_scene(encoder, erp_a, erp_b, c2w_a, c2w_b, options)
    except EncoderInputError as exc:
        raise CliError(option_message(str(exc))) from None
    from ..scenes import check_not_empty

    try:  # the API's 422 empty_scene: no PLY without a Gaussian is written
        check_not_empty(rec, STEP_FLAGS)  # an empty compaction named in the flags that set it
    except ServiceError as exc:
        raise CliError(exc.message) from None
    if given is not None:  # the API's 422 poses_mismatch
        from ..pose_check import check_given_poses

        try:
            check_given_poses(erp_a, erp_b, c2w_a, c2w_b, rec.info.get("mean_confidence"), source["convention"])
        except ServiceError as exc:
            raise CliError(exc.message) from None
    total = time.perf_counter() - t0
    out = Path(args.output)
    write_output(out, rec.gaussians)
    from ..store import json_safe

    summary = json_safe({
        "ply": str(out), "num_gaussians": len(rec.gaussians), "source": source,
        "model": {k: encoder.metadata.get(k) for k in ("name", "version", "sha256")},
        "timings": {**rec.timings, "poses": poses_s, "model_load": load_s, "total": total}, "info": rec.info,
        "poses": poses_json,
    })
    text = json.dumps(summary, indent=2)
    if args.json:
        write_output(args.json, (text + "\n").encode())
    print(text)
    say(f"wrote {len(rec.gaussians)} Gaussians to {out} in {total:.2f} s")
    return 0


def add_parser(sub) -> None:
    r = sub.add_parser("reconstruct", help="scene folder or two images + poses -> Gaussian PLY and a JSON summary",
                       description="Reconstruct 3D Gaussians from two ERP panoramas, without the HTTP service.")
    r.add_argument("inputs", nargs="+", help="a scene folder (scene.json), or two image files")
    r.add_argument("--poses", help='with two images: JSON file {"convention": "opencv"|"opengl", "c2w": [A, B]}; '
                                   "without it the poses are estimated from the images (world = camera A, levelled)")
    r.add_argument("--camera-height", type=float, help="estimated poses: metres of camera A above the floor (sets the scale)")
    r.add_argument("--baseline", type=float, help="estimated poses: metres between the cameras (sets the scale)")
    r.add_argument("--refine-poses", action="store_true", help="refine given poses against the images (upright model)")
    r.add_argument("--split", type=int, help="scene folder: which split's references (default 0)")
    r.add_argument("--refs", help="scene folder: two frame names, e.g. 00,02 (overrides --split)")
    r.add_argument("-o", "--output", default="scene.ply",
                   help="output PLY (default scene.ply), or SPZ (a name ending in .spz: a fifth of the bytes)")
    r.add_argument("--json", help="also write the summary JSON to this .json file")
    r.add_argument("--model", type=Path, help="ONNX model (default: the one `serve` uses, built if missing)")
    r.add_argument("--no-build", action="store_true", help="fail instead of building a missing model")
    r.add_argument("--near", type=float, help="nearest depth in metres (default from the baseline)")
    r.add_argument("--far", type=float, help="farthest depth in metres")
    r.add_argument("--threads", type=int, help="onnxruntime threads, 1-256 (default 2)")
    c = r.add_argument_group("leave out what the scene does not need (default: min opacity and the smooth merge)")
    c.add_argument("--no-compaction", action="store_true", help="keep every pixel-aligned Gaussian")
    c.add_argument("--no-merge-smooth", action="store_true",
                   help="keep flat, evenly coloured regions at one Gaussian per pixel (default: merge 2x2 blocks)")
    c.add_argument("--min-opacity", type=float, help="drop Gaussians below this opacity (default 1/255)")
    c.add_argument("--max-gaussians", type=int, help="cap the count (merges more flat blocks, then drops the least visible)")
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
