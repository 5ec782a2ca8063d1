"""Selections, segments and edits over HTTP (small model, m3d references resized to 128 x 256)."""

import io
import json

import numpy as np
import pytest
from PIL import Image

from rasterizer.scene_folder import load_scene
from tests.service._support import edit_server, post_scene

IDENTITY = ",".join(str(float(x)) for x in np.eye(4).ravel())


def _png(img, step: int = 4) -> bytes:
    buf = io.BytesIO()
    Image.fromarray((np.asarray(img)[::step, ::step] * 255).astype(np.uint8)).save(buf, format="PNG")
    return buf.getvalue()


@pytest.fixture(scope="module")
def live(model_path, tmp_path_factory):
    with edit_server(model_path, tmp_path_factory.mktemp("edit-store")) as server:
        yield server


@pytest.fixture(scope="module")
def scene(client, m3d_dir):
    s = load_scene(m3d_dir)
    fa, fb = s.frames["00"], s.frames["02"]
    poses = json.dumps({"convention": "opencv", "c2w": [fa.c2w.tolist(), fb.c2w.tolist()]})
    r = post_scene(client, _png(fa.image()), _png(fb.image()), poses=poses)
    assert r.status_code == 201, r.text
    return r.json()["id"]


def _error(r, status, code):
    assert r.status_code == status, r.text
    assert r.json()["error"]["code"] == code, r.text
    return r.json()["error"]["message"]


def test_select_mask_segments_and_edits(client, scene, live):
    body = {"view": "a", "points": [[0.95, 0.5]], "negative": []}
    r = client.post(f"/v1/scenes/{scene}/selections", json=body)
    assert r.status_code == 201, r.text
    sel = r.json()
    assert sel["num_gaussians"] > 0 and 0 < sel["coverage"]["a"] < 0.5 and sel["coverage"]["b"] > 0
    assert client.post(f"/v1/scenes/{scene}/selections", json=body).json()["id"] == sel["id"]  # idempotent
    for q in ("view=a&width=256", "view=b&width=128", f"c2w={IDENTITY}&width=128"):
        m = client.get(f"/v1/scenes/{scene}/selections/{sel['id']}/mask?{q}")
        assert m.status_code == 200 and m.headers["content-type"] == "image/png", m.text
        img = np.asarray(Image.open(io.BytesIO(m.content)))
        assert set(np.unique(img)) <= {0, 255}
        if q.startswith("view=a"):
            assert img.shape[:2] == (128, 256) and (img[..., 0] == 255).any()
    seg = [np.asarray(Image.open(io.BytesIO(client.get(f"/v1/scenes/{scene}/segments?view={v}&width=256").content)))
           for v in ("a", "b")]
    assert seg[0].shape == (128, 256, 3)
    # the same segments carry the same colours in both references: most of A's pixels have a colour B shows too
    in_b = {tuple(c) for c in seg[1].reshape(-1, 3)}
    assert np.mean([tuple(c) in in_b for c in seg[0].reshape(-1, 3)]) > 0.5
    assert client.get(f"/v1/scenes/{scene}/segments?c2w={IDENTITY}&width=128").status_code == 200
    r = client.post(f"/v1/scenes/{scene}/selections", json={"segment": 0})
    assert r.status_code == 201, r.text
    # per-Gaussian segment labels are stored with the scene, one per Gaussian, every label a real segment
    with np.load(live.store / "scenes" / scene / "edit_index.npz") as z:
        n = client.get(f"/v1/scenes/{scene}").json()["num_gaussians"]
        assert z["gaussian_labels"].shape == (n,) and z["gaussian_labels"].max() < z["segment_sizes"].size
        assert z["segments"].shape[0] == 2 and z["segment_sizes"].sum() == z["segments"].size

    r = client.post(f"/v1/scenes/{scene}/edits", json={"selection": sel["id"], "op": "remove"})
    assert r.status_code == 201, r.text
    removed = r.json()
    assert removed["num_gaussians"] == client.get(f"/v1/scenes/{scene}").json()["num_gaussians"] - sel["num_gaussians"]
    again = client.post(f"/v1/scenes/{scene}/edits", json={"selection": sel["id"], "op": "remove"}).json()
    assert again["id"] == removed["id"] and again["cached"] is True
    meta = client.get(f"/v1/scenes/{removed['id']}").json()
    assert meta["parent"] == scene and 0.0 <= meta["edit"]["uncovered"]["a"] <= 1.0
    # every link the edit's answers give leads somewhere, back to the scene it was made from too
    assert removed["links"] == meta["links"] and meta["links"]["parent"] == f"/v1/scenes/{scene}"
    assert client.get(f"/v1/scenes/{scene}").json()["links"]["parent"] is None
    assert client.get(meta["links"]["parent"]).json()["id"] == scene
    assert client.get(meta["links"]["segments"], params={"view": "a", "width": 64}).status_code == 200
    # the environment shell (last Gaussians) loses the removed pixels' blocks and stays counted
    shell = client.get(f"/v1/scenes/{scene}").json()["shell"]
    assert 0 < meta["shell"] < shell
    with np.load(live.store / "scenes" / removed["id"] / "edit_index.npz") as z:
        assert z["gaussian_labels"].shape == (removed["num_gaussians"],)
    for op, extra in (("keep", {}), ("recolor", {"color": [0, 1, 0]}), ("translate", {"offset": [0, 0.1, 0]})):
        r = client.post(f"/v1/scenes/{scene}/edits", json={"selection": sel["id"], "op": op, **extra})
        assert r.status_code == 201, r.text
        assert r.json()["id"] != removed["id"]
        if op == "keep":  # an extracted object takes its surfels, not the backdrop behind them
            kept = client.get(f"/v1/scenes/{r.json()['id']}").json()
            assert kept["shell"] == 0 and 0 < kept["num_gaussians"] < sel["num_gaussians"]
    # an edited scene can be selected again (it kept its correspondences)
    r = client.post(f"/v1/scenes/{removed['id']}/selections", json={"view": "b", "points": [[0.2, 0.5]]})
    assert r.status_code == 201, r.text


