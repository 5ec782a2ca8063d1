"""Give memory back to the system after big requests (glibc malloc), so the server's RSS follows its work.

A reconstruction or a large render allocates hundreds of MB of numpy arrays in worker threads. glibc
serves them from per-thread arenas and, once the dynamic mmap threshold has risen (it follows the
largest freed block, up to 32 MB), from the heap: freed, they stay resident as fragmented arena
memory. :func:`release_memory` (after each heavy call) returns free pages with ``malloc_trim(0)``;
the first call also pins the mmap threshold (arrays of 4 MB and more are mapped and unmapped on free)
and caps the arenas at 2. Outside glibc (musl, macOS) both are no-ops.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import threading
import time
from typing import Any, Callable, TypeVar

T = TypeVar("T")

#: glibc mallopt parameters (malloc.h)
_M_MMAP_THRESHOLD = -3
_M_ARENA_MAX = -8
#: allocations from this size on are mmap'ed (returned to the system on free)
MMAP_THRESHOLD_BYTES = 4 << 20
#: malloc arenas (one per worker thread otherwise, up to 8 per core)
ARENA_MAX = 2
#: least seconds between two trims (a trim walks the heap: a few ms per hundred MB)
TRIM_INTERVAL_S = 0.5

_lock = threading.Lock()
_state: dict[str, Any] = {"libc": None, "configured": False, "last": 0.0}
#: False turns release_memory off (the bench measures the difference)
enabled = True


def _libc():
    if _state["libc"] is None:
        try:
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
            libc.malloc_trim  # noqa: B018 - glibc only
            libc.mallopt  # noqa: B018
            _state["libc"] = libc
        except (OSError, AttributeError):
            _state["libc"] = False
    return _state["libc"]


def release_memory(force: bool = False) -> bool:
    """Return free heap pages to the system (at most every :data:`TRIM_INTERVAL_S` unless ``force``);
    True when a trim ran."""
    libc = _libc() if enabled else False
    if not libc:
        return False
    with _lock:
        if not _state["configured"]:
            libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)
            libc.mallopt(_M_ARENA_MAX, ARENA_MAX)
            _state["configured"] = True
        now = time.monotonic()
        if not force and now - _state["last"] < TRIM_INTERVAL_S:
            return False
        _state["last"] = now
    libc.malloc_trim(0)
    return True


def trimmed(fn: Callable[..., T], *args: Any) -> T:
    """``fn(*args)``, then :func:`release_memory` once its arrays are freed: ``WorkGate.run(trimmed, fn, ...)``."""
    try:
        return fn(*args)
    finally:
        release_memory()
