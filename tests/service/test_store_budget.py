"""The scene store's byte budget, free-space margin, eviction order, stored precision and crash leftovers."""

from __future__ import annotations

import os
import re
import shutil
from collections import namedtuple

import numpy as np
import pytest

from rasterizer.gaussians import Gaussians
from service.store import STORED_RENDER_TOLERANCE, SceneStore, StoreFull, content_id, stored_form


def _gaussians(n: int, seed: int = 0, sh_degree: int = 1) -> Gaussians:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    return Gaussians(rng.normal(size=(n, 3)), rng.uniform(0.01, 0.1, (n, 3)), q / np.linalg.norm(q, axis=1, keepdims=True),
                     rng.uniform(0, 1, n), rng.normal(size=(n, (sh_degree + 1) ** 2, 3)))


def _scene_bytes(store: SceneStore, sid: str) -> int:
    folder = store.scenes_dir / sid
    return sum(p.stat().st_size for p in folder.iterdir())


def _bytes_of_one(tmp_path, g) -> int:
    """What a scene of ``g`` takes in a store (written to a probe store beside the test's)."""
    probe = SceneStore(tmp_path / "probe")
    probe.put(content_id("probe"), g, {})
    return _scene_bytes(probe, content_id("probe"))


def _filled_store(tmp_path, budget_scenes: float, tag: str, count: int) -> tuple[SceneStore, list[str]]:
    """A store whose budget holds ``budget_scenes`` scenes of 2000 Gaussians, with ``count`` of them written."""
    store = SceneStore(tmp_path / "s", budget_bytes=int(budget_scenes * _bytes_of_one(tmp_path, _gaussians(2000))),
                       min_free_bytes=0)
    ids = [content_id(tag, str(i)) for i in range(count)]
    for i, sid in enumerate(ids):
        store.put(sid, _gaussians(2000, i), {})
    return store, ids


def test_stored_scene_takes_float16_where_precision_allows(tmp_path):
    store = SceneStore(tmp_path)
    g = _gaussians(10_000)
    sid = content_id("size")
    store.put(sid, g, {})
    per_gaussian = (store.scenes_dir / sid / "gaussians.npz").stat().st_size / len(g)
    assert per_gaussian < 12 + 12 + 8 + 2 + 24 + 1  # 92 bytes in float32
    back = SceneStore(tmp_path).gaussians(sid)
    assert back.means.dtype == np.float32 and np.array_equal(back.means, g.means)  # positions exact
    assert np.array_equal(back.scales, g.scales)
    assert np.abs(back.sh - g.sh).max() <= 2.0 ** -11 * np.abs(g.sh).max()


def test_renders_of_a_stored_scene_stay_within_the_stated_tolerance():
    from rasterizer.render import render

    rng = np.random.default_rng(3)
    n = 20_000
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    q = rng.normal(size=(n, 4))
    g = Gaussians(d * rng.uniform(2.0, 4.0, (n, 1)), rng.uniform(0.02, 0.12, (n, 3)),
                  q / np.linalg.norm(q, axis=1, keepdims=True), rng.uniform(0.05, 1.0, n),
                  rng.normal(0.0, 0.6, (n, 4, 3)))
    for pose in (np.eye(4), np.array([[0, 0, 1, 0.3], [0, 1, 0, -0.2], [-1, 0, 0, 0.1], [0, 0, 0, 1.0]])):
        a = render(g, pose, width=256).colour
        b = render(stored_form(g), pose, width=256).colour
        assert np.abs(a - b).max() <= STORED_RENDER_TOLERANCE


def test_budget_evicts_least_recently_used_scenes_no_job_holds(tmp_path):
    store, ids = _filled_store(tmp_path, 3.5, "lru", 3)
    store.gaussians(ids[0])  # used: now the most recent
    with store.hold(ids[1]):  # a job reads it: never evicted meanwhile
        store.put(content_id("lru", "3"), _gaussians(2000, 3), {})
        assert set(store.ids()) == {ids[0], ids[1], content_id("lru", "3")}
        assert store.usage() <= store.budget_bytes and store.evictions == 1
        store.put(content_id("lru", "4"), _gaussians(2000, 4), {})
        assert ids[1] in store.ids() and ids[0] not in store.ids()
    for k in range(5, 12):  # a flood never passes the budget
        store.put(content_id("lru", str(k)), _gaussians(2000, k), {})
        assert store.usage() <= store.budget_bytes
    assert len(store.ids()) == 3


def test_write_that_cannot_fit_is_refused_and_leaves_nothing(tmp_path):
    store = SceneStore(tmp_path, budget_bytes=10_000, min_free_bytes=0)
    with pytest.raises(StoreFull) as info:
        store.put(content_id("big"), _gaussians(5000), {})
    assert "budget" in str(info.value) and info.value.code == "store_full"
    assert store.ids() == [] and list(store.tmp_dir.iterdir()) == [] and store.refusals == 1
    small = content_id("small")
    store.put(small, _gaussians(10), {})
    with store.hold(small), pytest.raises(StoreFull):  # the only scene is held: no room to make
        store.put(content_id("big2"), _gaussians(200), {})
    assert store.ids() == [small]


