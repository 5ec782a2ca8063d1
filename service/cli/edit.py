"""``omnisplat select`` / ``omnisplat edit``: selections and edits of scenes in a service store."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from .common import CliError, as_flags, cli_settings


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
    """The store the server's settings describe (budget, max scenes: OMNISPLAT_*), in ``--store`` if given.
    It never clears unfinished writes: a running server may be writing them. A folder that holds no store
    (no ``scenes/``: a mistyped path) is a CliError, not made into an empty store that then has no such scene."""
    from ..store import SceneStore

    settings = cli_settings(args, {"store_dir": ("store", "--store")})
    where = f"--store {settings.store_dir}" if args.store is not None else f"the scene store {settings.store_dir}"
    if not (settings.store_dir / "scenes").is_dir():
        raise CliError(f"{where}: no scene store there (no scenes/ folder); give the folder that "
                       "`omnisplat serve --store` keeps its scenes in")
    try:
        return SceneStore.from_settings(settings, clean_up=False)
    except OSError as exc:  # e.g. --store names a file
        raise CliError(f"{where}: cannot open the scene store: {exc.strerror or exc}") from None


def _edit_call(fn, *a):
    from ..errors import ServiceError, translate
    from ..store import json_safe

    try:
        out = fn(*a)
    except Exception as exc:  # domain errors (a malformed scene id, a full store...) as the API words them
        mapped = translate(exc)
        if not isinstance(mapped, ServiceError):
            raise
        raise CliError(f"{mapped.code}: {mapped.message}") from None
    print(json.dumps(json_safe(out), indent=1))
    return 0


#: the flag (without its dashes) of each key of the API's bodies (POST .../selections and .../edits)
BODY_FLAGS = {"points": "point", "negative": "negative", "view": "view", "segment": "segment",
              "selection": "selection", "op": "op", "color": "color", "offset": "offset"}


def _checked(model, request: dict, what: str) -> dict:
    """``request`` validated by the API's body model (:class:`service.edits.SelectionRequest` / ``EditRequest``);
    an error names the flags (``--point``), not the body's keys (``select.points``)."""
    from pydantic import ValidationError

    from ..options import describe_error

    try:
        model.model_validate(request)
    except ValidationError as exc:
        raise CliError(as_flags(describe_error(exc, prefix=what), (), prefix=f"{what}.", renamed=BODY_FLAGS)) from None
    return request


def cmd_select(args: argparse.Namespace) -> int:
    from .. import edits
    from ..errors import ServiceError

    if args.segment is not None:
        request = {"segment": args.segment}
        if args.view is not None or args.point or args.negative:  # the API's 422 for a segment with points
            raise CliError("--segment: give either --segment or --view with --point, not both")
    else:
        if not args.point:
            raise CliError("give --point u,v (one or more) or --segment N")
        if args.view is None:  # the API's 422 for a selection without its view
            raise CliError("--view: give the reference the points lie on, a or b")
        request = {"view": args.view, "points": [_point(p) for p in args.point],
                   "negative": [_point(p) for p in args.negative or []]}
        for name in ("points", "negative"):
            try:  # the API's check (POST .../selections)
                edits.check_points(request[name], name)
            except ServiceError as exc:
                raise CliError(f"--{BODY_FLAGS[name]}: {exc.message}") from None
    _checked(edits.SelectionRequest, request, "select")
    return _edit_call(edits.create_selection, _edit_store(args), args.scene, request)


def cmd_edit(args: argparse.Namespace) -> int:
    from .. import edits

    request = {"selection": args.selection, "op": args.op}
    if args.op == "recolor" or args.color is not None:
        request["color"] = _triple(args.color or "", "--color")
    if args.op == "translate" or args.offset is not None:
        request["offset"] = _triple(args.offset or "", "--offset")
    _checked(edits.EditRequest, request, "edit")  # e.g. --color 2,0,0, or with --op remove: refused as the API does
    return _edit_call(lambda *a: edits.create_edit(*a)[0], _edit_store(args), args.scene, request)


def add_parsers(sub) -> None:
    e = sub.add_parser("select", help="select an object (points on a reference, or a segment) of a stored scene")
    e.add_argument("scene", help="scene id in the store")
    e.add_argument("--store", type=Path, help="scene store folder (default ~/.omnisplat/scenes)")
    e.add_argument("--view", choices=["a", "b"], help="the reference the points lie on (required with --point)")
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
