"""Memory goes back to the system after big requests (service.memory), measured in a fresh process."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
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


def test_large_uint8_input_reaches_the_graph_as_when_resampled_in_float(model_path):
    """A panorama at 4x the model's size, sent as uint8 (resampled in row blocks, scaled after), feeds the
    graph the image that converting to float at full size and resampling gives (the whole-image path).

    The graph's inputs are compared: the small test model's untrained weights turn a 1-ulp change of its
    inputs into visible changes of its outputs, so its Gaussians cannot show float-rounding equality."""
    from rasterizer.yin_yang import resize_erp
    from service.encoder import OnnxEncoder

    enc = OnnxEncoder(model_path)
    fed = []
    session = enc.session

    class Spy:  # the session, recording the images it is fed
        def __getattr__(self, name):
            return getattr(session, name)

        def run(self, names, feeds, *args):
            fed.append((feeds["erp_a"].copy(), feeds["erp_b"].copy()))
            return session.run(names, feeds, *args)

    enc.session = Spy()
    rng = np.random.default_rng(3)
    h = 4 * enc.height
    yy, xx = np.mgrid[0:h, 0:2 * h] / h
    base = np.stack([np.sin(5 * xx + yy), np.cos(3 * yy - 2 * xx), np.sin(7 * xx * yy)], -1)
    img_a = np.clip(127.5 + 100 * base + rng.normal(0, 20, base.shape), 0, 255).astype(np.uint8)
    img_b = np.roll(img_a, 16, axis=1)
    keep = img_a.copy()
    a, b = np.eye(4), np.eye(4)
    b[0, 3] = 0.5
    big = enc.reconstruct(img_a, img_b, a, b)
    assert np.array_equal(img_a, keep)  # the caller's array is untouched
    small = [resize_erp(im.astype(np.float32) / np.float32(255.0), enc.height, enc.width) for im in (img_a, img_b)]
    ref = enc.reconstruct(*small, a, b)
    assert len(big.gaussians) == len(ref.gaussians)
    (got_a, got_b), (want_a, want_b) = fed
    assert got_a.shape == (1, 3, enc.height, enc.width) and got_a.dtype == np.float32
    assert np.abs(got_a - want_a).max() < 1e-6 and np.abs(got_b - want_b).max() < 1e-6
