"""What every sub-command shares: the one-line user error, the progress line on stderr, lazy optional imports."""

from __future__ import annotations

import math
import os
import sys
from pathlib import Path


class CliError(Exception):
    """A user-facing error: printed as one line, exit status 2."""


#: what a missing ``--model`` (or OMNISPLAT_MODEL_PATH) file's error adds
MODEL_HINT = ("; only the default model (no --model) is built when missing: check the path, or build this one "
              "with `omnisplat export PATH.onnx`")


def cli_settings(args=None, flags: dict | None = None, *, serving: bool = False, **extra):
    """The service settings (OMNISPLAT_* variables) with a command's flags over them; a bad value is a one-line
    CliError naming the flag (with the value typed) or the variable, never a traceback.

    flags: settings field -> (argparse dest, flag) of ``args``; a flag left out (None) keeps the variable.
    extra: further field values. A command that does not serve binds nothing, so the network's own check (a
    non-loopback ``host`` needs an API key) does not concern it: it is checked on 127.0.0.1.
    """
    from pydantic import ValidationError

    from ..config import Settings

    flags = flags or {}
    given = {field: getattr(args, dest) for field, (dest, _) in flags.items() if getattr(args, dest) is not None}
    values = {**given, **extra}
    if "max_upload_bytes" in values:  # the flag is in MiB; NaN and Inf are left for the field's own check
        mib = values["max_upload_bytes"]
        values["max_upload_bytes"] = int(mib * 1024 * 1024) if math.isfinite(mib) else mib
    if not serving:
        values.setdefault("host", "127.0.0.1")
    try:
        return Settings(**values)
    except ValidationError as exc:
        raise CliError("; ".join(_setting_error(err, args, flags, given) for err in exc.errors(include_url=False))) from None
    except ValueError as exc:  # a variable that does not parse (pydantic-settings' SettingsError): its first line
        raise CliError(f"OMNISPLAT_* settings: {str(exc).splitlines()[0]}") from None


def _setting_error(err: dict, args, flags: dict, given: dict) -> str:
    """One settings error in the user's words: the flag and the value typed, or the environment variable."""
    field = str(err["loc"][0]) if err.get("loc") else ""
    msg = str(err.get("msg", "invalid")).removeprefix("Value error, ")
    if field in given:
        dest, flag = flags[field]
        mib = field == "max_upload_bytes"  # a limit in the message is in bytes, the flag in MiB
        return f"{flag}: {msg}{' bytes' * (mib and msg[-1:].isdigit())} (got {getattr(args, dest)!r}{' MiB' * mib})"
    if not field:  # a rule across settings (its message names them)
        return f"OMNISPLAT_* settings: {msg}"
    return f"OMNISPLAT_{field.upper()}: {msg} (got {err.get('input')!r})"


def load_encoder(model: Path, threads: int):
    """The :class:`service.encoder.OnnxEncoder` of ``model``; a file that is no omnisplat model (another ONNX
    graph, an older exporter's, not ONNX at all) is a one-line CliError naming ``--model``."""
    from ..encoder import OnnxEncoder

    try:
        return OnnxEncoder(model, threads=threads)
    except ValueError as exc:  # an ONNX file that is not an omnisplat encoder, or from an older exporter
        raise CliError(f"--model {model}: {str(exc).removeprefix(f'{model}: ')}") from None  # the path said once
    except Exception as exc:  # onnxruntime's own errors: a file that is no ONNX model
        if not type(exc).__module__.startswith("onnxruntime"):
            raise
        raise CliError(f"--model {model}: not a loadable ONNX model ({str(exc).strip()[:300]})") from None


def say(msg: str) -> None:
    """One progress line on stderr (stdout carries the commands' JSON)."""
    print(f"[omnisplat] {msg}", file=sys.stderr, flush=True)


def forward_import(load, hint: str):
    """``load()`` (a lazy import of an optional part), with a missing module as a one-line CliError."""
    try:
        return load()
    except ModuleNotFoundError as exc:
        if exc.name and exc.name.split(".")[0] in ("export", "service"):
            raise CliError(f"not available: module {exc.name} is not installed here ({hint})") from None
        raise CliError(f"not available: needs {exc.name!r}, which is not installed ({hint})") from None


