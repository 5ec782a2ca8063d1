"""Scene store against damage on disk and races: what a damaged scene folder reads as, and what a write over it does."""

from __future__ import annotations

import json
import shutil

import pytest

from service.store import SceneStore, StoreCorrupt, content_id, stored_form

from ._support import random_gaussians, same_gaussians


def test_a_scene_folder_without_its_metadata_is_replaced_by_the_next_write_of_that_scene(tmp_path):
    """A folder whose meta.json was lost is no scene (404); writing the scene again stores it whole in its place
    instead of failing on the folder in the way."""
    store = SceneStore(tmp_path, min_free_bytes=0)
    sid, g = content_id("meta lost"), random_gaussians(20)
    store.put(sid, g, {}, artifacts={"extra.bin": b"x"})
    (tmp_path / "scenes" / sid / "meta.json").unlink()
    restarted = SceneStore(tmp_path, min_free_bytes=0, cache_scenes=0)
    assert not restarted.exists(sid)
    meta = restarted.put(sid, g, {"note": "again"}, artifacts={"references.npz": b"r"})
    assert meta["id"] == sid and restarted.meta(sid)["note"] == "again"
    assert same_gaussians(restarted.gaussians(sid), stored_form(g))
    assert sorted(p.name for p in (tmp_path / "scenes" / sid).iterdir()) == ["gaussians.npz", "meta.json",
                                                                            "references.npz"]
    assert list((tmp_path / "tmp").iterdir()) == [] and list((tmp_path / "trash").iterdir()) == []


def test_files_of_another_scene_swapped_in_are_reported_not_served(tmp_path):
    """A meta.json or gaussians.npz copied over from another scene (or JSON that is no metadata) reads as a damaged
    scene (StoreCorrupt), never as that other scene's content under this id."""
    store = SceneStore(tmp_path, min_free_bytes=0)
    one, other = content_id("one"), content_id("other")
    store.put(one, random_gaussians(30), {})
    store.put(other, random_gaussians(40, 1), {})
    folder, source = tmp_path / "scenes" / one, tmp_path / "scenes" / other
    shutil.copy(source / "gaussians.npz", folder / "gaussians.npz")
    with pytest.raises(StoreCorrupt, match="40 Gaussians"):
        SceneStore(tmp_path, min_free_bytes=0).gaussians(one)
    for text in ((source / "meta.json").read_text(), "[1, 2]", '"text"',
                 json.dumps({"id": one, "num_gaussians": "30"})):
        (folder / "meta.json").write_text(text)
        with pytest.raises(StoreCorrupt, match="not this scene's metadata"):
            SceneStore(tmp_path, min_free_bytes=0).meta(one)


def test_a_second_writer_of_one_scene_evicts_nothing(tmp_path, monkeypatch):
    """Two writers of one id at once (the same content POSTed twice): the one that finds the scene stored once its
    own copy is staged drops its copy without evicting a scene to make room for it."""
    import service.store as store_module

    store = SceneStore(tmp_path, min_free_bytes=0, max_scenes=2)
    old, sid, g = content_id("old"), content_id("twice"), random_gaussians(10)
    store.put(old, random_gaussians(10, 1), {})
    write = store_module._write_file
    other_writer: list[dict] = []

    def write_racing(path, writer):  # the other writer renames its copy in while this one stages
        if not other_writer:
            other_writer.append({})
            other_writer[0] = store.put(sid, g, {})
        write(path, writer)

    monkeypatch.setattr(store_module, "_write_file", write_racing)
    assert store.put(sid, g, {})["id"] == sid and other_writer[0]["id"] == sid
    assert store.ids() == sorted([old, sid]) and store.evictions == 0
    assert list((tmp_path / "tmp").iterdir()) == []


def test_delete_works_when_the_trash_folder_was_removed(tmp_path):
    """trash/ removed while the server runs (a clean-up by hand): a DELETE still removes the scene, never answers
    'not found' for a scene that stays."""
    store = SceneStore(tmp_path, min_free_bytes=0)
    sid = content_id("deleted")
    store.put(sid, random_gaussians(5), {})
    shutil.rmtree(tmp_path / "trash")
    assert store.delete(sid) and not store.exists(sid) and not (tmp_path / "scenes" / sid).exists()
    assert not store.delete(sid)


def test_a_folder_not_named_by_an_id_is_no_scene_for_the_budget(tmp_path):
    """A copy of a scene folder made by hand under scenes/ (``<id>.bak``) is not counted as a scene, so it neither
    displaces real scenes nor, chosen for eviction, fails every later write with 'malformed scene id'."""
    store = SceneStore(tmp_path, min_free_bytes=0, max_scenes=2)
    first = content_id("first")
    store.put(first, random_gaussians(10), {})
    shutil.copytree(tmp_path / "scenes" / first, tmp_path / "scenes" / f"{first}.bak")
    store = SceneStore(tmp_path, min_free_bytes=0, max_scenes=2)
    assert store.ids() == [first]
    later = [content_id(f"later {k}") for k in range(2)]
    for k, sid in enumerate(later):
        store.put(sid, random_gaussians(10, k + 1), {})
    assert store.ids() == sorted(later) and (tmp_path / "scenes" / f"{first}.bak" / "meta.json").is_file()


@pytest.mark.parametrize("damage", ["truncated", "foreign meta"])
def test_a_post_of_a_damaged_scene_builds_it_again_instead_of_answering_cached(tmp_path, damage):
    """POST's check for a stored scene (service.scenes.stored_whole) reads its metadata and Gaussians: a damaged scene
    (a truncated array file, another scene's metadata) is removed and reported as not stored, so the POST builds it
    again; a whole one is answered from the store."""
    from service.scenes import stored_whole

    store = SceneStore(tmp_path, min_free_bytes=0)
    sid, other = content_id("damaged"), content_id("other")
    store.put(sid, random_gaussians(30), {})
    store.put(other, random_gaussians(40, 1), {})
    restarted = SceneStore(tmp_path, min_free_bytes=0, cache_scenes=0)
    assert stored_whole(restarted, sid)["num_gaussians"] == 30 and stored_whole(restarted, content_id("none")) is None
    folder = tmp_path / "scenes" / sid
    if damage == "truncated":
        data = (folder / "gaussians.npz").read_bytes()
        (folder / "gaussians.npz").write_bytes(data[: len(data) // 2])
    else:
        shutil.copy(tmp_path / "scenes" / other / "meta.json", folder / "meta.json")
    restarted = SceneStore(tmp_path, min_free_bytes=0, cache_scenes=0)
    assert stored_whole(restarted, sid) is None
    assert not restarted.exists(sid) and restarted.exists(other)
    restarted.put(sid, random_gaussians(30), {})
    assert stored_whole(restarted, sid)["num_gaussians"] == 30
