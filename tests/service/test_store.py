"""Scene store: atomic writes, restart survival, LRU bounds, content ids, id validation."""

from __future__ import annotations

import json
import os
import shutil
import threading
import time

import numpy as np
import pytest

from service.errors import BadInput, translate
from service.store import (
    InvalidSceneId,
    SceneNotFound,
    SceneStore,
    StoreCorrupt,
    StoreInterrupted,
    content_id,
    json_safe,
    stored_form,
)

from ._support import random_gaussians, same_gaussians


def test_content_id_is_stable_and_part_boundaries_matter():
    assert content_id("a", b"bc") == content_id("a", b"bc")
    assert content_id("ab", "c") != content_id("a", "bc")
    assert len(content_id("x")) == 32 and all(c in "0123456789abcdef" for c in content_id("x"))


def test_scene_ids_follow_the_inputs_and_the_code_that_builds_them(monkeypatch, tmp_path):
    """A store written by other code (another pose estimator, decoding or colour fit) must not answer an
    upload with the scene that code built: the id hashes the rasterizer's and the service's sources."""
    from service import model_files, scenes

    args = ("model-sha", b"image a", b"image b", None, {"near": 0.5})
    first = scenes.scene_id_for(*args)
    assert first == scenes.scene_id_for(*args)
    assert first != scenes.scene_id_for("model-sha", b"image a", b"image B", None, {"near": 0.5})
    monkeypatch.setattr(scenes, "build_code_hash", lambda: "0123456789")
    assert scenes.scene_id_for(*args) != first

    code = tmp_path / "rasterizer"
    code.mkdir()
    (code / "step.py").write_text("X = 1\n")
    monkeypatch.setattr(model_files, "REPO_ROOT", tmp_path)
    model_files.build_code_hash.cache_clear()
    try:
        before = model_files.build_code_hash()
        (code / "step.py").write_text("X = 2\n")
        model_files.build_code_hash.cache_clear()
        assert model_files.build_code_hash() != before
    finally:
        model_files.build_code_hash.cache_clear()


def test_put_get_and_restart(tmp_path):
    store = SceneStore(tmp_path)
    g = random_gaussians(100)
    sid = content_id("scene", "1")
    meta = store.put(sid, g, {"options": {"near": 1.0}, "value": np.float32(2.5)})
    assert meta["num_gaussians"] == 100 and meta["value"] == 2.5
    assert store.exists(sid) and store.ids() == [sid]
    # a fresh store over the same folder (a restart) sees the scene, byte for byte what the cache held
    again = SceneStore(tmp_path)
    assert again.exists(sid)
    assert same_gaussians(again.gaussians(sid), stored_form(g)) and same_gaussians(store.gaussians(sid), stored_form(g))
    assert again.meta(sid)["options"] == {"near": 1.0}


def test_put_same_id_twice_keeps_first(tmp_path):
    store = SceneStore(tmp_path)
    sid = content_id("dup")
    store.put(sid, random_gaussians(10, 1), {"tag": "first"})
    meta = store.put(sid, random_gaussians(10, 2), {"tag": "second"})
    assert meta["tag"] == "first"
    assert same_gaussians(SceneStore(tmp_path).gaussians(sid), stored_form(random_gaussians(10, 1)))


def test_concurrent_writers_of_one_id(tmp_path):
    store = SceneStore(tmp_path)
    sid = content_id("race")
    errors = []

    def write():
        try:
            store.put(sid, random_gaussians(5000), {"x": 1})
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=write) for _ in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    assert store.ids() == [sid]
    assert list((tmp_path / "tmp").iterdir()) == []


