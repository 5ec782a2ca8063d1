"""Worker threads for the numpy stages of a request.

numpy releases the GIL inside its array loops, so independent chunks of work (grids, blocks, Gaussians) run side
by side on the machine's two cores. Each caller's chunks are independent and give the values of one pass.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")

#: Threads per stage: the two cores of the machine the service is sized for.
WORKERS = 2


def map_threads(fn: Callable[..., T], *iterables: Iterable) -> list[T]:
    """``[fn(*args) for args in zip(*iterables)]`` on :data:`WORKERS` threads, results in order."""
    with ThreadPoolExecutor(max_workers=WORKERS) as pool:
        return list(pool.map(fn, *iterables))
