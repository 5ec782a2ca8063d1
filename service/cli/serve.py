"""``omnisplat serve``: the HTTP API (uvicorn, or Ray Serve replicas with ``--ray``)."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from .common import CliError, cannot_write_in, cli_settings, load_encoder, model_file, say

#: the settings (service.config.Settings fields) that serve's flags set: (argparse dest, flag)
SETTING_FLAGS = {"host": ("host", "--host"), "port": ("port", "--port"), "store_dir": ("store", "--store"),
                 "model_path": ("model", "--model"), "models_dir": ("models_dir", "--models-dir"),
                 "ort_threads": ("threads", "--threads"), "max_upload_bytes": ("max_upload_mb", "--max-upload-mb"),
                 "max_requests": ("max_requests", "--max-requests")}


def cmd_serve(args: argparse.Namespace) -> int:
    import uvicorn

    from ..app import create_app
    from ..config import unknown_variables
    from ..server import server_config

    if args.ray:  # a missing extra is said before anything is checked or loaded
        _ray_serving()
    settings = cli_settings(args, SETTING_FLAGS, serving=True)
    typos, others = unknown_variables(os.environ)
    if typos:  # the setting meant would silently keep its default
        raise CliError("; ".join(typos))
    if others:
        say(f"ignoring {', '.join(others)}: no omnisplat setting (see service/config.py)")
    try:  # the store must be a folder this user can write in, or one it can make
        settings.store_dir.mkdir(parents=True, exist_ok=True)
        problem = cannot_write_in(settings.store_dir)
    except OSError as exc:
        problem = str(exc.strerror or exc)
    if problem is not None:
        raise CliError(f"--store {settings.store_dir}: cannot keep scenes there: {problem}")
    if not args.ray:  # Ray Serve binds its own proxy
        _check_port_free(settings.host, settings.port)
    model_file(settings, args.no_build)
    encoder = _checked_encoder(settings, named_by_flag=args.model is not None)
    say(f"model {settings.resolved_model_path}; scenes in {settings.store_dir}")
    if args.ray:  # the replicas load their own: this one is not held while they serve
        encoder = None
        return _serve_ray(args, settings.model_copy(update={"model_path": settings.resolved_model_path}))
    say(f"serving on http://{settings.host}:{settings.port} (docs at /docs; /readyz turns 200 after warm-up)")
    app = create_app(settings, encoder=encoder)  # the checked model is the served one: loaded once
    uvicorn.Server(server_config(app, settings, log_level=args.log_level)).run()
    return 0


def _checked_encoder(settings, *, named_by_flag: bool):
    """The loaded encoder of the model ``settings`` name. A file that cannot load (not ONNX, another graph, an
    older exporter's, damaged) fails here in one line naming where it came from: ``--model``,
    ``OMNISPLAT_MODEL_PATH``, or the default model in ``models_dir``, which a start would otherwise serve as a
    /readyz 503 that never ends (it exists, so it is not built again)."""
    path = settings.resolved_model_path
    try:
        return load_encoder(path, settings.ort_threads)
    except CliError as exc:
        if named_by_flag:
            raise
        source = (f"OMNISPLAT_MODEL_PATH {path}" if settings.model_path is not None
                  else f"the default model {path} (OMNISPLAT_MODELS_DIR)")
        reason = str(exc).removeprefix(f"--model {path}: ")
        hint = "" if settings.model_path is not None else "; delete it and `omnisplat serve` builds it again"
        raise CliError(f"{source}: {reason}{hint}") from None


def _check_port_free(host: str, port: int) -> None:
    """A CliError when ``host:port`` cannot be bound (another server listens there, or the address is not this
    machine's), said before a model is built or loaded: uvicorn would find out only after the warm-up began."""
    import socket

    if int(port) == 0:  # any free port
        return
    try:
        infos = socket.getaddrinfo(host, int(port), type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as exc:
        raise CliError(f"--host {host}: not an address to bind ({exc.strerror})") from None
    family, kind, proto, _, address = infos[0]
    with socket.socket(family, kind, proto) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn binds
        try:
            probe.bind(address)
        except OSError as exc:
            raise CliError(f"--port {port}: cannot listen on {host}:{port}: {exc.strerror} (another server there? "
                           "choose another --port)") from None


def _ray_serving():
    """(RayOptions, run) of :mod:`service.serve_ray`; a CliError when the [ray] extra is not installed."""
    try:
        import ray.serve  # noqa: F401  (the [ray] extra)

        from ..serve_ray import RayOptions, run
    except ModuleNotFoundError as exc:
        raise CliError(f"--ray needs {exc.name!r}: pip install 'omnisplat[ray]'") from None
    return RayOptions, run


def _serve_ray(args: argparse.Namespace, settings) -> int:
    RayOptions, run = _ray_serving()
    opts = RayOptions(min_replicas=args.min_replicas, max_replicas=max(args.min_replicas, args.max_replicas),
                      replica_cpus=args.replica_cpus)
    say(f"Ray Serve: {opts.min_replicas}-{opts.max_replicas} replicas of {opts.replica_cpus:g} CPU "
         f"on http://{settings.host}:{settings.port}")
    return run(settings, opts, address=args.ray_address)


def add_parser(sub) -> None:
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
