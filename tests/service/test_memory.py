"""Memory goes back to the system after big requests (service.memory), measured in a fresh process."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

CHILD = r"""
import json, threading
import numpy as np
from service import memory

def rss():
    with open("/proc/self/status") as f:
        return next(int(l.split()[1]) * 1024 for l in f if l.startswith("VmRSS"))

memory.release_memory(force=True)  # the first call configures the allocator
keep = []
def work():  # a request in a worker thread: 1 MB arrays (below the mmap threshold), one survivor on top
    arrays = [np.ones(1 << 17) for _ in range(300)]
    keep.append(np.ones(1 << 17))
    del arrays
t = threading.Thread(target=work); t.start(); t.join()
before = rss()
ran = memory.release_memory(force=True)
print(json.dumps({"before": before, "after": rss(), "ran": ran}))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="malloc_trim is glibc's")
def test_release_memory_returns_freed_heap_pages():
    out = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True, check=True)
    res = json.loads(out.stdout.strip().splitlines()[-1])
    assert res["ran"] is True
    assert res["before"] - res["after"] > 150 << 20, res  # most of the 300 MB freed in the worker
