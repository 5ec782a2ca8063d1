"""Edits and refinements against a changing store: empty results, deletions mid-run (service.edits, service.jobs)."""

from __future__ import annotations

import numpy as np
import pytest

from service.store import SceneStore
from tests.service.test_service_api import LiveServer, make_settings, model_path, panorama, post_scene  # noqa: F401


@pytest.fixture(scope="module")
def live(model_path, tmp_path_factory):  # noqa: F811  (model_path is the imported fixture)
    store = tmp_path_factory.mktemp("store-edits")
    with LiveServer(make_settings(model_path, store, max_render_width=512, max_render_pixels=512 * 256)) as server:
        server.store = store
        yield server


@pytest.fixture(scope="module")
def client(live):
    with live.client() as c:
        yield c


def _scene(client, seed: int) -> str:
    r = post_scene(client, panorama(seed=seed), panorama(seed=seed, shift=7))
    assert r.status_code == 201, r.text
    return r.json()["id"]


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