def test_a_selections_location_answers_what_its_201_said(client, scene, live):
    """The 201 of a selection points at it (``Location``, ``links.self``): that URL answers the 201's body less its
    timings, and 404 for a selection the scene does not hold; a selection stored without that description is
    described by its masks and Gaussians."""
    r = client.post(f"/v1/scenes/{scene}/selections", json={"view": "a", "points": [[0.3, 0.6]]})
    assert r.status_code == 201, r.text
    created = r.json()
    assert r.headers["location"] == created["links"]["self"]
    got = client.get(r.headers["location"])
    assert got.status_code == 200, got.text
    assert got.json() == {k: v for k, v in created.items() if k != "timings"}
    unknown = "0" * 32
    _error(client.get(f"/v1/scenes/{scene}/selections/{unknown}"), 404, "selection_not_found")
    _error(client.get(f"/v1/scenes/{unknown}/selections/{created['id']}"), 404, "scene_not_found")
    path = live.store / "scenes" / scene / f"selection-{created['id']}.npz"
    with np.load(path) as z:
        kept = {k: z[k] for k in z.files if k != "description"}
    np.savez_compressed(path, **kept)
    bare = client.get(created["links"]["self"]).json()
    assert bare["num_gaussians"] == created["num_gaussians"]
    assert bare["coverage"] == pytest.approx(created["coverage"])


