"""Regression tests of the hardening audit: slow clients, limits, store failures, access."""

from __future__ import annotations

import errno
import io
import json
import os
import socket
import threading
import time
import types

import anyio
import httpx
import numpy as np
import plyfile
import pytest
from starlette.applications import Starlette
from starlette.responses import PlainTextResponse
from starlette.routing import Route

from rasterizer.splat import RenderLimitError
from service.access import AccessGuard
from service.config import Settings
from service.errors import translate
from service.limits import RENDER_PIXEL_GAUSSIANS, render_cost
from tests.service._support import (
    IDENTITY,
    POSES,
    LiveServer,
    make_settings,
    new_scene,
    panorama,
    post_scene,
)

HUGE = "1" + "0" * 399


@pytest.fixture(scope="module")
def guarded(model_path, tmp_path_factory):
    settings = make_settings(model_path, tmp_path_factory.mktemp("store"), header_timeout_s=1.0, body_timeout_s=2.0,
                             max_requests=3, max_render_cost=64 * 32 * (60_000.0 + RENDER_PIXEL_GAUSSIANS), heavy_render_cost=4e7)
    with LiveServer(settings) as server:
        yield server


@pytest.fixture(scope="module")
def scene(guarded) -> str:
    with guarded.client() as c:
        return new_scene(c, seed=41, shift=4)


def _connect(url: str) -> socket.socket:
    host, port = url.removeprefix("http://").split(":")
    return socket.create_connection((host, int(port)), timeout=10)


def _closed_by_server(sock: socket.socket, within: float) -> bool:
    sock.settimeout(within)
    try:
        while chunk := sock.recv(4096):
            if b"HTTP/1.1" in chunk:  # an answer is also fine (408/400), as long as it closes
                continue
        return True
    except socket.timeout:
        return False
    except ConnectionError:
        return True


# -- D1: idle and slow connections -------------------------------------------------------------------

def test_idle_and_trickling_connections_time_out_and_health_stays_200(guarded):
    idle = [_connect(guarded.url) for _ in range(80)]
    trickle = _connect(guarded.url)
    trickle.sendall(b"GET /healthz HTTP/1.1\r\n")
    try:
        with guarded.client() as c:
            for _ in range(3):  # while they are open
                r = c.get("/healthz")
                assert r.status_code == 200 and r.json() == {"status": "ok"}
                assert c.get("/readyz").status_code == 200
        for _ in range(3):  # a trickle of header bytes does not extend the deadline
            trickle.sendall(b"X")
            time.sleep(0.2)
        assert _closed_by_server(trickle, within=3.0)
        assert all(_closed_by_server(s, within=3.0) for s in idle[:5])
    finally:
        for s in [*idle, trickle]:
            s.close()


def test_trickled_body_gets_408_json(guarded):
    sock = _connect(guarded.url)
    try:
        sock.sendall(b"POST /v1/scenes HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: multipart/form-data; "
                     b"boundary=x\r\nContent-Length: 100000\r\n\r\n--x\r\n")
        deadline = time.monotonic() + 10
        data = b""
        sock.settimeout(0.3)
        while time.monotonic() < deadline and b"\r\n\r\n{" not in data:
            try:
                sock.sendall(b"y")
                data += sock.recv(4096)
            except socket.timeout:
                continue
            except ConnectionError:
                break
        head, _, body = data.partition(b"\r\n\r\n")
        assert head.startswith(b"HTTP/1.1 408"), data[:200]
        assert json.loads(body)["error"]["code"] == "request_timeout"
    finally:
        sock.close()


def test_overload_is_json_503_with_retry_after_and_health_exempt(guarded):
    admission = guarded.app.state.admission
    admission.working += admission.max_requests  # every work slot taken
    try:
        with guarded.client() as c:
            r = c.get("/v1/info")
            assert r.status_code == 503 and r.headers["retry-after"] and r.json()["error"]["code"] == "busy"
            assert c.get("/healthz").status_code == 200
            ready = c.get("/readyz")
            assert ready.status_code == 503 and "request slots" in ready.json()["error"]
    finally:
        admission.working -= admission.max_requests


