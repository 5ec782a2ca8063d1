"""rasterizer.lru.LRUCache: eviction order, the entry and byte bounds, counters and use from many threads."""

import random
import threading

import pytest

from rasterizer.lru import LRUCache


def test_least_recently_used_goes_first():
    cache: LRUCache[str, int] = LRUCache(3)
    for i, key in enumerate("abc"):
        assert cache.put(key, i)
    assert cache.keys() == ["a", "b", "c"]
    assert cache.get("a") == 0  # a is now the newest
    assert cache.put("d", 3)  # b goes
    assert cache.keys() == ["c", "a", "d"]
    assert cache.get("b") is None
    assert cache.put("c", 20)  # a put replaces the value and makes it the newest
    assert cache.keys() == ["a", "d", "c"] and cache.get("c") == 20
    assert cache.put("e", 4)
    assert cache.keys() == ["d", "c", "e"] and len(cache) == 3


def test_byte_bound_evicts_oldest_until_it_fits():
    cache: LRUCache[str, bytes] = LRUCache(10, max_bytes=10, size=len)
    cache.put("a", b"1234")
    cache.put("b", b"1234")
    assert cache.nbytes == 8 and len(cache) == 2
    cache.put("c", b"123")  # 11 bytes: a goes
    assert cache.keys() == ["b", "c"] and cache.nbytes == 7
    cache.put("d", b"123456789")  # 16 bytes, then 12: b and c go
    assert cache.keys() == ["d"] and cache.nbytes == 9
    cache.put("d", b"1")  # a replaced value's bytes are counted once
    assert cache.nbytes == 1


def test_an_entry_larger_than_the_byte_bound_is_not_stored():
    cache: LRUCache[str, bytes] = LRUCache(10, max_bytes=4, size=len)
    assert cache.put("a", b"12")
    assert cache.put("b", b"12")
    assert not cache.put("big", b"12345")
    assert cache.get("big") is None
    assert cache.keys() == ["a", "b"] and cache.nbytes == 4  # nothing evicted for it
    assert not cache.put("a", b"12345")  # the older value for that key goes too: no stale read
    assert cache.get("a") is None and cache.keys() == ["b"] and cache.nbytes == 2


@pytest.mark.parametrize("bound", [0, -1])
def test_no_room_stores_nothing(bound):
    cache: LRUCache[str, int] = LRUCache(bound)
    assert not cache.put("a", 1)
    assert len(cache) == 0 and cache.get("a") is None and cache.nbytes == 0


def test_a_callable_bound_is_read_at_each_put():
    bound = {"n": 3}
    cache: LRUCache[int, int] = LRUCache(lambda: bound["n"])
    for i in range(5):
        cache.put(i, i)
    assert cache.keys() == [2, 3, 4] and cache.max_items == 3
    bound["n"] = 1
    cache.put(5, 5)
    assert cache.keys() == [5]
    bound["n"] = 0
    assert not cache.put(6, 6)
    assert len(cache) == 0


def test_drop_and_clear():
    cache: LRUCache[str, bytes] = LRUCache(4, max_bytes=100, size=len)
    cache.put("a", b"xx")
    cache.put("b", b"yyy")
    assert cache.drop("a") and not cache.drop("a")
    assert cache.keys() == ["b"] and cache.nbytes == 3
    cache.get("b")
    cache.get("a")
    cache.clear()
    assert len(cache) == 0 and cache.nbytes == 0 and cache.keys() == []
    assert (cache.hits, cache.misses) == (1, 1)  # clear keeps the counts
    assert cache.put("a", b"z") and cache.get("a") == b"z"


def test_hits_and_misses_are_counted():
    cache: LRUCache[str, int] = LRUCache(1)
    assert (cache.hits, cache.misses) == (0, 0)
    cache.get("a")
    cache.put("a", 1)
    cache.get("a")
    cache.get("a")
    cache.put("b", 2)  # a goes
    cache.get("a")
    assert (cache.hits, cache.misses) == (2, 2)


def test_a_byte_bound_needs_a_size():
    with pytest.raises(ValueError):
        LRUCache(4, max_bytes=10)


def test_threads_keep_the_bounds_and_the_byte_count():
    max_items, max_bytes = 8, 200
    cache: LRUCache[int, tuple[int, bytes]] = LRUCache(max_items, max_bytes=max_bytes, size=lambda v: len(v[1]))
    gets_per_thread, threads = 3000, 8
    wrong: list[tuple[int, object]] = []
    start = threading.Barrier(threads)

    def work(seed: int) -> None:
        rng = random.Random(seed)
        start.wait()
        for _ in range(gets_per_thread):
            key = rng.randrange(32)
            got = cache.get(key)
            if got is not None and got[0] != key:
                wrong.append((key, got))
            if got is None:
                cache.put(key, (key, bytes(rng.randrange(1, 60))))
            elif rng.random() < 0.1:
                cache.drop(key)

    pool = [threading.Thread(target=work, args=(seed,)) for seed in range(threads)]
    for t in pool:
        t.start()
    for t in pool:
        t.join()
    assert not wrong
    assert cache.hits + cache.misses == threads * gets_per_thread
    assert cache.hits > 0 and cache.misses > 0
    keys = cache.keys()
    assert 0 < len(keys) <= max_items and len(cache) == len(keys)
    values = [cache.get(k) for k in keys]
    assert all(v is not None and v[0] == k for k, v in zip(keys, values))
    assert cache.nbytes == sum(len(v[1]) for v in values) <= max_bytes
