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