def test_slow_uploads_do_not_take_work_slots(guarded):
    socks = []
    try:
        for _ in range(3):  # as many uploads arriving as there are work slots (max_requests=3)
            s = _connect(guarded.url)
            s.sendall(b"POST /v1/scenes HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: multipart/form-data; "
                      b"boundary=x\r\nContent-Length: 1000\r\n\r\n--x\r\n")
            socks.append(s)
        time.sleep(0.3)
        with guarded.client() as c:
            assert c.get("/v1/info").status_code == 200
            assert c.get("/healthz").status_code == 200 and c.get("/readyz").status_code == 200
    finally:
        for s in socks:
            s.close()


# -- D2 / D6: render limits --------------------------------------------------------------------------

def test_renderer_limit_maps_to_413_with_its_message():
    mapped = translate(RenderLimitError("footprints need about 9e9 contributions"))
    assert mapped.status == 413 and "9e9 contributions" in mapped.message


def test_render_cost_limit_is_413_before_rendering(guarded, scene):
    with guarded.client() as c:
        r = c.get(f"/v1/scenes/{scene}/render", params={"c2w": IDENTITY, "width": 512})
        assert r.status_code == 413 and r.json()["error"]["code"] == "render_too_large"
        assert "Gaussians" in r.json()["error"]["message"]
        assert c.get(f"/v1/scenes/{scene}/render", params={"c2w": IDENTITY, "width": 16}).status_code == 200


@pytest.mark.parametrize("method, headers", [("HEAD", {}), ("GET", {"If-None-Match": "*"})])
def test_render_cost_limit_holds_for_head_and_conditional_requests(guarded, scene, method, headers):
    """Neither renders, so a HEAD answered 200 and ``If-None-Match: *`` 304 where the GET is a 413."""
    with guarded.client() as c:
        r = c.request(method, f"/v1/scenes/{scene}/render", params={"c2w": IDENTITY, "width": 512}, headers=headers)
        assert r.status_code == 413, (method, r.status_code)


def test_heavy_renders_take_the_reconstruction_slot(guarded, scene, monkeypatch):
    state = guarded.app.state
    assert state.heavy_render_gate.limiter is state.inference_gate.limiter
    used = []
    for name in ("render_gate", "heavy_render_gate"):
        gate = getattr(state, name)
        monkeypatch.setattr(gate, "run", lambda fn, *a, _n=name, _run=gate.run: used.append(_n) or _run(fn, *a))
    with guarded.client() as c:
        n = c.get(f"/v1/scenes/{scene}").json()["num_gaussians"]
        assert render_cost(8, 16, n) < 4e7 < render_cost(16, 32, n)  # light at width 16, heavy at width 32
        for width in (16, 32):
            assert c.get(f"/v1/scenes/{scene}/render", params={"c2w": IDENTITY, "width": width}).status_code == 200
    assert used == ["render_gate", "heavy_render_gate"]


def test_full_reconstruction_queue_refused_before_the_body_is_read():
    received = []

    async def endpoint(request):
        received.append(await request.body())
        return PlainTextResponse("ran")

    class State:
        class inference_gate:  # noqa: N801 - a stand-in with the WorkGate interface the guard uses
            full = True
            rejected = 0

            @classmethod
            def reject(cls):
                cls.rejected += 1

    app = Starlette(routes=[Route("/v1/scenes", endpoint, methods=["POST"])])
    guarded_app = AccessGuard(app, Settings(retry_after_s=7), State)

    async def post():
        async with httpx.AsyncClient(transport=httpx.ASGITransport(app=guarded_app), base_url="http://127.0.0.1") as c:
            return await c.post("/v1/scenes", content=b"x" * 1000)

    r = anyio.run(post)
    assert r.status_code == 503 and r.headers["retry-after"] == "7" and r.json()["error"]["code"] == "busy"
    assert received == [] and State.inference_gate.rejected == 1


# -- D3: huge integers ---------------------------------------------------------------------------------

@pytest.mark.parametrize("field, value", [("options", f'{{"near": {HUGE}}}'), ("options", f'{{"far": {HUGE}}}'),
                                          ("options", f'{{"min_opacity": {HUGE}}}'),
                                          ("options", f'{{"adaptive_range": {{"margin": {HUGE}}}}}'),
                                          ("poses", POSES.replace("0.5", HUGE))])
