"""What every sub-command shares: the one-line user error, the progress line on stderr, lazy optional imports."""

from __future__ import annotations

import sys
from pathlib import Path


class CliError(Exception):
    """A user-facing error: printed as one line, exit status 2."""


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


def as_flags(message: str, names, prefix: str = "") -> str:
    """An API error message with each parameter ``prefix + name + ":"`` written as the CLI's flag ``--name:``
    (underscores as dashes), so that the user reads the option they typed."""
    for name in names:
        message = message.replace(f"{prefix}{name}:", f"--{name.replace('_', '-')}:")
    return message


def read_panorama(path: str | Path):
    """An image file decoded as the API decodes an upload (:func:`service.images.decode_rgb`: 16-bit and
    float images scaled by their range, the EXIF orientation applied, truncated or non-2:1 files refused,
    the API's default pixel limits), as float32 RGB (H, W, 3) in [0, 1]; a bad file is a CliError naming it."""
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
                            min_height=fields["min_image_height"].default)
    except ServiceError as exc:
        raise CliError(exc.message) from None
    return rgb.astype(np.float32) / np.float32(255.0)
