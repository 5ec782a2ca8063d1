"""Measurements: error against run time, stability, compaction, refinement, load.

Imports anything (export/ for building models, service/ for the runtime path);
imported by nothing but the tests. Its own entry point: ``omnisplat-bench NAME`` (``python -m bench``,
:mod:`bench.__main__`).
The runtime image does not ship it.
"""

from pathlib import Path

#: The dev scenes beside the checkout (``../shared/data``); CI has them too.
DEV_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