def test_huge_integers_are_422_and_keep_the_connection(guarded, field, value):
    with guarded.client() as c:
        data = {"poses": POSES, field: value}
        t0 = time.perf_counter()
        r = c.post("/v1/scenes", files={"image_a": ("a.png", panorama(seed=3)), "image_b": ("b.png", panorama(seed=4))},
                   data=data)
        assert r.status_code == 422, r.text
        assert "digits" in r.json()["error"]["message"]
        assert "reconstruct" not in r.json()["error"]["message"]
        assert c.get("/healthz").status_code == 200  # same keep-alive connection still usable
        assert time.perf_counter() - t0 < 60


# -- D5: a full or read-only store --------------------------------------------------------------------

def test_store_write_failures_are_507_and_readiness_drops(guarded, monkeypatch):
    import service.store as store_module

    def disk_full(path, writer):
        raise OSError(errno.ENOSPC, "No space left on device")

    with guarded.client() as c:
        monkeypatch.setattr(store_module, "_write_file", disk_full)
        r = post_scene(c, panorama(seed=51), panorama(seed=52))
        assert r.status_code == 507 and r.json()["error"]["code"] == "store_unavailable", r.text
        assert "full" in r.json()["error"]["message"]
        ready = c.get("/readyz")
        assert ready.status_code == 503 and "not writable" in ready.json()["error"]
        monkeypatch.undo()
        assert c.get("/readyz").status_code == 200


def test_free_space_checked_before_inference(guarded, monkeypatch):
    calls = []
    encoder = guarded.app.state.runtime.encoder
    monkeypatch.setattr(guarded.app.state.settings, "min_free_store_bytes", 1 << 62)
    monkeypatch.setattr(encoder, "reconstruct", lambda *a, **k: calls.append(1))
    with guarded.client() as c:
        r = post_scene(c, panorama(seed=53), panorama(seed=54))
        assert r.status_code == 507 and "free" in r.json()["error"]["message"]
        assert c.get("/readyz").status_code == 503
    assert calls == []


def test_read_only_delete_is_507(guarded, scene, monkeypatch):
    import service.store as store_module

    def read_only(src, dst):
        raise OSError(errno.EROFS, "Read-only file system")

    with guarded.client() as c:  # the store's os.replace only (the server's own stays)
        monkeypatch.setattr(store_module, "os", types.SimpleNamespace(**{**vars(os), "replace": read_only}))
        r = c.delete(f"/v1/scenes/{scene}")
        monkeypatch.undo()
        assert r.status_code == 507 and "read-only" in r.json()["error"]["message"]
        assert c.get(f"/v1/scenes/{scene}").status_code == 200  # nothing lost


# -- D7: empty results --------------------------------------------------------------------------------

def test_empty_reconstruction_is_422_and_not_stored(guarded):
    with guarded.client() as c:
        r = post_scene(c, panorama(seed=61), panorama(seed=62), options='{"min_opacity": 0.999999}')
        assert r.status_code == 422 and r.json()["error"]["code"] == "empty_scene", r.text
        assert c.get(f"/v1/scenes/{r.headers.get('location', '/x').rsplit('/', 1)[-1]}").status_code in (404, 422)


# -- D8: PLY download racing a delete -----------------------------------------------------------------

def test_ply_download_during_delete_is_404_or_complete(guarded):
    outcomes = []
    with guarded.client() as c:
        for i in range(6):
            r = post_scene(c, panorama(seed=70 + i), panorama(seed=80 + i))
            assert r.status_code == 201, r.text
            sid = r.json()["id"]
            results = {}

            def download(sid=sid, results=results):
                with guarded.client() as d:
                    results["ply"] = d.get(f"/v1/scenes/{sid}/gaussians.ply")

            t = threading.Thread(target=download)
            t.start()
            c.delete(f"/v1/scenes/{sid}")
            t.join(60)
            ply = results["ply"]
            outcomes.append(ply.status_code)
            assert ply.status_code in (200, 404), ply.text[:300]
            if ply.status_code == 200:
                assert len(ply.content) == int(ply.headers["content-length"])
                assert plyfile.PlyData.read(io.BytesIO(ply.content))["vertex"].count == r.json()["num_gaussians"]
    assert set(outcomes) <= {200, 404}


