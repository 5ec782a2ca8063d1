"""Render compositing: plain (front to back over black, what 3DGS viewers show) is the default of the
API and the CLI for every projection; ``compositing=va`` / ``--compositing va`` is the paper's V/A."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from rasterizer.ply import read_ply
from rasterizer.render import render, to_uint8
from service import cli
from service.inputs import RENDER_CUT_SIGMA

from ._support import IDENTITY, LiveServer, make_settings, panorama, post_scene, small_model

YAW = ",".join(str(v) for v in np.array([[0.0, 0, 1, 0.1], [0, 1, 0, 0], [-1, 0, 0, 0], [0, 0, 0, 1]]).ravel())


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    model = small_model(tmp_path_factory)
    with LiveServer(make_settings(model, tmp_path_factory.mktemp("store"))) as server, server.client() as client:
        r = post_scene(client, panorama(seed=3), panorama(seed=3, shift=7))
        assert r.status_code == 201, r.text
        scene_id = r.json()["id"]
        ply = tmp_path_factory.mktemp("ply") / "scene.ply"
        ply.write_bytes(client.get(f"/v1/scenes/{scene_id}/gaussians.ply").content)
        shell = client.get(f"/v1/scenes/{scene_id}").json()["shell"]
        assert shell > 0
        yield client, scene_id, read_ply(ply), shell


def _close(a: np.ndarray, b: np.ndarray) -> bool:
    d = np.abs(a.astype(int) - b.astype(int))
    return a.shape == b.shape and d.max() <= 1 and d.mean() < 0.01


def _png(data: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))


CASES = [
    ({"projection": "erp", "width": 256}, {"projection": "erp", "width": 256}),
    ({"projection": "yin", "width": 192}, {"projection": "yin", "width": 192}),
    ({"projection": "yang", "width": 192}, {"projection": "yang", "width": 192}),
    ({"projection": "perspective", "width": 160, "height": 120, "fov_deg": 90},
     {"projection": "perspective", "width": 160, "height": 120, "fov_deg": 90.0}),
]


@pytest.mark.parametrize("params, kwargs", CASES, ids=[c[0]["projection"] for c in CASES])
@pytest.mark.parametrize("pose", [IDENTITY, YAW], ids=["identity", "yawed"])
def test_api_default_is_plain_and_va_is_explicit(served, params, kwargs, pose):
    client, scene_id, gaussians, shell = served
    c2w = np.array([float(v) for v in pose.split(",")]).reshape(4, 4)
    default = client.get(f"/v1/scenes/{scene_id}/render", params={"c2w": pose, **params})
    plain = client.get(f"/v1/scenes/{scene_id}/render", params={"c2w": pose, **params, "compositing": "plain"})
    va = client.get(f"/v1/scenes/{scene_id}/render", params={"c2w": pose, **params, "compositing": "va"})
    assert default.status_code == plain.status_code == va.status_code == 200
    # the API renders at the scene's own resolution (rasterizer.scene_resolution), the shell apart, a plain
    # composite's footprints cut as a reconstruction's (V/A's not)
    kwargs = dict(kwargs, resolution="scene", backdrop=shell)
    expect_plain = to_uint8(render(gaussians, c2w, normalize=False, cut_sigma=RENDER_CUT_SIGMA, **kwargs).colour)
    expect_va = to_uint8(render(gaussians, c2w, normalize=True, **kwargs).colour)
    # the PLY round trip (logit/log/quaternion in float32) may move a pixel by one level
    assert _close(_png(default.content), expect_plain)
    assert _close(_png(plain.content), expect_plain)
    assert _close(_png(va.content), expect_va)
    # the two differ where coverage is partial: plain is never brighter than V/A of the same footprints
    assert not np.array_equal(expect_plain, expect_va)
    va_cut = to_uint8(render(gaussians, c2w, normalize=True, cut_sigma=RENDER_CUT_SIGMA, **kwargs).colour)
    assert (expect_plain.astype(int) <= va_cut.astype(int) + 1).all()
    assert default.headers["etag"] != va.headers["etag"]


@pytest.mark.parametrize("fov, cut", [(160.0, RENDER_CUT_SIGMA), (170.0, None)])
def test_wide_perspective_views_are_not_cut(served, fov, cut):
    """The API cuts a reconstruction's footprints in views up to CUT_MAX_FOV_DEG only: wider, the footprints
    stretched at the rim lose coverage to the cut (dev-scene views moved by 40-43 dB)."""
    client, scene_id, gaussians, shell = served
    params = {"projection": "perspective", "width": 160, "height": 120, "fov_deg": fov}
    r = client.get(f"/v1/scenes/{scene_id}/render", params={"c2w": YAW, **params})
    assert r.status_code == 200
    c2w = np.array([float(v) for v in YAW.split(",")]).reshape(4, 4)
    expect = to_uint8(render(gaussians, c2w, normalize=False, cut_sigma=cut, resolution="scene", backdrop=shell,
                             **params).colour)
    other = to_uint8(render(gaussians, c2w, normalize=False, cut_sigma=RENDER_CUT_SIGMA if cut is None else None,
                            resolution="scene", backdrop=shell, **params).colour)
    assert not _close(expect, other)  # the two renders differ, so the comparison tells them apart
    assert _close(_png(r.content), expect)


def test_plain_erp_is_the_premultiplied_yin_yang_merge(served):
    _, _, g, _ = served
    plain = render(g, np.eye(4), projection="erp", width=256, normalize=False)
    va = render(g, np.eye(4), projection="erp", width=256, normalize=True)
    legacy = render(g, np.eye(4), projection="erp", width=256)  # the rasterizer's own default is unchanged
    assert np.array_equal(va.colour, legacy.colour)
    ok = va.alpha >= 1 / 255
    np.testing.assert_allclose(plain.colour[ok], (va.colour * va.alpha[:, :, None])[ok], atol=2e-6)
    assert np.array_equal(plain.alpha, va.alpha) and np.array_equal(plain.range, va.range)


def test_bad_compositing_is_422(served):
    client, scene_id, _, _ = served
    r = client.get(f"/v1/scenes/{scene_id}/render", params={"c2w": IDENTITY, "width": 64, "compositing": "over"})
    assert r.status_code == 422 and r.json()["error"]["code"] in ("invalid_request", "invalid_render_query")


def test_openapi_documents_compositing(served):
    client, _, _, _ = served
    params = client.get("/openapi.json").json()["paths"]["/v1/scenes/{scene_id}/render"]["get"]["parameters"]
    comp = next(p for p in params if p["name"] == "compositing")
    assert comp["schema"]["default"] == "plain" and "V/A" in comp["description"]
    assert "paper" in comp["description"]


def test_cli_render_default_plain_and_flag_va(served, tmp_path):
    client, scene_id, g, _ = served
    ply = tmp_path / "s.ply"
    ply.write_bytes(client.get(f"/v1/scenes/{scene_id}/gaussians.ply").content)
    base = ["render", str(ply), "--c2w", YAW, "--projection", "perspective", "--width", "96", "--height", "64"]
    assert cli.main([*base, "-o", str(tmp_path / "plain.png")]) == 0
    assert cli.main([*base, "--compositing", "va", "-o", str(tmp_path / "va.png")]) == 0
    c2w = np.array([float(v) for v in YAW.split(",")]).reshape(4, 4)
    kw = dict(projection="perspective", width=96, height=64, fov_deg=90.0, resolution="scene")
    assert np.array_equal(np.asarray(Image.open(tmp_path / "plain.png").convert("RGB")),
                          to_uint8(render(g, c2w, normalize=False, **kw).colour))  # the CLI reads the same PLY
    assert np.array_equal(np.asarray(Image.open(tmp_path / "va.png").convert("RGB")),
                          to_uint8(render(g, c2w, normalize=True, **kw).colour))
    with pytest.raises(SystemExit):
        cli.main([*base, "--compositing", "bogus"])