def as_flags(message: str, names, prefix: str = "", *, renamed: dict[str, str] | None = None) -> str:
    """An API error message with each parameter ``prefix + name + ":"`` written as the CLI's flag ``--name:``
    (underscores as dashes), so that the user reads the option they typed; ``renamed`` maps the API names
    whose flag has another name (``{"compaction.max_count": "max-gaussians"}``) to it."""
    pairs = [(name, name) for name in names] + list((renamed or {}).items())
    for name, flag in sorted(pairs, key=lambda p: -len(p[0])):  # longest first: "x.max_count" before "max_count"
        message = message.replace(f"{prefix}{name}:", f"--{flag.replace('_', '-')}:")
    return message


def check_suffix(path: str | Path, flag: str, suffixes: tuple[str, ...], what: str) -> str:
    """``path``'s lower-case suffix, one of ``suffixes``; else a CliError naming ``flag`` (the file's format
    follows its name, as the API's ``format`` does its content type)."""
    suffix = Path(path).suffix.lower()
    if suffix not in suffixes:
        names = ", ".join(suffixes[:-1]) + (" or " if len(suffixes) > 1 else "") + suffixes[-1]
        raise CliError(f"{flag} {path}: the name must end in {names} ({what})")
    return suffix


def check_output(path: str | Path, flag: str, suffixes: tuple[str, ...], what: str, inputs=(), outputs=()) -> str:
    """``path``'s suffix (:func:`check_suffix`) once the output is known to be writable, before any work:
    a CliError naming ``flag`` for an empty name, a folder, a path under a file, a folder this user cannot
    write in (probed with a temporary file), one of the command's ``inputs`` (paths, None skipped), which
    the output would overwrite, or a path inside another of its ``outputs`` or above one: the second file
    written would fail on the first, after the work and with the first left behind."""
    if not str(path).strip():
        raise CliError(f"{flag}: give a file name")
    out = Path(path)
    if out.is_dir():
        raise CliError(f"{flag} {path} is a folder; give a file name")
    suffix = check_suffix(path, flag, suffixes, what)
    for other in outputs:
        a, b = Path(os.path.abspath(out)), Path(os.path.abspath(other))
        if a == b or a in b.parents or b in a.parents:
            raise CliError(f"{flag} {path}: it and the output {other} cannot both be files (the same path, or one "
                           "under the other); give the outputs separate names")
    if out.exists() and any(p is not None and Path(p).exists() and Path(p).samefile(out) for p in inputs):
        raise CliError(f"{flag} {path} is one of the command's inputs; give another file name")
    folder = out.absolute().parent
    while not folder.exists():  # the folders the command will make
        folder = folder.parent
    if not folder.is_dir():
        raise CliError(f"{flag} {path}: {folder} is a file, not a folder")
    if (problem := cannot_write_in(folder)) is not None:
        raise CliError(f"{flag} {path}: cannot write in {folder}: {problem}")
    return suffix


def cannot_write_in(folder: Path) -> str | None:
    """Why this user cannot create a file in ``folder`` (an existing folder), probed with a temporary file;
    None when it can."""
    import tempfile

    try:
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".omnisplat-probe-"):
            return None
    except OSError as exc:
        return str(exc.strerror or exc)


def model_file(settings, no_build: bool) -> Path:
    """The model file ``settings`` name, built first when it is the default one and missing (unless
    ``no_build``); a named model that is missing is a typo, not a request to build: a CliError with
    :data:`MODEL_HINT`."""
    from ..model_files import ModelUnavailable, ensure_model

    try:
        return ensure_model(settings.resolved_model_path, build_if_missing=not no_build and settings.model_path is None)
    except ModelUnavailable as exc:
        raise CliError(str(exc) + MODEL_HINT * (settings.model_path is not None)) from None


