"""Regression tests of the request audit: what a clumsy client sends that a route would otherwise read
silently in another way than meant (extra or repeated fields, image files a viewer shows otherwise)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.service._support import IDENTITY, POSES, LiveServer, make_settings, new_scene, panorama, stored_scene_count

MOVED = ",".join(str(v) for v in np.array([[1, 0, 0, 0.2], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]).ravel())


@pytest.fixture(scope="module")
def live(model_path, tmp_path_factory):
    with LiveServer(make_settings(model_path, tmp_path_factory.mktemp("store"), max_render_width=512,
                                  max_render_pixels=512 * 256)) as server:
        yield server


@pytest.fixture(scope="module")
def client(live):
    with live.client() as c:
        yield c


@pytest.fixture(scope="module")
def scene(client) -> str:
    return new_scene(client, seed=61, shift=4)


@pytest.mark.parametrize("field", ["option", "Options", "pose", "image_c"])
def test_unknown_form_field_is_422_naming_it_and_nothing_is_stored(client, live, field):
    before = stored_scene_count(live.settings.store_dir)
    r = client.post("/v1/scenes", files={"image_a": ("a.png", panorama(seed=62)), "image_b": ("b.png", panorama(seed=63))},
                    data={"poses": POSES, field: '{"sh_degree": 0}'})
    assert r.status_code == 422, r.text
    err = r.json()["error"]
    assert err["code"] == "unknown_form_field" and field in err["message"] and "options" in err["message"]
    assert stored_scene_count(live.settings.store_dir) == before


@pytest.mark.parametrize("path, params, again", [
    ("render", [("c2w", IDENTITY), ("width", "64")], ("c2w", MOVED)),
    ("render", [("c2w", IDENTITY), ("width", "64")], ("width", "128")),
    ("render", [("c2w", IDENTITY), ("width", "64"), ("format", "png")], ("format", "jpeg")),
    ("segments", [("view", "a"), ("width", "64")], ("view", "b")),
])
def test_a_query_parameter_given_twice_is_400_naming_it(client, scene, path, params, again):
    """The route would keep one of the two values without a word (the last one)."""
    assert client.get(f"/v1/scenes/{scene}/{path}", params=params).status_code == 200
    r = client.get(f"/v1/scenes/{scene}/{path}", params=params + [again])
    assert r.status_code == 400, r.text
    err = r.json()["error"]
    assert err["code"] == "duplicate_query_parameter" and repr(again[0]) in err["message"]

