"""``omnisplat render``: a view of a Gaussian PLY from a camera pose, with the CPU rasterizer."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from .common import CliError, as_flags, check_output, cli_settings, read_gaussians, read_panorama, say, write_output


def _pose_from_args(args: argparse.Namespace):
    from ..errors import ServiceError
    from ..inputs import json_value, parse_c2w_query, without_bom

    if (args.c2w is None) == (args.pose is None):
        raise CliError("give exactly one of --c2w '16 numbers' or --pose FILE.json")
    try:
        if args.c2w is not None:
            return parse_c2w_query(args.c2w)
        from rasterizer.geometry import PoseError, as_c2w

        obj = json_value(without_bom(Path(args.pose).read_bytes()), "--pose")  # as the API reads its JSON fields
        unknown = sorted(set(obj) - {"convention", "c2w"}) if isinstance(obj, dict) else []
        if unknown:  # a misspelt "convention" would otherwise mean OpenCV
            raise CliError(f"{args.pose}: unknown key(s) {unknown[:5]}; expected a 4x4 matrix or "
                           '{"convention": "opencv"|"opengl", "c2w": M}')
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
    try:
        images = [read_panorama(p) for p in args.rig]
    except CliError as exc:
        raise CliError(f"--rig: {exc}") from None
    if images[0].shape != images[1].shape or images[0].shape[1] != 2 * images[0].shape[0]:
        raise CliError(f"--rig: need two 2:1 panoramas of one size, got {images[0].shape[1]}x{images[0].shape[0]} "
                       f"and {images[1].shape[1]}x{images[1].shape[0]}")
    try:
        return require_rig_layer(*images)
    except NoRigError as exc:
        raise CliError(f"--rig: {exc}; render without --rig") from None


def cmd_render(args: argparse.Namespace) -> int:
    c2w = _pose_from_args(args)
    from rasterizer.render import render, to_uint8
    from rasterizer.splat import ALPHA_MIN, RenderLimitError

    from ..errors import ServiceError
    from ..images import encode
    from ..inputs import check_render_query
    from ..limits import check_render_budget

    suffix = check_output(args.output, "-o", (".png", ".jpg", ".jpeg"), "the image format", [args.ply, *(args.rig or ())])
    fmt = {".png": "png", ".jpg": "jpeg", ".jpeg": "jpeg"}[suffix]
    # as the API renders (the same query and its limits): plain compositing unless --compositing va
    settings = cli_settings()
    try:
        query = check_render_query(c2w, args.projection, args.width, args.height,
                                   args.fov_deg, fmt,
                                   max_width=settings.max_render_width, max_pixels=settings.max_render_pixels,
                                   compositing=args.compositing)
    except ServiceError as exc:
        raise CliError(as_flags(exc.message, ("width", "height", "fov_deg"))) from None
    gaussians = read_gaussians(args.ply)
    h, w = query.output_size()
    try:  # the API's render budget: its time and memory grow with pixels x Gaussians
        check_render_budget(h, w, len(gaussians), settings.max_render_cost)
    except ServiceError as exc:
        flags = "--width" if args.projection != "perspective" else "--width and --height"
        raise CliError(f"{flags}: {exc.message}") from None
    # a PLY from anywhere: its footprints are not cut short as a reconstruction's are in the API
    kwargs = query.render_kwargs(normalize=args.compositing == "va", reconstruction=False)
    layer = _rig_layer_from_args(args)
    say(f"rendering {len(gaussians)} Gaussians, {args.projection} {args.width} px wide")
    t0 = time.perf_counter()
    try:
        out = render(gaussians, c2w, **kwargs)
    except RenderLimitError as exc:  # the API's 413 render_too_large
        raise CliError(f"--width {args.width}: this view of {len(gaussians)} Gaussians is too large for the renderer "
                       f"({exc}); give a smaller --width") from None
    colour = out.colour
    if not (out.alpha >= ALPHA_MIN).any():  # an all-black image is a valid render, not a silent one
        say(f"the view shows none of the {len(gaussians)} Gaussians (every pixel's alpha is under 1/255): "
            "they lie outside it, behind the camera or too far to cover a pixel; check --c2w / --pose")
    if layer is not None:
        from rasterizer.camera import camera_directions
        from rasterizer.rig import overlay_rig

        h, w = colour.shape[:2]
        colour = overlay_rig(colour, camera_directions(args.projection, h, w, query.fov_deg), layer)
    data = encode(to_uint8(colour), fmt)
    write_output(args.output, data)
    say(f"wrote {args.output} in {time.perf_counter() - t0:.2f} s")
    return 0


def add_parser(sub) -> None:
    v = sub.add_parser("render", help="Gaussian PLY + camera pose -> image",
                       description="Render a view of a Gaussian PLY with the CPU rasterizer.")
    v.add_argument("ply", help="3DGS PLY file (or SPZ)")
    v.add_argument("--c2w", help="camera-to-world as 16 (or 12) comma-separated numbers, row-major, OpenCV "
                   "(write --c2w=-0.8,... when the first number is negative)")
    v.add_argument("--pose", help='JSON file with a 4x4 matrix or {"convention": ..., "c2w": M}')
    v.add_argument("--projection", default="erp", choices=["erp", "perspective", "yin", "yang"])
    v.add_argument("--width", type=int, default=1024, help="image width (ERP height = width/2)")
    v.add_argument("--height", type=int, help="perspective only (default = width)")
    v.add_argument("--fov-deg", type=float, help="perspective only: horizontal field of view (default 90)")
    v.add_argument("--compositing", default="plain", choices=["plain", "va"],
                   help="plain (default): front-to-back over black, what 3DGS viewers show of the PLY; "
                        "va: colour / accumulated alpha, the OmniSplat paper's normalisation")
    v.add_argument("--rig", nargs=2, metavar=("IMAGE_A", "IMAGE_B"),
                   help="the two reference panoramas: composite the capture rig (tripod) both show at their "
                        "nadir over the render, at its camera's nadir, as a capture from that pose would show it")
    v.add_argument("-o", "--output", default="view.png", help="output .png or .jpg (default view.png)")
    v.set_defaults(func=cmd_render)