# -- D9: access ---------------------------------------------------------------------------------------

def test_non_loopback_host_needs_a_key_or_an_explicit_opt_out():
    with pytest.raises(ValueError, match="api_key"):
        Settings(host="0.0.0.0")
    assert Settings(host="0.0.0.0", allow_no_auth=True).trusted_hosts == ["*"]
    assert Settings(host="10.1.2.3", api_key="k").trusted_hosts[-1] == "10.1.2.3"


def test_api_key_hosts_origins_and_info(model_path, tmp_path):
    settings = make_settings(model_path, tmp_path / "store", api_key="s3cret", cors_origins=["https://ok.example"])
    with LiveServer(settings) as server, server.client() as c:
        assert c.get("/healthz").status_code == 200  # probes need no key
        r = c.get("/v1/info")
        assert r.status_code == 401 and r.headers["www-authenticate"] == "Bearer"
        assert c.get("/v1/info", headers={"X-API-Key": "wrong"}).status_code == 401
        info = c.get("/v1/info", headers={"Authorization": "Bearer s3cret"})
        assert info.status_code == 200 and info.json()["settings"]["auth"] is True
        assert str(tmp_path) not in info.text and str(model_path.parent) not in info.text and "s3cret" not in info.text
        rebinding = c.get("/healthz", headers={"Host": "evil.example:8000"})
        assert rebinding.status_code == 400 and rebinding.json()["error"]["code"] == "invalid_host"
        foreign = c.post("/v1/scenes", headers={"Origin": "http://evil.example", "Authorization": "Bearer s3cret"})
        assert foreign.status_code == 403 and foreign.json()["error"]["code"] == "origin_not_allowed"
        pre = c.options("/v1/info", headers={"Origin": "https://ok.example", "Access-Control-Request-Method": "GET"})
        assert pre.status_code == 200 and pre.headers["access-control-allow-origin"] == "https://ok.example"


def test_viewer_page_takes_the_key_once_and_keeps_it_in_a_same_site_cookie(model_path, tmp_path):
    settings = make_settings(model_path, tmp_path / "store", api_key="s3cret")
    with LiveServer(settings) as server, server.client() as c:
        c.headers["Authorization"] = "Bearer s3cret"
        sid = post_scene(c, panorama(seed=95), panorama(seed=96)).json()["id"]
        del c.headers["Authorization"]
        assert c.get("/v1/info", params={"key": "s3cret"}).status_code == 401  # the query key opens the page only
        assert c.get(f"/v1/scenes/{sid}/viewer", params={"key": "wrong"}).status_code == 401
        moved = c.get(f"/v1/scenes/{sid}/viewer", params={"key": "s3cret", "fov_deg": "70"})
        assert moved.status_code == 303, moved.text  # the key leaves the URL at once
        assert moved.headers["location"] == f"/v1/scenes/{sid}/viewer?fov_deg=70"
        assert moved.headers["referrer-policy"] == "no-referrer"
        cookie = moved.headers["set-cookie"].lower()
        assert "omnisplat_key=s3cret" in cookie and "httponly" in cookie and "samesite=strict" in cookie
        page = c.get(moved.headers["location"])  # the browser follows, with the cookie
        assert page.status_code == 200 and page.headers["referrer-policy"] == "no-referrer", page.text
        assert c.get(f"/v1/scenes/{sid}/gaussians.ply").status_code == 200  # the browser's next requests
        for keys in (["s3cret", "other"], ["other", "s3cret"], ["s3cret", "s3cret"]):  # one rule: refused
            twice = c.get(f"/v1/scenes/{sid}/viewer", params=[("key", k) for k in keys])
            assert twice.status_code == 400 and twice.json()["error"]["code"] == "duplicate_query_parameter"