def test_crash_leftovers_are_invisible_and_cleaned(tmp_path):
    store = SceneStore(tmp_path)
    sid = content_id("half")
    # simulate a crash after writing the arrays but before the rename
    staging = tmp_path / "tmp" / f"{sid}-deadbeef"
    staging.mkdir()
    (staging / "gaussians.npz").write_bytes(b"partial")
    os.utime(staging, (0, 0))  # the crash was longer ago than the grace
    assert not store.exists(sid)
    SceneStore(tmp_path)  # restart
    assert not staging.exists()
    assert not store.exists(sid)


def test_delete(tmp_path):
    store = SceneStore(tmp_path)
    sid = content_id("del")
    store.put(sid, random_gaussians(3), {})
    assert store.delete(sid) is True
    assert not store.exists(sid)
    assert store.delete(sid) is False
    with pytest.raises(SceneNotFound):
        store.gaussians(sid)
    with pytest.raises(SceneNotFound):
        store.meta(sid)


@pytest.mark.parametrize("bad", ["../../etc", "..", "ABCDEF0123456789ABCDEF0123456789", "x" * 32, "", "a/b",
                                 "0123456789abcdef0123456789abcde", "0123456789abcdef0123456789abcdef0"])
def test_malformed_ids_are_refused(tmp_path, bad):
    store = SceneStore(tmp_path)
    with pytest.raises(InvalidSceneId):
        store.exists(bad)
    with pytest.raises(InvalidSceneId):
        store.gaussians(bad)
    assert isinstance(translate(InvalidSceneId(bad)), BadInput)  # 422 over HTTP


def test_lru_bounds(tmp_path):
    g = random_gaussians(1000)
    nbytes = sum(getattr(g, f).nbytes for f in ("means", "scales", "quats", "opacities", "sh"))
    store = SceneStore(tmp_path, cache_scenes=2, cache_bytes=10 * nbytes)
    ids = [content_id("lru", str(i)) for i in range(4)]
    for sid in ids:
        store.put(sid, g, {})
    assert len(store.cache) == 2
    store2 = SceneStore(tmp_path, cache_scenes=10, cache_bytes=int(1.5 * nbytes))
    for sid in ids:
        store2.gaussians(sid)
    assert len(store2.cache) == 1 and store2.cache.nbytes == nbytes
    store3 = SceneStore(tmp_path, cache_scenes=0)
    store3.gaussians(ids[0])
    assert len(store3.cache) == 0


def test_max_scenes_evicts_oldest(tmp_path):
    store = SceneStore(tmp_path, max_scenes=2)
    ids = [content_id("evict", str(i)) for i in range(3)]
    for i, sid in enumerate(ids):
        store.put(sid, random_gaussians(5), {})
        os.utime(tmp_path / "scenes" / sid, (1000 + i, 1000 + i))
    store.put(content_id("evict", "3"), random_gaussians(5), {})
    assert set(store.ids()) == {ids[2], content_id("evict", "3")}


def test_corrupt_file_is_reported(tmp_path):
    store = SceneStore(tmp_path, cache_scenes=0)
    sid = content_id("corrupt")
    store.put(sid, random_gaussians(5), {})
    (tmp_path / "scenes" / sid / "gaussians.npz").write_bytes(b"garbage")
    with pytest.raises(StoreCorrupt):
        store.gaussians(sid)


def test_artifact_is_atomic_and_scoped(tmp_path):
    store = SceneStore(tmp_path)
    sid = content_id("art")
    store.put(sid, random_gaussians(5), {})
    path = store.put_artifact(sid, "gaussians.ply", b"ply\n")
    assert path.read_bytes() == b"ply\n" and store.artifact(sid, "gaussians.ply") == path
    assert [p.name for p in path.parent.iterdir() if p.name.endswith(".tmp")] == []
    with pytest.raises(SceneNotFound):
        store.put_artifact(content_id("missing"), "x", b"")


def test_json_safe():
    out = json_safe({"a": np.float32(1.5), "b": np.arange(3), "c": float("nan"), "d": (1, np.int64(2))})
    assert json.loads(json.dumps(out)) == {"a": 1.5, "b": [0, 1, 2], "c": None, "d": [1, 2]}