def write_output(path: str | Path, data) -> None:
    """Write ``data`` (bytes, or a :class:`rasterizer.gaussians.Gaussians` as a PLY, or as SPZ when the name
    ends in ``.spz``) to ``path``, making its folders (as :func:`check_output` allowed); an OSError, or Gaussians
    SPZ cannot hold, is a CliError naming the file.

    Every format is written to a hidden temporary file beside ``path`` and renamed over it, so that a write that
    fails (a full disk, a file size limit, Ctrl-C) leaves neither a truncated file nor a damaged older one; a
    symbolic link is written through (its target replaced), as a plain write would
    (:func:`rasterizer.ply.write_whole`)."""
    from rasterizer.ply import ply_bytes, write_whole
    from rasterizer.spz import SpzError, spz_bytes

    out = Path(path)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        if isinstance(data, bytes):
            payload = data
        elif out.suffix.lower() == ".spz":
            payload = spz_bytes(data)
        else:
            payload = ply_bytes(data)
        write_whole(out, payload)
    except OSError as exc:
        raise CliError(f"cannot write {out}: {exc.strerror or exc}") from None
    except SpzError as exc:
        raise CliError(f"cannot write {out}: {exc}") from None


#: PLY properties of each :class:`rasterizer.gaussians.Gaussians` field, as a user reads them in the file
PLY_FIELDS = {"means": "x, y, z", "scales": "scale_0..2", "quats": "rot_0..3", "opacities": "opacity",
              "sh": "f_dc_0..2 / f_rest_*"}


#: The first bytes of a gzip stream: an SPZ file (a PLY starts with "ply").
GZIP_MAGIC = b"\x1f\x8b"


def read_gaussians(path: str | Path):
    """The Gaussians of a PLY or SPZ file (told apart by their first bytes), as the service keeps a scene's:
    rows holding NaN or Inf (or a scale whose exp overflows float32) are dropped, as the API's pipeline and
    PLY writer drop them, and said on stderr with the first such row; an unreadable file or one without any
    Gaussian is a CliError naming it."""
    import numpy as np

    from rasterizer.ply import finite_rows, read_ply
    from rasterizer.spz import read_spz

    try:
        data = Path(path).read_bytes()
        spz = data[:2] == GZIP_MAGIC
        g = read_spz(data) if spz else read_ply(data)
    except (OSError, ValueError) as exc:  # PlyError and SpzError name the problem (a malformed header line...)
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
        raise CliError(f"cannot read {path}: {reason}") from None
    n = len(g)
    ok = finite_rows(g)
    if not ok.all():
        row = int(np.flatnonzero(~ok)[0])
        field = next(f for f in PLY_FIELDS if not np.isfinite(getattr(g, f)[row]).all())
        g = g.subset(ok)
        if len(g):
            say(f"{path}: dropped {n - len(g)} of {n} Gaussians holding NaN or Inf, as the service does "
                f"(the first: row {row}, {PLY_FIELDS[field]})")
    if len(g) == 0:
        raise CliError(f"{path}: the {'SPZ' if spz else 'PLY'} holds no Gaussians"
                       + (f" with finite values (all {n} rows hold NaN or Inf, e.g. row {row}: {PLY_FIELDS[field]})"
                          if n else ""))
    return g


def read_panorama(path: str | Path, min_width: int | None = None):
    """An image file decoded as the API decodes an upload (:func:`service.images.decode_rgb`: 16-bit and
    float images scaled by their range, the EXIF orientation applied, truncated or non-2:1 files refused,
    the API's default pixel limits), as float32 RGB (H, W, 3) in [0, 1]; a bad file is a CliError naming it.
    A JPEG wider than twice ``min_width`` is decoded at a reduced scale, as the API decodes it
    (:func:`service.images.jpeg_reduction`); None decodes it whole."""
    import numpy as np

    from ..config import Settings
    from ..errors import ServiceError
    from ..images import decode_rgb

    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise CliError(f"cannot read image {path}: {exc.strerror or exc}") from None
    fields = Settings.model_fields
    try:
        rgb, _ = decode_rgb(data, str(path), max_pixels=fields["max_image_pixels"].default,
                            min_height=fields["min_image_height"].default, min_width=min_width)
    except ServiceError as exc:
        raise CliError(exc.message) from None
    return rgb.astype(np.float32) / np.float32(255.0)
