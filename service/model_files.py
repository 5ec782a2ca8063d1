"""Find or build the ONNX model file the service runs.

Building needs torch (the ``export`` extra); it is imported here only when a build is
actually needed, so the runtime (and the Docker runtime stage) never imports it.
"""

from __future__ import annotations

import functools
import hashlib
import os
import sys
import time
import uuid
from pathlib import Path
from typing import Callable

REPO_ROOT = Path(__file__).resolve().parents[1]
#: rasterizer modules the exporter bakes into the graph
_RASTERIZER_DEPS = ("geometry.py", "gaussians.py", "sweep.py", "yin_yang.py")


def source_hash(files) -> str:
    """Short hash (10 hex digits) of the named source files' bytes, in the order given (absent ones skipped)."""
    h = hashlib.sha256()
    for f in files:
        if f.exists():
            h.update(f.name.encode() + b"\0" + f.read_bytes())
    return h.hexdigest()[:10]


def export_code_hash() -> str:
    """Short hash of the exporter's source (export/*.py and the rasterizer modules it uses).

    Part of model file names, so a model built by older code is never reused. Reads the
    files as bytes: no torch import.
    """
    return source_hash(sorted((REPO_ROOT / "export").glob("*.py")) + [REPO_ROOT / "rasterizer" / f for f in _RASTERIZER_DEPS])


@functools.cache
def build_code_hash() -> str:
    """Short hash of the code that turns uploads into a stored scene (rasterizer/ and service/ sources).

    Part of scene ids, so a store written by other code (another pose estimator, colour fit,
    compaction or image decoding) never answers a new upload with a scene built otherwise.
    """
    return source_hash(sorted((REPO_ROOT / "rasterizer").rglob("*.py")) + sorted((REPO_ROOT / "service").rglob("*.py")))


def default_model_name() -> str:
    """File name of the default model built by this version of the exporter."""
    return f"omnisplat-default-{export_code_hash()}.onnx"


class ModelUnavailable(RuntimeError):
    """The model file is missing and cannot be built here."""


def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    """Hex sha256 of a file, read in chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def _say(msg: str) -> None:
    print(f"[omnisplat] {msg}", file=sys.stderr, flush=True)


def build_whole(path: str | Path, export_model: Callable[..., str | Path], **export_kwargs) -> Path:
    """Build a model with ``export_model(temporary path, **export_kwargs)`` into a hidden file beside ``path`` and
    rename it over ``path`` once complete (a symbolic link is written through); returns the path written. A
    failed or interrupted build (minutes of torch) leaves neither a half-written model at ``path``, nor a damaged
    earlier one, nor its temporary file (or an external-data file beside it)."""
    path = Path(path)
    target = path.resolve() if path.is_symlink() else path
    tmp = target.with_name(f".{target.name}.{uuid.uuid4().hex[:12]}.tmp.onnx")
    try:
        os.replace(Path(export_model(tmp, **export_kwargs)), target)
    except BaseException:
        for leftover in (tmp, tmp.with_name(tmp.name + ".data")):
            leftover.unlink(missing_ok=True)
        raise
    return target


def ensure_model(path: str | Path, *, build_if_missing: bool = True,
                 progress: Callable[[str], None] = _say, **export_kwargs) -> Path:
    """Return ``path`` if it exists; otherwise export the default model there (needs torch).

    The export writes to a temporary name and renames, so an interrupted build never
    leaves a half-written model that a later start would load.
    """
    path = Path(path)
    if path.is_file():
        return path
    if path.exists():  # a folder (or a device) where the model file should be: never built over
        kind = "a folder" if path.is_dir() else "not a regular file"
        raise ModelUnavailable(f"model file {path} is {kind}; give the path of an .onnx file")
    if not build_if_missing:
        raise ModelUnavailable(f"model file {path} does not exist")
    try:
        from export.onnx_export import export_model  # imports torch
    except ImportError as exc:
        raise ModelUnavailable(
            f"model file {path} does not exist and cannot be built here ({exc}). "
            "Install the export extra (pip install -e '.[export]') or pass --model PATH to a prebuilt .onnx"
        ) from None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:  # models_dir under a file, or a folder this user cannot make
        raise ModelUnavailable(f"model file {path} does not exist and cannot be built there: cannot make "
                               f"{path.parent} ({exc.strerror or exc})") from None
    progress(f"building the ONNX model -> {path} (one-off, needs torch; this can take a minute)")
    start = time.perf_counter()
    build_whole(path, export_model, **export_kwargs)
    progress(f"model built in {time.perf_counter() - start:.1f} s ({path.stat().st_size / 1e6:.1f} MB)")
    return path
