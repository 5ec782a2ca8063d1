"""Edits and refinements against a changing store: empty results, deletions mid-run (service.edits, service.jobs)."""

from __future__ import annotations

import numpy as np
import pytest

from service.store import SceneStore
from tests.service._support import edit_server, new_scene


@pytest.fixture(scope="module")
def live(model_path, tmp_path_factory):
    with edit_server(model_path, tmp_path_factory.mktemp("store-edits")) as server:
        yield server


def _scene(client, seed: int) -> str:
    return new_scene(client, seed, shift=7)


def _selection(client, scene_id: str) -> str:
    r = client.post(f"/v1/scenes/{scene_id}/selections", json={"view": "a", "points": [[0.5, 0.5]]})
    assert r.status_code == 201, r.text
    return r.json()["id"]


def _select_everything(store: SceneStore, scene_id: str, sel_id: str) -> None:
    """Overwrite a stored selection so that it holds every Gaussian of the scene."""
    import io

    path = store.artifact(scene_id, f"selection-{sel_id}.npz")
    with np.load(path) as z:
        saved = {k: z[k] for k in z.files}
    n = int(saved["count"])
    saved["gaussians"] = np.packbits(np.ones(n, dtype=bool))
    buf = io.BytesIO()
    np.savez_compressed(buf, **saved)
    store.put_artifact(scene_id, f"selection-{sel_id}.npz", buf.getvalue())


def test_edit_that_leaves_no_gaussian_is_422_and_not_stored(client, live):
    scene_id = _scene(client, 21)
    sel = _selection(client, scene_id)
    store = SceneStore(live.store)
    _select_everything(store, scene_id, sel)
    before = set(store.ids())
    r = client.post(f"/v1/scenes/{scene_id}/edits", json={"selection": sel, "op": "remove"})
    assert r.status_code == 422, r.text
    assert r.json()["error"]["code"] == "empty_scene"
    assert set(store.ids()) == before


def test_delete_while_an_edit_runs_is_404(client, live, monkeypatch):
    from rasterizer.edit import ops

    scene_id = _scene(client, 22)
    sel = _selection(client, scene_id)
    real = ops.edit_gaussians

    def delete_then_edit(*args, **kwargs):
        assert client.delete(f"/v1/scenes/{scene_id}").status_code == 204
        return real(*args, **kwargs)

    monkeypatch.setattr(ops, "edit_gaussians", delete_then_edit)
    r = client.post(f"/v1/scenes/{scene_id}/edits", json={"selection": sel, "op": "recolor", "color": [1, 0, 0]})
    assert r.status_code == 404, r.text
    assert r.json()["error"]["code"] == "scene_not_found"


def test_refine_whose_parent_is_deleted_mid_run_keeps_its_references(client, live, monkeypatch):
    import importlib
    import time

    refine_module = importlib.import_module("rasterizer.refine")

    scene_id = _scene(client, 23)
    real = refine_module.refine

    def delete_then_refine(*args, **kwargs):
        SceneStore(live.store).delete(scene_id)
        return real(*args, **kwargs)

    monkeypatch.setattr(refine_module, "refine", delete_then_refine)
    r = client.post(f"/v1/scenes/{scene_id}/refine", json={"iterations": 2, "height": 32})
    assert r.status_code == 202, r.text
    job = r.json()
    deadline = time.monotonic() + 120
    while job["status"] in ("queued", "running") and time.monotonic() < deadline:
        time.sleep(0.2)
        job = client.get(f"/v1/jobs/{job['id']}").json()
    assert job["status"] == "done", job
    assert client.get(f"/v1/scenes/{scene_id}").status_code == 404
    result = job["scene_id"]
    assert SceneStore(live.store).artifact(result, "references.npz") is not None
    again = client.post(f"/v1/scenes/{result}/refine", json={"iterations": 1, "height": 32})
    assert again.status_code == 202, again.text


def test_edit_flood_stays_within_the_store_budget_and_metrics_show_it(client, live):
    store = live.app.state.store
    scene_id = _scene(client, 24)
    sel = _selection(client, scene_id)
    one = store.usage() // max(1, len(store.ids()))
    saved = store.budget_bytes
    store.budget_bytes = store.usage() + 2 * one
    try:
        statuses = []
        for k in range(6):
            r = client.post(f"/v1/scenes/{scene_id}/edits",
                            json={"selection": sel, "op": "recolor", "color": [k / 6, 0.5, 0.5]})
            statuses.append(r.status_code)
            assert r.status_code in (201, 507), r.text
            if r.status_code == 507:
                assert r.json()["error"]["code"] == "store_full"
            assert store.usage() <= store.budget_bytes
        assert statuses.count(201) >= 2 and store.exists(scene_id)  # the edited scene is held, never evicted
        values = {line.split()[0]: float(line.split()[1]) for line in client.get("/metrics").text.splitlines()
                  if line.startswith("omnisplat_store")}
        assert values["omnisplat_store_budget_bytes"] == store.budget_bytes
        assert 0 < values["omnisplat_store_bytes"] <= store.budget_bytes
        assert values["omnisplat_store_evictions"] == store.evictions > 0
    finally:
        store.budget_bytes = saved


def test_selection_below_the_free_space_margin_is_507(client, live, monkeypatch):
    import shutil
    from collections import namedtuple

    scene_id = _scene(client, 25)
    store = live.app.state.store
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(1 << 40, 1 << 39, store.min_free_bytes + 10))
    r = client.post(f"/v1/scenes/{scene_id}/selections", json={"view": "a", "points": [[0.4, 0.5]]})
    assert r.status_code == 507, r.text
    assert r.json()["error"]["code"] == "store_full" and "margin" in r.json()["error"]["message"]


def test_ply_is_streamed_from_the_stored_arrays_without_a_copy_on_disk(client, live):
    from rasterizer.ply import ply_bytes

    scene_id = _scene(client, 21)
    r = client.get(f"/v1/scenes/{scene_id}/gaussians.ply")
    assert r.status_code == 200 and int(r.headers["content-length"]) == len(r.content)
    assert r.content == ply_bytes(SceneStore(live.store).gaussians(scene_id))
    assert sorted(p.name for p in (live.store / "scenes" / scene_id).iterdir() if p.name.endswith(".ply")) == []


def test_job_status_of_an_edited_scene_is_404_not_an_invented_refine_job(client, live):
    scene_id = _scene(client, 26)
    sel = _selection(client, scene_id)
    r = client.post(f"/v1/scenes/{scene_id}/edits", json={"selection": sel, "op": "recolor", "color": [0, 1, 0]})
    assert r.status_code == 201, r.text
    edited = r.json()["id"]
    job = client.get(f"/v1/jobs/{edited}")
    assert job.status_code == 404 and job.json()["error"]["code"] == "job_not_found"