def test_bad_selection_and_edit_inputs(client, scene, live):
    url = f"/v1/scenes/{scene}"
    msg = _error(client.post(f"{url}/selections", json={"view": "a", "points": [[1.2, 0.5]]}), 422, "invalid_selection")
    assert "[0, 1]" in msg
    _error(client.post(f"{url}/selections", json={"view": "a", "points": [[0.5, 0.5]], "negative": [[0.5, -1]]}),
           422, "invalid_selection")
    assert client.post(f"{url}/selections", json={"view": "a", "points": []}).status_code == 422
    assert client.post(f"{url}/selections", json={"view": "c", "points": [[0.5, 0.5]]}).status_code == 422
    _error(client.post(f"{url}/selections", json={"segment": 10 ** 6}), 404, "unknown_segment")
    huge = _error(client.post(f"{url}/selections", json={"segment": 10 ** 4000}), 422, "invalid_request")
    assert "segment" in huge and len(huge) < 200  # named, not repeated digit by digit
    _error(client.post(f"{url}/selections", json={"view": "a", "points": [[0.5, 0.5]], "negative": [[0.5, 0.5]]}),
           422, "invalid_selection")
    unknown = "0" * 32
    _error(client.get(f"{url}/selections/{unknown}/mask?view=a&width=256"), 404, "selection_not_found")
    _error(client.post(f"{url}/edits", json={"selection": unknown, "op": "remove"}), 404, "selection_not_found")
    assert client.post(f"{url}/edits", json={"selection": unknown, "op": "recolor", "color": [2, 0, 0]}).status_code == 422
    assert client.post(f"{url}/edits", json={"selection": unknown, "op": "translate"}).status_code == 422
    _error(client.post(f"/v1/scenes/{unknown}/selections", json={"segment": 0}), 404, "scene_not_found")
    assert client.get(f"{url}/segments").status_code == 422  # neither view nor c2w
    # a scene without correspondences (as built by an older model): 409 for selections and edits
    sel = client.post(f"{url}/selections", json={"view": "a", "points": [[0.5, 0.3]]}).json()["id"]
    copy = post_scene(client, _png(np.full((512, 1024, 3), 0.4) + np.random.default_rng(0).random((512, 1024, 3)) * 0.5),
                      _png(np.random.default_rng(1).random((512, 1024, 3))))
    plain = copy.json()["id"]
    assert copy.json()["links"]["selections"] == f"/v1/scenes/{plain}/selections"
    (live.store / "scenes" / plain / "edit.npz").unlink()
    links = client.get(f"/v1/scenes/{plain}").json()["links"]  # it offers no object links it cannot follow
    assert links["selections"] is links["segments"] is links["edits"] is None and links["ply"]
    _error(client.post(f"/v1/scenes/{plain}/selections", json={"view": "a", "points": [[0.5, 0.5]]}), 409,
           "correspondences_missing")
    _error(client.post(f"/v1/scenes/{plain}/edits", json={"selection": sel, "op": "remove"}), 409,
           "correspondences_missing")


def test_translations_stay_within_the_scenes_extent(client, scene):
    """An offset beyond the extent names the bound; translations that add up past it (where no render camera
    may go) are refused on the edit that would cross it, not stored."""
    url = f"/v1/scenes/{scene}"
    sel = client.post(f"{url}/selections", json={"view": "a", "points": [[0.5, 0.7]]}).json()["id"]
    msg = _error(client.post(f"{url}/edits", json={"selection": sel, "op": "translate", "offset": [1e7, 0, 0]}),
                 422, "invalid_request")
    assert msg.startswith("offset: the translate op needs dx, dy, dz, each within +-1e+06"), msg


def _splats(n: int, centre: float, size: float):
    """n Gaussians around (centre, centre, centre), one unit apart, of middle scale ``size``."""
    from rasterizer.gaussians import Gaussians

    rng = np.random.default_rng(11)
    return Gaussians(means=(centre + rng.normal(size=(n, 3))).astype(np.float32),
                     scales=np.tile(np.float32([size / 10, size, 2 * size]), (n, 1)),
                     quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)), opacities=np.full(n, 0.5, np.float32),
                     sh=np.zeros((n, 1, 3), np.float32))


def test_translated_gaussians_stay_within_the_extent_and_float32s_resolution():
    """The translate edit's check: moves that add up beyond the scenes' extent are refused (for metre-wide splats,
    which float32 still places there), as are moves to where float32 steps exceed an eighth of the moved splats'
    size, unless they already lay where it steps as coarsely (a scene far out may be nudged)."""
    from service.edits import check_translated
    from service.errors import BadInput

    def moved(g, by):
        return g.with_(means=g.means + np.float32(by))

    every = np.ones(50, bool)
    giant = _splats(50, 6e5, 50.0)
    check_translated(giant, moved(giant, 3e5), every)
    with pytest.raises(BadInput, match="beyond 1e\\+06 from the origin"):
        check_translated(giant, moved(giant, 6e5), every)
    cm = _splats(50, 0.0, 0.016)  # an eighth of their size is 2 mm: float32 steps by 1.95 mm up to 32768 out
    check_translated(cm, moved(cm, 2e4), every)
    with pytest.raises(BadInput, match="float32 positions step by 0.0039"):  # 3.9 mm from 32768 out
        check_translated(cm, moved(cm, 5e4), every)
    far = moved(cm, 5e4)  # a scene that already lies there (sent with such poses) may be nudged, not moved farther
    check_translated(far, moved(far, 1.0), every)
    with pytest.raises(BadInput, match="float32 positions step by 0.0078"):
        check_translated(far, moved(far, 3e4), every)
    check_translated(cm, cm, np.zeros(50, bool))  # nothing moved