def test_viewer_cookie_carries_a_key_with_characters_a_cookie_quotes(model_path, tmp_path):
    """A base64 key (``/``, ``+``, ``=``) or one with ``;``, ``,``, quotes or backslashes: a cookie holding it raw
    is sent back quoted and escaped, so the page's own requests after the 303 were refused with 401."""
    key = 'Zm9v/YmFy+cXV4=;a,b"c\\d'
    with LiveServer(make_settings(model_path, tmp_path / "store", api_key=key)) as server, server.client() as c:
        c.headers["X-API-Key"] = key
        sid = post_scene(c, panorama(seed=97), panorama(seed=98)).json()["id"]
        del c.headers["X-API-Key"]
        moved = c.get(f"/v1/scenes/{sid}/viewer", params={"key": key})
        assert moved.status_code == 303, moved.text
        assert key not in moved.headers["set-cookie"]  # percent-encoded, not quoted
        for path in (moved.headers["location"], f"/v1/scenes/{sid}/gaussians.ply", f"/v1/scenes/{sid}"):
            assert c.get(path).status_code == 200, path  # the browser's next requests carry the cookie
        c.cookies.clear()
        c.cookies.set("omnisplat_key", "Zm9v/YmFy+cXV4=")  # a wrong key stays wrong
        assert c.get(f"/v1/scenes/{sid}").status_code == 401


# -- D10: one error shape ------------------------------------------------------------------------------

def test_405_allow_lists_every_method_of_the_path(guarded, scene):
    with guarded.client() as c:
        r = c.put(f"/v1/scenes/{scene}")
        assert r.status_code == 405 and r.json()["error"]["code"] == "method_not_allowed"
        assert {m.strip() for m in r.headers["allow"].split(",")} >= {"GET", "DELETE"}


def test_refine_malformed_json_is_422_naming_the_body(guarded, scene):
    with guarded.client() as c:
        r = c.post(f"/v1/scenes/{scene}/refine", content=b'{"iterations": ', headers={"content-type": "application/json"})
        assert r.status_code == 422, r.text
        assert r.json()["error"]["message"].startswith("body: not valid JSON")
        r = c.post(f"/v1/scenes/{scene}/refine", json={"colour_reg": float("1" + "0" * 300)})
        assert r.status_code == 422


def test_spz_of_a_scene_far_from_the_origin_is_a_422_that_names_the_ply(model_path, tmp_path):
    """A stored scene 5e3 units out whose splats are 1 mm wide: SPZ's 24-bit step there (2^-10) is 0.98 of their
    size, so the SPZ download is refused with what to do and the PLY is served."""
    from fastapi.testclient import TestClient

    from rasterizer.gaussians import Gaussians
    from service.app import create_app

    rng = np.random.default_rng(5)
    n = 500
    g = Gaussians(means=(5e3 + rng.normal(size=(n, 3))).astype(np.float32),
                  scales=np.tile(np.float32([1e-4, 1e-3, 2e-3]), (n, 1)), quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                  opacities=np.full(n, 0.5, np.float32), sh=np.zeros((n, 4, 3), np.float32))
    app = create_app(make_settings(model_path, tmp_path / "store", warmup=False))
    with TestClient(app, base_url="http://127.0.0.1") as c:
        scene_id = "ab" * 16
        app.state.store.put(scene_id, g, {"shell": 0})
        r = c.get(f"/v1/scenes/{scene_id}/gaussians.spz")
        assert r.status_code == 422 and r.json()["error"]["code"] == "spz_unsupported", r.text
        assert r.json()["error"]["message"].endswith("use the PLY, or send poses nearer the origin")
        assert c.get(f"/v1/scenes/{scene_id}/gaussians.ply").status_code == 200


def test_lifespan_owns_the_state_and_cancels_jobs(model_path, tmp_path):
    from fastapi.testclient import TestClient

    from service.app import create_app

    app = create_app(make_settings(model_path, tmp_path / "store", warmup=False))
    with TestClient(app, base_url="http://127.0.0.1") as c:
        assert c.get("/healthz").status_code == 200
        jobs = app.state.jobs
        assert not jobs.cancelled.is_set() and app.state.refine_gate.limiter is app.state.inference_gate.limiter
    assert jobs.cancelled.is_set()


def test_decoded_images_resampled_once(guarded, monkeypatch):
    import rasterizer.yin_yang as yy
    import service.encoder as encoder_module

    calls = []
    real = yy.resize_erp
    spy = lambda *a, **k: calls.append(a[1:]) or real(*a, **k)
    monkeypatch.setattr(yy, "resize_erp", spy)
    monkeypatch.setattr(encoder_module, "resize_erp", spy)
    with guarded.client() as c:
        r = post_scene(c, panorama(height=64, seed=91), panorama(height=64, seed=92))
    assert r.status_code == 201, r.text
    assert calls == [(128, 256), (128, 256)]  # once per image, to the model's size


