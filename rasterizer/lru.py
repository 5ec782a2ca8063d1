"""A bounded, thread-safe least-recently-used cache, shared by the numpy stages and the service.

:class:`LRUCache` holds at most ``max_items`` entries and, when ``max_bytes`` is given, at most that many
bytes as measured by its ``size`` callable. A :meth:`~LRUCache.get` hit makes the entry the most recently
used; a :meth:`~LRUCache.put` inserts as the most recently used and then evicts the least recently used
entries while either bound is exceeded. An entry larger than ``max_bytes`` is never stored (it would
evict everything and then itself), and ``max_items <= 0`` stores nothing.

A bound may be an ``int`` or a callable returning one. A callable is read at every put, so a bound kept
as a module constant (``lambda: CACHE_SIZE``) follows that constant when it is changed at run time, as
tests do to exercise eviction.

The cache never computes values. Callers look up with :meth:`~LRUCache.get`, compute on a miss without
holding any lock (the work can take seconds and other keys must stay readable meanwhile), then
:meth:`~LRUCache.put` the result. Two threads that miss the same key both compute it; the later put
replaces the earlier entry. Values are stored as given: a caller that shares them between threads
makes them immutable first (numpy arrays read-only). ``None`` is not a storable value, since
:meth:`~LRUCache.get` returns it for a miss.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Generic, TypeVar, Union

K = TypeVar("K", bound=Hashable)
V = TypeVar("V")

#: A bound: a fixed number, or a callable read at every put.
Bound = Union[int, Callable[[], int]]


def _read(bound: Bound) -> int:
    return int(bound() if callable(bound) else bound)


class LRUCache(Generic[K, V]):
    """Least-recently-used map bounded by entry count and optionally by bytes; every method is thread-safe.

    ``max_items``: most entries kept. ``max_bytes``: most bytes kept, as the sum of ``size(value)`` over the
    entries (``None``: no byte bound). ``size``: bytes of one value, called outside the lock; required with
    ``max_bytes``, optional otherwise (without it every entry counts 0 bytes). ``hits`` and ``misses``
    count :meth:`get` results since construction; :meth:`clear` does not reset them.
    """

    def __init__(self, max_items: Bound, max_bytes: Bound | None = None,
                 size: Callable[[V], int] | None = None) -> None:
        if max_bytes is not None and size is None:
            raise ValueError("a byte bound needs a size callable")
        self._max_items = max_items
        self._max_bytes = max_bytes
        self._size = size
        self._data: OrderedDict[K, tuple[V, int]] = OrderedDict()  # least recently used first
        self._bytes = 0
        self._lock = threading.Lock()
        self.hits = 0
        self.misses = 0

    @property
    def max_items(self) -> int:
        """The entry bound now."""
        return _read(self._max_items)

    @property
    def max_bytes(self) -> int | None:
        """The byte bound now (``None``: none)."""
        return None if self._max_bytes is None else _read(self._max_bytes)

    def get(self, key: K) -> V | None:
        """The value kept for ``key``, made the most recently used; ``None`` when absent."""
        with self._lock:
            item = self._data.get(key)
            if item is None:
                self.misses += 1
                return None
            self._data.move_to_end(key)
            self.hits += 1
            return item[0]

    def put(self, key: K, value: V) -> bool:
        """Keep ``value`` under ``key`` as the most recently used entry, replacing any entry for ``key``, then
        evict the least recently used entries while a bound is exceeded. Returns whether ``value`` is kept:
        not when ``max_items <= 0`` or its size exceeds ``max_bytes`` (any older entry for ``key`` is then
        removed too, so a later get does not return a stale value)."""
        size = int(self._size(value)) if self._size is not None else 0
        with self._lock:
            max_items, max_bytes = self.max_items, self.max_bytes
            old = self._data.pop(key, None)
            if old is not None:
                self._bytes -= old[1]
            kept = max_items > 0 and (max_bytes is None or size <= max_bytes)
            if kept:
                self._data[key] = (value, size)
                self._bytes += size
            while self._data and (len(self._data) > max_items or (max_bytes is not None and self._bytes > max_bytes)):
                _, (_, evicted) = self._data.popitem(last=False)
                self._bytes -= evicted
            return kept

    def drop(self, key: K) -> bool:
        """Forget ``key``; True when an entry for it is removed."""
        with self._lock:
            item = self._data.pop(key, None)
            if item is None:
                return False
            self._bytes -= item[1]
            return True

    def clear(self) -> None:
        """Forget every entry (the hit and miss counts stay)."""
        with self._lock:
            self._data.clear()
            self._bytes = 0

    def keys(self) -> list[K]:
        """The keys kept, least recently used first (a snapshot; the order is not changed)."""
        with self._lock:
            return list(self._data)

    @property
    def nbytes(self) -> int:
        """Bytes held: the sum of ``size(value)`` over the entries."""
        return self._bytes

    def __len__(self) -> int:
        return len(self._data)