def test_a_translation_of_zero_size_splats_is_a_422_not_a_division_by_zero():
    """Splats of scale 0 (a point cloud a PLY may hold) have no size to hold a step against: moved any distance
    where float32 steps more coarsely than where they were, the edit is refused with words, not a ZeroDivisionError."""
    from service.edits import check_translated
    from service.errors import BadInput

    points = _splats(4, 0.0, 0.0)
    with pytest.raises(BadInput, match="more than its Gaussians' median size 0"):
        check_translated(points, points.with_(means=points.means + np.float32(1000.0)), np.ones(4, bool))


def test_a_translation_to_where_float32_scrambles_the_selection_is_a_422(client, scene):
    """Moved 6e5 units out (a georeferenced scene's distance), float32 positions step by 0.0625 units, far beyond the
    splats' size: the stored scene, its renders and its PLY would show the object scrambled, so the edit is refused
    with what to do; a move that keeps the step within an eighth of their size is made."""
    url = f"/v1/scenes/{scene}"
    sel = client.post(f"{url}/selections", json={"view": "a", "points": [[0.5, 0.7]]}).json()["id"]
    r = client.post(f"{url}/edits", json={"selection": sel, "op": "translate", "offset": [6e5, 0, 0]})
    msg = _error(r, 422, "invalid_edit")
    assert "float32 positions step by 0.0625" in msg and msg.endswith("translate by less"), msg
    near = client.post(f"{url}/edits", json={"selection": sel, "op": "translate", "offset": [0.5, 0, 0]})
    assert near.status_code == 201, near.text


def test_empty_selection_is_a_clear_422(scene, live, monkeypatch):
    """A prompt whose masks own no Gaussian (forced here) is refused with empty_selection, not stored."""
    from rasterizer.edit import scene as edit_scene
    from service import edits
    from service.errors import ServiceError
    from service.store import SceneStore, content_id

    store = SceneStore(live.store)
    real = edit_scene.select_points

    def nothing(index, view, points, negative=()):
        sel = real(index, view, points, negative)
        return edit_scene.Selection(np.zeros_like(sel.masks), np.zeros_like(sel.gaussians), sel.level, None)

    monkeypatch.setattr(edit_scene, "select_points", nothing)
    request = {"view": "b", "points": [[0.3, 0.6]], "negative": []}
    with pytest.raises(ServiceError) as err:
        edits.create_selection(store, scene, request)
    assert err.value.status == 422 and err.value.code == "empty_selection"
    sel_id = content_id("selection/v1", scene, json.dumps(request, sort_keys=True, separators=(",", ":")))
    assert store.artifact(scene, f"selection-{sel_id}.npz") is None


def test_cli_select_and_edit(scene, live, capsys):
    from service.cli import main

    assert main(["select", scene, "--store", str(live.store), "--view", "a", "--point", "0.95,0.5"]) == 0
    sel = json.loads(capsys.readouterr().out)
    assert sel["num_gaussians"] > 0
    assert main(["edit", scene, "--store", str(live.store), "--selection", sel["id"], "--op", "recolor",
                 "--color", "0,0.5,1"]) == 0
    new = json.loads(capsys.readouterr().out)
    assert new["parent"] == scene and new["edit"]["op"] == "recolor"
    assert main(["select", scene, "--store", str(live.store), "--view", "a", "--point", "1.5,0.5"]) == 2
    assert "[0, 1]" in capsys.readouterr().err
    assert main(["edit", scene, "--store", str(live.store), "--selection", "0" * 32, "--op", "remove"]) == 2
    assert "selection_not_found" in capsys.readouterr().err


def test_a_scene_with_split_pixels_selects_and_removes_them_whole(client, m3d_dir):
    """Uploads twice the model's width split textured pixels into 2x2 Gaussians (rasterizer.compaction.split);
    the children keep their pixel's provenance, so a selection takes all four and a removal leaves none."""
    s = load_scene(m3d_dir)
    fa, fb = s.frames["00"], s.frames["02"]
    poses = json.dumps({"convention": "opencv", "c2w": [fa.c2w.tolist(), fb.c2w.tolist()]})
    r = post_scene(client, _png(fa.image(), 2), _png(fb.image(), 2), poses=poses)
    assert r.status_code == 201, r.text
    scene = r.json()["id"]
    meta = client.get(f"/v1/scenes/{scene}").json()
    assert meta["compaction"]["split_textured"]["split"] > 0
    sel = client.post(f"/v1/scenes/{scene}/selections", json={"view": "a", "points": [[0.95, 0.5]]})
    assert sel.status_code == 201, sel.text
    assert sel.json()["num_gaussians"] > 0
    r = client.post(f"/v1/scenes/{scene}/edits", json={"selection": sel.json()["id"], "op": "remove"})
    assert r.status_code == 201, r.text
    assert r.json()["num_gaussians"] == meta["num_gaussians"] - sel.json()["num_gaussians"]