def test_post_path_skips_jobs_and_the_adaptive_step(guarded, monkeypatch):
    import service.jobs as jobs_module
    import service.pipeline as pipeline_module

    called = []
    monkeypatch.setattr(pipeline_module, "reconstruct_adaptive", lambda *a, **k: called.append("adaptive"))
    own = [n for n, f in vars(jobs_module).items() if callable(f) and getattr(f, "__module__", "") == "service.jobs"
           and not isinstance(f, type)]
    assert "refine_scene" in own
    for name in own:  # no function of the jobs module runs while a scene is created
        monkeypatch.setattr(jobs_module, name, lambda *a, _n=name, **k: called.append(_n))
    with guarded.client() as c:
        r = post_scene(c, panorama(seed=93), panorama(seed=94))
        assert r.status_code == 201, r.text
        assert c.get(f"/v1/scenes/{r.json()['id']}").json()["num_gaussians"] == r.json()["num_gaussians"]
    assert called == []


def test_model_file_hashed_once_at_load(model_path, monkeypatch):
    import service.encoder as encoder_module
    from service.model_files import sha256_file
    from service.runtime import ModelRuntime

    calls = []  # this thread's calls only (an abandoned load of an earlier test may still run)
    me = threading.get_ident()
    monkeypatch.setattr(encoder_module, "sha256_file",
                        lambda p: (threading.get_ident() == me and calls.append(p)) or sha256_file(p))
    runtime = ModelRuntime(model_path)
    runtime.load(warmup=False)
    assert runtime.ready and len(calls) == 1 and runtime.sha256 == sha256_file(model_path)


def test_millimetre_baseline_scene_renders_not_black(guarded):
    """The render's near cull scales with the scene (a fixed 1 cm cull blacked out a 1 mm-baseline scene)."""
    from PIL import Image

    a, b = np.eye(4), np.eye(4)
    b[0, 3] = 1e-3
    poses = json.dumps({"convention": "opencv", "c2w": [a.tolist(), b.tolist()]})
    with guarded.client() as c:
        r = post_scene(c, panorama(seed=95), panorama(seed=95, shift=4), poses=poses)
        assert r.status_code == 201 and r.json()["num_gaussians"] > 0, r.text
        img = c.get(f"/v1/scenes/{r.json()['id']}/render", params={"c2w": IDENTITY, "width": 64})
        assert img.status_code == 200
        pixels = np.asarray(Image.open(io.BytesIO(img.content)))
        assert pixels.mean() > 20 and pixels.std() > 1


def test_far_off_cameras_are_recentred_in_float64(model_path):
    """Cameras 1 km out (recentred for the graph, offset added back in float64) give the scene at the origin, moved."""
    from PIL import Image

    from service.encoder import OnnxEncoder

    enc = OnnxEncoder(model_path)
    img_a = np.asarray(Image.open(io.BytesIO(panorama(seed=96))))
    img_b = np.asarray(Image.open(io.BytesIO(panorama(seed=96, shift=4))))
    a, b = np.eye(4), np.eye(4)
    b[0, 3] = 0.5
    near = enc.reconstruct(img_a, img_b, a, b)
    offset = np.array([1000.0, -700.0, 300.0])
    a[:3, 3] += offset
    b[:3, 3] += offset
    far = enc.reconstruct(img_a, img_b, a, b)
    assert len(far.gaussians) == len(near.gaussians)
    moved = far.gaussians.means.astype(np.float64) - offset
    # float32 at ~1e3 resolves 6e-5: the positions agree to that, not to the offset's rounding in the graph
    assert np.abs(moved - near.gaussians.means).max() < 1e-3
    # and they stay as distinct as float32 storage at ~1e3 allows (nothing collapsed inside the graph)
    stored = (near.gaussians.means[:, 0].astype(np.float64) + offset[0]).astype(np.float32)
    assert len(np.unique(far.gaussians.means[:, 0])) >= 0.99 * len(np.unique(stored))
