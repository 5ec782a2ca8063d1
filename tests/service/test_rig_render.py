"""Renders with the capture rig (``rig=true`` / ``--rig``): the rig both references show at their nadir is
composited at the render camera's own nadir; a scene without one answers 422; the default is the scene alone."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from rasterizer.camera import camera_directions
from rasterizer.rig import AUTO_RIG_CAP_DEG
from service import cli

from ._support import IDENTITY, LiveServer, make_settings, panorama, post_scene, small_model

RIG_U8 = np.uint8([26, 20, 15])
DISC_DEG = 20.0
#: a pose 0.25 m from both references, turned 90 deg about the vertical
TURNED = ",".join(str(v) for v in np.array([[0.0, 0, 1, 0.25], [0, 1, 0, 0.05], [-1, 0, 0, 0], [0, 0, 0, 1]]).ravel())


def _with_rig(data: bytes) -> bytes:
    """The panorama with a dark tripod disc within DISC_DEG of its nadir."""
    img = np.asarray(Image.open(io.BytesIO(data)).convert("RGB")).copy()
    down = camera_directions("erp", *img.shape[:2])[..., 1]
    img[np.degrees(np.arccos(np.clip(down, -1, 1))) < DISC_DEG] = RIG_U8
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    return buf.getvalue()


def _png(data: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))


def _from_nadir_deg(kind: str, h: int, w: int, fov: float = 90.0) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(camera_directions(kind, h, w, fov)[..., 1], -1, 1)))


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    model = small_model(tmp_path_factory)
    images = tmp_path_factory.mktemp("rig_images")
    a, b = _with_rig(panorama(seed=11)), _with_rig(panorama(seed=12))
    (images / "a.png").write_bytes(a)
    (images / "b.png").write_bytes(b)
    with LiveServer(make_settings(model, tmp_path_factory.mktemp("store"))) as server, server.client() as client:
        rigged = post_scene(client, a, b)
        bare = post_scene(client, panorama(seed=11), panorama(seed=12))
        assert rigged.status_code == 201 and bare.status_code == 201, (rigged.text, bare.text)
        yield client, rigged.json()["id"], bare.json()["id"], images


def test_scene_metadata_says_whether_the_references_show_a_rig(served):
    client, rigged, bare, _ = served
    meta = client.get(f"/v1/scenes/{rigged}").json()
    rig = meta["rig"]
    assert rig["detected"] is True and rig["agreement"] <= rig["max_agreement"]
    assert meta["info"]["rig_cap_deg"] == AUTO_RIG_CAP_DEG  # the rig's pixels take the other view's colour
    meta = client.get(f"/v1/scenes/{bare}").json()
    rig = meta["rig"]
    assert rig["detected"] is False and rig["agreement"] > rig["max_agreement"]
    assert meta["info"]["rig_cap_deg"] == 0.0


@pytest.mark.parametrize("params, kind", [({"projection": "erp", "width": 128}, "erp"),
                                          ({"projection": "yang", "width": 96}, "yang"),
                                          ({"projection": "perspective", "width": 41, "fov_deg": 170}, "perspective")])
def test_rig_render_shows_the_rig_at_the_render_cameras_nadir_and_the_scene_elsewhere(served, params, kind):
    client, rigged, _, _ = served
    url = f"/v1/scenes/{rigged}/render"
    plain = client.get(url, params={"c2w": TURNED, **params})
    with_rig = client.get(url, params={"c2w": TURNED, **params, "rig": "true"})
    assert plain.status_code == 200 and with_rig.status_code == 200, with_rig.text
    assert plain.headers["etag"] != with_rig.headers["etag"]
    a, b = _png(plain.content), _png(with_rig.content)
    from_nadir = _from_nadir_deg(kind, *a.shape[:2], params.get("fov_deg", 90.0))
    near, far = from_nadir < 8.0, from_nadir > 35.0
    assert near.any() and far.any()
    assert np.abs(b[near].astype(int) - RIG_U8).max() <= 2  # the rig, wherever the scene is under the camera
    np.testing.assert_array_equal(a[far], b[far])  # the scene, untouched above the rig's cap


def test_rig_render_of_a_scene_without_a_rig_is_422(served):
    client, _, bare, _ = served
    r = client.get(f"/v1/scenes/{bare}/render", params={"c2w": IDENTITY, "width": 64, "rig": "true"})
    assert r.status_code == 422
    err = r.json()["error"]
    assert err["code"] == "no_rig" and "no common capture rig" in err["message"]
    assert client.get(f"/v1/scenes/{bare}/render", params={"c2w": IDENTITY, "width": 64}).status_code == 200


@pytest.mark.parametrize("method, headers", [("HEAD", {}), ("GET", {"If-None-Match": "*"})])
def test_rig_check_holds_for_head_and_conditional_requests(served, method, headers):
    """Neither renders; both answered 200 / 304 for a rig the scene does not have."""
    client, rigged, bare, _ = served
    params = {"c2w": IDENTITY, "width": 64, "rig": "true"}
    r = client.request(method, f"/v1/scenes/{bare}/render", params=params, headers=headers)
    assert r.status_code == 422, (method, r.status_code)
    ok = client.request(method, f"/v1/scenes/{rigged}/render", params=params, headers=headers)
    assert ok.status_code == (200 if method == "HEAD" else 304)


def test_openapi_documents_rig(served):
    client = served[0]
    params = client.get("/openapi.json").json()["paths"]["/v1/scenes/{scene_id}/render"]["get"]["parameters"]
    rig = next(p for p in params if p["name"] == "rig")
    assert rig["schema"]["default"] is False and "nadir" in rig["description"]


def test_cli_render_with_rig_images(served, tmp_path, capsys):
    client, rigged, _, images = served
    ply = tmp_path / "s.ply"
    ply.write_bytes(client.get(f"/v1/scenes/{rigged}/gaussians.ply").content)
    base = ["render", str(ply), "--c2w", TURNED, "--width", "128"]
    assert cli.main([*base, "--rig", str(images / "a.png"), str(images / "b.png"), "-o", str(tmp_path / "r.png")]) == 0
    out = np.asarray(Image.open(tmp_path / "r.png").convert("RGB"))
    api = _png(client.get(f"/v1/scenes/{rigged}/render", params={"c2w": TURNED, "width": 128, "rig": "true"}).content)
    near = _from_nadir_deg("erp", *out.shape[:2]) < 8.0
    assert np.abs(out[near].astype(int) - RIG_U8).max() <= 2
    diff = np.abs(out.astype(int) - api.astype(int))
    assert diff[near].mean() < 1.0  # the same rig (the API's references are resampled)
    assert diff.mean() < 2.0  # the API cuts a reconstruction's footprints short (RENDER_CUT_SIGMA), the CLI any PLY's not
    bare = tmp_path / "bare.png"
    bare.write_bytes(panorama(seed=13))
    assert cli.main([*base, "--rig", str(images / "a.png"), str(bare), "-o", str(tmp_path / "x.png")]) != 0
    assert "no common capture rig" in capsys.readouterr().err and not (tmp_path / "x.png").exists()