def test_failed_write_leaves_nothing(tmp_path, monkeypatch):
    store = SceneStore(tmp_path)
    sid = content_id("crash")

    def boom(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez", boom)
    with pytest.raises(OSError):
        store.put(sid, random_gaussians(5), {})
    assert not store.exists(sid)
    assert list((tmp_path / "tmp").iterdir()) == [] and list((tmp_path / "scenes").iterdir()) == []


def test_start_up_keeps_young_unfinished_writes_by_default(tmp_path):
    """Another process sharing the store (a second server on one volume, the CLI) may be writing into tmp/, trash/
    or an artifact .tmp: a start-up removes only leftovers older than the grace; 0 removes all of them."""
    SceneStore(tmp_path)
    sid = content_id("young")
    SceneStore(tmp_path).put(sid, random_gaussians(5), {})
    young, old = tmp_path / "tmp" / "young", tmp_path / "tmp" / "old"
    young.mkdir()
    old.mkdir()
    trash = tmp_path / "trash" / "young"
    trash.mkdir()
    artifact = tmp_path / "scenes" / sid / ".gaussians.ply.0123abcd.tmp"
    artifact.write_bytes(b"half")
    os.utime(old, (time.time() - 3600, time.time() - 3600))
    SceneStore(tmp_path)
    assert young.exists() and trash.exists() and artifact.exists() and not old.exists()
    SceneStore(tmp_path, clean_up=False, tmp_grace_s=0)  # a client of a server's store clears nothing
    assert young.exists() and trash.exists() and artifact.exists()
    SceneStore(tmp_path, tmp_grace_s=0)  # a store no other process uses: everything left is a crash's leftover
    assert not young.exists() and not trash.exists() and not artifact.exists()


def test_put_writes_again_when_its_staging_folder_vanishes(tmp_path, monkeypatch):
    """Another process clearing tmp/ under a write: the write is staged again, never a FileNotFoundError; when it
    keeps happening, a StoreInterrupted (retryable) and nothing stored."""
    store = SceneStore(tmp_path)
    real = np.savez
    cleared = []

    def clear_tmp_while_writing(f, **arrays):
        if len(cleared) < budget:
            cleared.append(f.name)
            shutil.rmtree(store.tmp_dir)  # the whole tmp/, as a start-up cleanup of another process does
        real(f, **arrays)

    monkeypatch.setattr(np, "savez", clear_tmp_while_writing)
    budget = 1
    sid = content_id("vanish")
    store.put(sid, random_gaussians(5), {"x": 1}, artifacts={"references.npz": b"refs"})
    assert store.exists(sid) and store.artifact(sid, "references.npz").read_bytes() == b"refs" and len(cleared) == 1
    budget = 100
    with pytest.raises(StoreInterrupted, match="send it again"):
        store.put(content_id("vanish", "2"), random_gaussians(5), {})
    assert store.ids() == [sid] and list(store.tmp_dir.glob("*")) == []


def test_an_interrupted_write_is_a_retryable_503():
    """The API's answer to a write whose staging folder kept vanishing: 503 with Retry-After, not a 500."""
    from service.errors import translate

    mapped = translate(StoreInterrupted("the write was interrupted; send it again"))
    assert mapped.status == 503 and mapped.code == "store_interrupted" and mapped.headers["Retry-After"] == "1"


def test_a_store_limit_is_a_507_naming_it_wherever_it_is_raised():
    """The CLI's edit, which writes outside the API's handlers, said 'the scene store's disk is full' for a
    scene-count cap: a StoreFull is an ENOSPC OSError and was taken for a full disk."""
    from service.errors import translate
    from service.store import StoreFull

    mapped = translate(StoreFull("the scene store keeps at most 1 scenes"))
    assert mapped.status == 507 and mapped.code == "store_full" and mapped.message.startswith("the scene store keeps")