def test_every_write_keeps_the_free_space_margin(tmp_path, monkeypatch):
    store = SceneStore(tmp_path, min_free_bytes=1 << 30)
    sid = content_id("margin")
    Usage = namedtuple("Usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: Usage(1 << 40, 1 << 39, (1 << 30) + 4096))
    store.put(sid, _gaussians(10), {})  # fits in the 4096 bytes above the margin
    with pytest.raises(StoreFull, match="margin"):
        store.put(content_id("margin2"), _gaussians(1000), {})
    with pytest.raises(StoreFull, match="margin"):
        store.put_artifact(sid, "selection-x.npz", b"x" * 10_000)
    assert store.ids() == [sid] and store.artifact(sid, "selection-x.npz") is None


def test_artifact_writes_count_against_the_budget(tmp_path):
    store = SceneStore(tmp_path, budget_bytes=0, min_free_bytes=0)
    a, b = content_id("a"), content_id("b")
    store.put(a, _gaussians(100), {})
    store.put(b, _gaussians(100), {})
    store.budget_bytes = store.usage() + 1000
    store.gaussians(b)
    store.put_artifact(b, "selection-1.npz", b"x" * 5000)  # evicts a, never b itself
    assert store.ids() == [b] and store.usage() <= store.budget_bytes


def test_start_up_removes_interrupted_artifact_writes(tmp_path):
    store = SceneStore(tmp_path)
    sid = content_id("crash")
    store.put(sid, _gaussians(10), {})
    leftover = store.scenes_dir / sid / ".gaussians.ply.0123abcd.tmp"
    leftover.write_bytes(b"half a file")
    os.utime(leftover, (0, 0))  # older than any grace: a crash's, not a live writer's
    SceneStore(tmp_path)
    assert not leftover.exists() and SceneStore(tmp_path).exists(sid)


def test_eviction_survives_a_delete_between_listing_and_sorting(tmp_path, monkeypatch):
    store = SceneStore(tmp_path, max_scenes=2, budget_bytes=0)
    ids = [content_id("race", str(i)) for i in range(2)]
    for sid in ids:
        store.put(sid, _gaussians(5), {})
    store = SceneStore(tmp_path, max_scenes=2, budget_bytes=0)  # a restart: order from the folders' mtimes
    listed = store.ids()
    shutil.rmtree(store.scenes_dir / ids[0])  # another process deletes it after the listing
    monkeypatch.setattr(store, "ids", lambda: listed)
    store.put(content_id("race", "2"), _gaussians(5), {})
    assert os.path.isdir(store.scenes_dir / content_id("race", "2"))


def test_store_from_settings_takes_the_budget_and_the_margin(tmp_path, monkeypatch):
    from service.config import Settings

    monkeypatch.setenv("OMNISPLAT_STORE_BUDGET_BYTES", "123456789")
    settings = Settings(model_path=tmp_path / "m.onnx", store_dir=tmp_path / "s", min_free_store_bytes=4096)
    store = SceneStore.from_settings(settings)
    assert (store.budget_bytes, store.min_free_bytes, store.root) == (123456789, 4096, tmp_path / "s")
    assert Settings(model_path=tmp_path / "m.onnx").store_budget_bytes == 123456789


def test_the_service_builds_its_store_from_the_settings(tmp_path, model_path):
    """The running app enforces the configured budget and margin, not the store's defaults."""
    from fastapi.testclient import TestClient

    from service.app import create_app
    from tests.service._support import make_settings

    settings = make_settings(model_path, tmp_path / "s", store_budget_bytes=987654321, min_free_store_bytes=8192,
                             warmup=False)
    with TestClient(create_app(settings)) as client:
        store = client.app.state.store
        assert (store.budget_bytes, store.min_free_bytes) == (987654321, 8192)


def test_a_write_that_cannot_fit_evicts_nothing(tmp_path):
    """Decide first, evict after: a scene bigger than the whole budget, or one that does not fit beside the held
    scenes, is refused with every stored scene still there."""
    store, kept = _filled_store(tmp_path, 2.5, "keep", 2)
    with pytest.raises(StoreFull) as info:
        store.put(content_id("huge"), _gaussians(6000, 9), {})
    assert store.ids() == sorted(kept) and store.evictions == 0
    assert re.search(r"the new scene alone takes \d+ bytes, more than the scene store's whole budget .*no scene was "
                     "evicted", str(info.value))
    with store.hold(kept[0]), pytest.raises(StoreFull, match=r"beside the \d+ bytes of 1 scenes that jobs") as info:
        store.put(content_id("big"), _gaussians(3600, 8), {})  # fits the budget, not beside the held scene
    assert "alone" not in str(info.value)
    assert store.ids() == sorted(kept) and store.evictions == 0 and store.refusals == 2
    store.put(content_id("fits"), _gaussians(2000, 7), {})  # one eviction makes room: still done
    assert store.evictions == 1 and len(store.ids()) == 2
    store.budget_bytes, store.max_scenes = 0, 2
    with store.hold(*store.ids()), pytest.raises(StoreFull, match="keeps at most 2 scenes and jobs .* are using 2"):
        store.put(content_id("count"), _gaussians(10), {})
    assert len(store.ids()) == 2 and store.evictions == 1
