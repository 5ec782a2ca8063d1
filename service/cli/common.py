"""What every sub-command shares: the one-line user error, the progress line on stderr, lazy optional imports."""

from __future__ import annotations

import sys


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