@pytest.mark.parametrize("route", ["render", "segments"])
@pytest.mark.parametrize("query", ["width=6_4", "width=%EF%BC%96%EF%BC%94", "projection=perspective&width=64&height=4_8",
                                   "projection=perspective&width=64&fov_deg=9_0"])
def test_query_numbers_are_plain_decimals(client, scene, route, query):
    """Width, height and fov_deg as the c2w query's numbers: digit groups (6_4, which Python reads as 64) and
    non-ASCII digits are a 422 naming the parameter, not a view of another size than most clients would read."""
    message = _error(client.get(f"/v1/scenes/{scene}/{route}?c2w={IDENTITY}&{query}"), 422, "invalid_request")
    assert "plain decimal" in message and query.rsplit("&", 1)[-1].split("=")[0] in message, message
    plain = query.replace("6_4", "64").replace("4_8", "48").replace("9_0", "90").replace("%EF%BC%96%EF%BC%94", "64")
    r = client.get(f"/v1/scenes/{scene}/{route}?c2w={IDENTITY}&{plain}")
    assert r.status_code == 200, r.text


def test_minus_zero_names_the_same_selection_and_edit(client, scene):
    """JSON's -0.0 is the number 0: a point on the seam, a colour channel or an offset of -0.0 asks for what 0.0 asks
    for, so it gets the same selection and edit id (the content hash is idempotent), not a second stored copy."""
    url = f"/v1/scenes/{scene}"
    plus = client.post(f"{url}/selections", json={"view": "a", "points": [[0.0, 0.5]]})
    minus = client.post(f"{url}/selections", json={"view": "a", "points": [[-0.0, 0.5]], "negative": [[0.5, -0.0]]})
    assert plus.status_code == minus.status_code == 201, minus.text
    signed = client.post(f"{url}/selections", json={"view": "a", "points": [[0.0, 0.5]], "negative": [[0.5, 0.0]]})
    assert minus.json()["id"] == signed.json()["id"] and minus.json()["request"]["points"] == [[0.0, 0.5]]
    sel = plus.json()["id"]
    for op, key in (("recolor", "color"), ("translate", "offset")):
        a = client.post(f"{url}/edits", json={"selection": sel, "op": op, key: [0.0, 1.0, 0.0]})
        b = client.post(f"{url}/edits", json={"selection": sel, "op": op, key: [-0.0, 1.0, -0.0]})
        assert a.status_code in (200, 201) and b.status_code in (200, 201), b.text
        assert b.json()["id"] == a.json()["id"] and b.json()["cached"] is True


def test_a_parent_link_is_null_once_the_parent_is_deleted(client, scene):
    """An edit of an edit keeps its parent's id in its metadata, but its links.parent is null once that scene is
    deleted: every link of an answer leads to something that answers."""
    sel = client.post(f"/v1/scenes/{scene}/selections", json={"view": "a", "points": [[0.95, 0.5]]}).json()
    middle = client.post(f"/v1/scenes/{scene}/edits",
                         json={"selection": sel["id"], "op": "recolor", "color": [0.2, 0.4, 0.6]}).json()
    sel2 = client.post(f"/v1/scenes/{middle['id']}/selections", json={"view": "a", "points": [[0.95, 0.5]]}).json()
    last = client.post(f"/v1/scenes/{middle['id']}/edits",
                       json={"selection": sel2["id"], "op": "recolor", "color": [0.9, 0.1, 0.1]})
    assert last.status_code == 201, last.text
    last = last.json()
    assert last["links"]["parent"] == f"/v1/scenes/{middle['id']}"
    assert client.delete(f"/v1/scenes/{middle['id']}").status_code == 204
    meta = client.get(f"/v1/scenes/{last['id']}").json()
    assert meta["parent"] == middle["id"] and meta["links"]["parent"] is None
