"""Regression tests of the HTTP layer's hardening: slow bodies and request slots, protocol errors, HEAD,
multipart framing, image pre-checks, the viewer's key, the API docs and error messages.

Every server here listens on 127.0.0.1 only; slow clients are few and stop by themselves.
"""

from __future__ import annotations

import base64
import hashlib
import io
import json
import logging
import re
import socket
import struct
import threading
import time
import zlib

import httpx
import pytest
import uvicorn
from fastapi import FastAPI
from starlette.responses import JSONResponse

from service.config import Settings
from service.errors import install_error_handlers
from service.limits import BodySizeLimit
from service.server import RedactKeyFilter, server_config
from tests.service._support import POSES, LiveServer, make_settings, new_scene, panorama, post_scene


class TinyServer:
    """uvicorn with the service's protocol (server_config) around a small ASGI app, on 127.0.0.1."""

    def __init__(self, app, **settings) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        config = server_config(app, Settings(**settings), log_level="critical", timeout_keep_alive=5)
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, kwargs={"sockets": [self.sock]}, daemon=True)

    def __enter__(self) -> "TinyServer":
        self.thread.start()
        deadline = time.monotonic() + 20
        while not self.server.started and time.monotonic() < deadline:
            time.sleep(0.02)
        assert self.server.started
        return self

    def __exit__(self, *exc) -> None:
        self.server.should_exit = True
        self.thread.join(10)
        self.sock.close()

    def connect(self) -> socket.socket:
        return socket.create_connection(("127.0.0.1", self.port), timeout=10)


def _read_until_closed(sock: socket.socket, within: float) -> tuple[bytes, bool]:
    """(everything the server sent, whether it closed the connection within ``within`` seconds)."""
    data = b""
    end = time.monotonic() + within
    while time.monotonic() < end:
        sock.settimeout(max(0.01, end - time.monotonic()))
        try:
            chunk = sock.recv(65536)
        except socket.timeout:
            return data, False
        except ConnectionError:
            return data, True
        if not chunk:
            return data, True
        data += chunk
    return data, False


def _head_and_json(data: bytes) -> tuple[bytes, dict]:
    head, _, body = data.partition(b"\r\n\r\n")
    return head, json.loads(body)


def _echo_app():
    app = FastAPI()
    install_error_handlers(app)

    @app.get("/boom")
    async def boom():
        raise RuntimeError("a bug")

    @app.get("/ok")
    async def ok():
        return {"ok": True}

    @app.post("/echo")
    async def echo(request: __import__("fastapi").Request):
        return JSONResponse({"bytes": len(await request.body())})

    return app


@pytest.fixture(scope="module")
def tiny():
    with TinyServer(_echo_app(), max_header_bytes=16 * 1024) as server:
        yield server


# -- protocol: 5xx, oversized headers, CL + TE -------------------------------------------------------

def test_500_says_connection_close_and_closes(tiny):
    sock = tiny.connect()
    try:  # two pipelined requests: the client must learn that the second will not be answered
        sock.sendall(b"GET /boom HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\nGET /ok HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        data, closed = _read_until_closed(sock, 5.0)
    finally:
        sock.close()
    head, body = _head_and_json(data.split(b"HTTP/1.1 200")[0])
    assert head.startswith(b"HTTP/1.1 500") and b"connection: close" in head.lower(), head
    assert body["error"]["code"] == "internal_error" and closed


def test_huge_header_is_431_json_not_a_reset(tiny):
    sock = tiny.connect()
    try:
        sock.sendall(b"GET /ok HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Big: " + b"a" * (1 << 20) + b"\r\n\r\n")
    except ConnectionError:
        pass  # the server may stop reading; its answer must still arrive
    try:
        data, closed = _read_until_closed(sock, 5.0)
    finally:
        sock.close()
    head, body = _head_and_json(data)
    assert head.startswith(b"HTTP/1.1 431"), data[:200]
    assert body["error"]["code"] == "header_too_large" and "16384 bytes" in body["error"]["message"]
    assert closed


def test_content_length_with_transfer_encoding_is_refused(tiny):
    sock = tiny.connect()
    try:
        sock.sendall(b"POST /echo HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: 4\r\nTransfer-Encoding: chunked\r\n"
                     b"\r\n4\r\nabcd\r\n0\r\n\r\nGET /ok HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        data, closed = _read_until_closed(sock, 5.0)
    finally:
        sock.close()
    head, body = _head_and_json(data)
    assert head.startswith(b"HTTP/1.1 400"), data[:200]
    assert "Content-Length and Transfer-Encoding" in body["error"]["message"]
    assert closed and data.count(b"HTTP/1.1") == 1  # the smuggled request is never answered


# -- slow bodies -------------------------------------------------------------------------------------

def _body_app(**limits):
    async def app(scope, receive, send):
        if scope["type"] != "http":
            return
        size = 0
        while True:
            message = await receive()
            size += len(message.get("body", b""))
            if not message.get("more_body", False):
                break
        body = json.dumps({"bytes": size}).encode()
        await send({"type": "http.response.start", "status": 200, "headers": [(b"content-type", b"application/json"),
                                                                          (b"content-length", b"%d" % len(body))]})
        await send({"type": "http.response.body", "body": body})

    return BodySizeLimit(app, max_bytes=1 << 20, timeout_s=60.0, **limits)


def _trickle(port: int, total: int, step: int, pause: float, within: float) -> tuple[bytes, float]:
    sock = socket.create_connection(("127.0.0.1", port), timeout=10)
    t0 = time.monotonic()
    try:
        sock.sendall(b"POST /x HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: %d\r\n\r\n" % total)
        sent = 0
        sock.settimeout(pause)
        data = b""
        while time.monotonic() - t0 < within:
            if sent < total:
                sock.sendall(b"y" * min(step, total - sent))
                sent += min(step, total - sent)
            try:
                chunk = sock.recv(4096)
                if not chunk:
                    break
                data += chunk
                if b"\r\n\r\n{" in data and data.endswith(b"}"):
                    break
            except socket.timeout:
                continue
            except ConnectionError:
                break
        return data, time.monotonic() - t0
    finally:
        sock.close()


def test_body_below_the_minimum_rate_gets_408_after_one_window():
    with TinyServer(_body_app(min_rate=100.0, rate_window_s=1.0)) as server:
        data, seconds = _trickle(server.port, total=200, step=1, pause=0.3, within=8.0)
    head, body = _head_and_json(data)
    assert head.startswith(b"HTTP/1.1 408"), data[:200]
    assert body["error"]["code"] == "request_timeout" and "bytes/s" in body["error"]["message"]
    assert seconds < 4.0  # one window (1 s), not the whole-body deadline (60 s)


def test_body_above_the_minimum_rate_is_read():
    with TinyServer(_body_app(min_rate=100.0, rate_window_s=1.0)) as server:
        data, _ = _trickle(server.port, total=900, step=100, pause=0.3, within=10.0)  # ~330 bytes/s
    head, body = _head_and_json(data)
    assert head.startswith(b"HTTP/1.1 200") and body == {"bytes": 900}, data[:200]


# -- the real app: request slots, readiness, HEAD -------------------------------------------------------

@pytest.fixture(scope="module")
def slots(model_path, tmp_path_factory):
    settings = make_settings(model_path, tmp_path_factory.mktemp("store"), max_requests=2, max_body_readers=3,
                             body_min_rate=0.0, header_timeout_s=5.0, body_timeout_s=30.0)
    with LiveServer(settings) as server:
        yield server


@pytest.fixture(scope="module")
def slots_scene(slots) -> str:
    with slots.client() as c:
        return new_scene(c, seed=141, shift=4)


def _slow_upload(url: str, path: str) -> socket.socket:
    host, port = url.removeprefix("http://").split(":")
    s = socket.create_connection((host, int(port)), timeout=10)
    s.sendall(f"POST {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
              "Content-Length: 1000\r\n\r\n{".encode())
    return s


def test_slow_uploads_fill_upload_slots_not_work_slots(slots, slots_scene):
    socks = [_slow_upload(slots.url, f"/v1/scenes/{slots_scene}/refine") for _ in range(3)]
    try:
        time.sleep(0.5)
        with slots.client() as c:
            for _ in range(3):  # more than max_requests (2) reads, one after another, while the uploads hang
                assert c.get("/v1/info").status_code == 200
                assert c.get(f"/v1/scenes/{slots_scene}").status_code == 200
            render = c.get(f"/v1/scenes/{slots_scene}/render", params={"c2w": ",".join(
                "1,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1".split(",")), "width": 16})
            assert render.status_code == 200
            fourth = c.post(f"/v1/scenes/{slots_scene}/refine", json={})
            assert fourth.status_code == 503 and fourth.json()["error"]["code"] == "busy"
            assert "uploads" in fourth.json()["error"]["message"] and fourth.headers["retry-after"]
            ready = c.get("/readyz")
            assert ready.status_code == 503 and "upload slots" in ready.json()["error"], ready.text
    finally:
        for s in socks:
            s.close()
    deadline = time.monotonic() + 10
    with slots.client() as c:
        while c.get("/readyz").status_code != 200 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert c.get("/readyz").status_code == 200  # the slots are given back when the clients leave


def test_readyz_reports_full_work_slots(slots):
    admission = slots.app.state.admission
    admission.working += admission.max_requests
    try:
        with slots.client() as c:
            r = c.get("/readyz")
            assert r.status_code == 503 and "request slots" in r.json()["error"]
            assert c.get("/healthz").status_code == 200
    finally:
        admission.working -= admission.max_requests


@pytest.mark.parametrize("path", ["/healthz", "/readyz", "/v1/info", "/metrics", "/openapi.json", "SCENE"])
def test_head_answers_like_get_without_a_body(slots, slots_scene, path):
    path = f"/v1/scenes/{slots_scene}" if path == "SCENE" else path
    with slots.client() as c:
        get, head = c.get(path), c.head(path)
    assert get.status_code == head.status_code == 200, head.text
    assert head.content == b"" and head.headers["content-type"] == get.headers["content-type"]
    if path != "/metrics":  # the metrics change between the two requests
        assert head.headers["content-length"] == get.headers["content-length"]


def test_head_requests_are_counted_under_their_route(slots):
    """The metrics listed every HEAD under route "unmatched"."""
    with slots.client() as c:
        assert c.head("/v1/info").status_code == 200
        text = c.get("/metrics").text
    heads = [line for line in text.splitlines() if line.startswith("omnisplat_http_requests_total{")
             and 'method="HEAD"' in line]
    assert any('route="/v1/info"' in line for line in heads), heads


# -- PNG: chunk bombs and truncated image data ---------------------------------------------------------

def _chunk(kind: bytes, payload: bytes) -> bytes:
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(kind + payload))


def _png(width: int, height: int, rows: int | None = None, before_idat: bytes = b"", idat_size: int = 1 << 30,
         interlace: int = 0) -> bytes:
    """An 8-bit RGB PNG (grey ramp) whose compressed stream holds ``rows`` rows (default: all, Adam7 if asked)."""
    import numpy as np
    from PIL import Image

    if interlace:  # let Pillow write the interlaced stream; re-chunk nothing
        buf = io.BytesIO()
        Image.fromarray(np.full((height, width, 3), 90, np.uint8)).save(buf, format="PNG", interlace=1)
        return buf.getvalue()
    row = b"\x00" + bytes(range(256)) * (3 * width // 256) + bytes(3 * width % 256)
    stream = zlib.compress(row * (height if rows is None else rows))
    idat = b"".join(_chunk(b"IDAT", stream[i:i + idat_size]) for i in range(0, len(stream), idat_size))
    ihdr = _chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, interlace))
    return b"\x89PNG\r\n\x1a\n" + ihdr + before_idat + idat + _chunk(b"IEND", b"")


def test_png_with_millions_of_chunks_is_refused_before_pillow(monkeypatch):
    from PIL import Image

    from service.errors import PayloadTooLarge
    from service.images import check_header

    opened = []
    monkeypatch.setattr(Image, "open", lambda *a, **k: opened.append(1))
    bomb = _png(256, 128, before_idat=_chunk(b"prVt", b"") * 200_000)  # 2.4 MB of empty private chunks
    t0 = time.perf_counter()
    with pytest.raises(PayloadTooLarge) as refused:
        check_header(bomb, "image_a", max_pixels=1 << 30, min_height=32)
    assert refused.value.status == 413 and refused.value.code == "image_too_many_chunks"
    assert "image_a" in refused.value.message and opened == []
    assert time.perf_counter() - t0 < 1.0  # stops at the limit, not after 200k chunks
    big_text = _png(256, 128, before_idat=_chunk(b"tEXt", b"c\x00" + b"x" * (17 << 20)))
    with pytest.raises(PayloadTooLarge):
        check_header(big_text, "image_b", max_pixels=1 << 30, min_height=32)


def test_png_split_into_small_idat_chunks_and_interlaced_pngs_still_decode():
    from service.images import decode_rgb

    for (w, h), data in [((256, 128), _png(256, 128, idat_size=64, before_idat=_chunk(b"tEXt", b"k\x00v") * 50)),
                         ((256, 128), _png(256, 128, interlace=1)), ((250, 125), _png(250, 125, interlace=1))]:
        rgb, header = decode_rgb(data, "image_a", max_pixels=1 << 30, min_height=32)
        assert rgb.shape == (h, w, 3) and header.format == "PNG"


def test_png_with_fewer_rows_than_declared_is_400():
    from service.errors import InvalidImage
    from service.images import decode_rgb

    short = _png(8192, 4096, rows=3)
    assert len(short) < 2000
    with pytest.raises(InvalidImage) as refused:
        decode_rgb(short, "image_b", max_pixels=8192 * 4096, min_height=32)
    assert refused.value.status == 400 and refused.value.code == "invalid_image"
    assert "3 of the 4096 rows" in refused.value.message
    with pytest.raises(InvalidImage):  # a few rows short is also refused
        decode_rgb(_png(256, 128, rows=120), "image_b", max_pixels=1 << 30, min_height=32)


def test_truncated_png_upload_is_400_not_a_black_scene(slots):
    with slots.client() as c:
        r = post_scene(c, panorama(seed=142), _png(8192, 4096, rows=3))
    assert r.status_code == 400, r.text
    assert r.json()["error"]["code"] == "invalid_image" and "image_b" in r.json()["error"]["message"]
    assert "truncated" in r.json()["error"]["message"]


def test_jpeg_cut_short_and_closed_with_an_end_marker_is_400_not_a_grey_scene(slots):
    """libjpeg fills the rest of the cut scan with grey and Pillow hides its warning: the upload is refused."""
    jpeg = panorama(seed=143, fmt="JPEG")
    with slots.client() as c:
        r = post_scene(c, panorama(seed=142), jpeg[:len(jpeg) * 6 // 10] + b"\xff\xd9", names=("a.png", "b.jpg"))
    assert r.status_code == 400, r.text
    assert r.json()["error"]["code"] == "invalid_image"
    assert r.json()["error"]["message"].startswith("image_b: the JPEG data is truncated or corrupt")


def test_two_bad_uploads_name_image_a_first(slots):
    """The two uploads decode side by side; the answer names the first bad one, as when they decoded in turn."""
    with slots.client() as c:
        r = post_scene(c, _png(8192, 4096, rows=3), _png(8192, 4096, rows=5))
    assert r.status_code == 400, r.text
    assert "image_a" in r.json()["error"]["message"] and "image_b" not in r.json()["error"]["message"]


# -- multipart framing ----------------------------------------------------------------------------------

def _multipart(parts: list[tuple[str, bytes]], boundary: str = "b0undary", close: bool = True) -> bytes:
    out = b""
    for name, data in parts:
        filename = f'; filename="{name}.png"' if name.startswith("image") else ""
        out += (f'--{boundary}\r\nContent-Disposition: form-data; name="{name}"{filename}\r\n\r\n').encode() + data + b"\r\n"
    return out + (f"--{boundary}--\r\n".encode() if close else b"")


def _post_multipart(server, body: bytes, boundary: str = "b0undary") -> httpx.Response:
    with server.client() as c:
        return c.post("/v1/scenes", content=body, headers={"content-type": f"multipart/form-data; boundary={boundary}"})


def test_multipart_without_its_closing_boundary_is_400(slots):
    parts = [("image_a", panorama(seed=143)), ("image_b", panorama(seed=144)), ("poses", POSES.encode())]
    r = _post_multipart(slots, _multipart(parts, close=False))
    assert r.status_code == 400, r.text
    assert r.json()["error"]["code"] == "incomplete_multipart" and "--b0undary--" in r.json()["error"]["message"]
    whole = _post_multipart(slots, _multipart(parts))  # the same upload, complete
    assert whole.status_code == 201, whole.text


def test_duplicate_form_fields_are_422_naming_the_field(slots):
    for dup in ("poses", "image_a"):
        parts = [("image_a", panorama(seed=145)), ("image_b", panorama(seed=146)), ("poses", POSES.encode())]
        parts.append(next(p for p in parts if p[0] == dup))
        r = _post_multipart(slots, _multipart(parts))
        assert r.status_code == 422, r.text
        assert r.json()["error"]["code"] == "duplicate_field" and repr(dup) in r.json()["error"]["message"]


# -- the viewer's key in logs; error messages -----------------------------------------------------------

def test_access_log_redacts_the_viewer_key():
    import logging

    from service.server import RedactKeyFilter

    server_config(_echo_app(), Settings())
    assert any(isinstance(f, RedactKeyFilter) for f in logging.getLogger("uvicorn.access").filters)
    record = logging.LogRecord("uvicorn.access", logging.INFO, __file__, 1, '%s - "%s %s HTTP/%s" %d',
                               ("127.0.0.1:5", "GET", "/v1/scenes/ab/viewer?fov_deg=70&key=s3cret%21&x=1", "1.1", 303),
                               None)
    assert RedactKeyFilter().filter(record)
    message = record.getMessage()
    assert "s3cret" not in message and "key=<redacted>" in message and "fov_deg=70" in message and "x=1" in message



@pytest.mark.parametrize("query", ["%6Bey=s3cret", "k%65%79=s3cret&x=1", "KEY=s3cret", "fov_deg=70&%6b%45Y=s3cret"])
def test_access_log_redacts_the_viewer_key_under_an_encoded_name(query):
    """The guard reads ``%6Bey`` as ``key`` (and opens the page with it); the log showed it as sent."""
    record = logging.LogRecord("uvicorn.access", logging.INFO, __file__, 1, '%s - "%s %s HTTP/%s" %d',
                               ("127.0.0.1:5", "GET", f"/v1/scenes/ab/viewer?{query}", "1.1", 303), None)
    assert RedactKeyFilter().filter(record)
    assert "s3cret" not in record.getMessage() and "<redacted>" in record.getMessage(), record.getMessage()


def test_viewer_unavailable_names_no_server_path(slots, slots_scene, monkeypatch):
    monkeypatch.setenv("OMNISPLAT_NODE_MODULES", "/nonexistent-omnisplat-test/node_modules")
    with slots.client() as c:
        r = c.get(f"/v1/scenes/{slots_scene}/viewer")
    assert r.status_code == 503 and r.json()["error"]["code"] == "viewer_unavailable"
    assert "nonexistent-omnisplat-test" not in r.text and "three/build/three.module.js" in r.text


# -- the API docs, served locally ----------------------------------------------------------------------

def test_docs_page_and_its_files_are_served_locally_without_a_key(model_path, tmp_path):
    settings = make_settings(model_path, tmp_path / "store", api_key="s3cret", warmup=False)
    with LiveServer(settings) as server, server.client() as c:
        page = c.get("/docs")
        assert page.status_code == 200 and "swagger-ui" in page.text
        assert "http://" not in page.text and "https://" not in page.text, "the page loads nothing from elsewhere"
        for asset in ("swagger-ui-bundle.js", "swagger-ui.css", "favicon-32x32.png"):
            assert f"/docs/assets/{asset}" in page.text
            r = c.get(f"/docs/assets/{asset}")
            assert r.status_code == 200 and len(r.content) > 500, asset
        assert c.get("/docs/assets/package.json").status_code == 404  # only the listed files
        assert c.get("/openapi.json").status_code == 200  # open by design (see service.access)
        assert c.get("/docs/oauth2-redirect").status_code == 200
        assert c.get("/v1/info").status_code == 401  # the rest still needs the key
        assert c.get("/redoc").status_code in (401, 404)  # not served (its page loads from CDNs)


def _csp(header: str) -> dict[str, list[str]]:
    return {d.split()[0]: d.split()[1:] for d in header.split(";") if d.strip()}


def _inline_script_hashes(page: str) -> set[str]:
    """``'sha256-...'`` of each inline script a browser runs (an import map is one; JSON data is not)."""
    scripts = re.findall(r"<script( [^>]*)?>(.*?)</script>", page, re.S)
    return {f"'sha256-{base64.b64encode(hashlib.sha256(code.encode()).digest()).decode()}'"
            for attrs, code in scripts if "src=" not in attrs and "application/json" not in attrs}


def test_viewer_and_docs_pages_refuse_framing_and_run_only_their_own_scripts(slots, slots_scene):
    """Neither page said whether it may be framed (another site could lay it under a decoy and have its links,
    or Swagger UI's *Try it out* with the viewer's cookie, clicked unseen), nor which scripts may run, and no answer
    said nosniff."""
    with slots.client() as c:
        for url in (f"/v1/scenes/{slots_scene}/viewer", "/docs"):
            r = c.get(url)
            assert r.status_code == 200, r.text
            csp = _csp(r.headers["content-security-policy"])
            assert csp["frame-ancestors"] == ["'none'"] and r.headers["x-frame-options"] == "DENY", url
            assert csp["object-src"] == ["'none'"] and csp["base-uri"] == ["'none'"], url
            script_src = set(csp["script-src"])
            assert "'unsafe-inline'" not in script_src and "'unsafe-eval'" not in script_src, url
            inline = _inline_script_hashes(r.text)
            assert inline and inline <= script_src, (url, inline, script_src)  # the page's own inline scripts run
            assert r.headers["x-content-type-options"] == "nosniff", url
        for url in ("/viewer-assets/viewer.js", "/viewer-assets/three.module.js", "/docs/assets/swagger-ui.css"):
            assert c.get(url).headers["x-content-type-options"] == "nosniff", url


def test_docs_without_the_npm_package_is_503_json(slots, monkeypatch):
    monkeypatch.setenv("OMNISPLAT_NODE_MODULES", "/nonexistent-omnisplat-test/node_modules")
    with slots.client() as c:
        r = c.get("/docs")
        assert r.status_code == 503 and r.json()["error"]["code"] == "docs_unavailable"
        assert "nonexistent-omnisplat-test" not in r.text
        assert c.get("/openapi.json").status_code == 200


def test_image_errors_name_the_file_not_library_internals(monkeypatch):
    import numpy as np
    from PIL import Image

    from service.errors import InvalidImage
    from service.images import decode_rgb

    buf = io.BytesIO()
    Image.fromarray(np.full((64, 128, 3), 80, np.uint8)).save(buf, format="WEBP")
    with pytest.raises(InvalidImage) as half:  # libwebp: "could not create decoder object"
        decode_rgb(buf.getvalue()[: len(buf.getvalue()) // 2], "image_a", max_pixels=1 << 30, min_height=32)
    assert half.value.message.startswith("image_a: ") and "decoder" not in half.value.message

    def internal(*a, **k):
        raise ValueError("ufunc 'isfinite' not supported for the input types")

    monkeypatch.setattr(Image, "open", internal)
    with pytest.raises(InvalidImage) as raised:
        decode_rgb(_png(256, 128), "image_b", max_pixels=1 << 30, min_height=32)
    assert "ufunc" not in raised.value.message and "image_b" in raised.value.message


def test_body_that_arrives_when_every_work_slot_is_taken_is_503():
    import anyio

    from service.access import AccessGuard

    ran = []

    async def app(scope, receive, send):
        while (await receive()).get("more_body"):
            pass
        ran.append(scope["path"])
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": b"ran"})

    class State:
        inference_gate = None

    guard = AccessGuard(app, Settings(max_requests=1, max_body_readers=2), State)
    scope = {"type": "http", "method": "POST", "path": "/v1/scenes/x/refine", "query_string": b"",
             "headers": [(b"host", b"127.0.0.1"), (b"content-length", b"2")]}
    sent: list[dict] = []

    async def main():
        first = anyio.Event()
        chunks = [{"type": "http.request", "body": b"a", "more_body": True},
                  {"type": "http.request", "body": b"b", "more_body": False}]

        async def receive():
            if len(chunks) == 1:  # between the two chunks, another request takes the only work slot
                first.set()
                guard.admission.working += 1
            return chunks.pop(0)

        async def send(message):
            sent.append(message)

        assert guard.admission.problem() is None
        await guard(scope, receive, send)
        assert first.is_set() and guard.admission.reading == 0
        guard.admission.working -= 1

    anyio.run(main)
    assert ran == [] and sent[0]["status"] == 503 and b"busy" in sent[1]["body"]
    assert guard.admission.working == 0 and guard.admission.reading == 0


def test_jpeg_with_millions_of_metadata_segments_or_padding_is_refused_before_pillow(monkeypatch):
    import numpy as np
    from PIL import Image

    from service.errors import PayloadTooLarge
    from service.images import check_header

    buf = io.BytesIO()
    Image.fromarray(np.full((128, 256, 3), 70, np.uint8)).save(buf, format="JPEG", icc_profile=b"p" * 100_000,
                                                               comment=b"a comment")
    jpeg = buf.getvalue()
    assert check_header(jpeg, "image_a", max_pixels=1 << 30, min_height=32).format == "JPEG"  # real metadata passes
    opened = []
    monkeypatch.setattr(Image, "open", lambda *a, **k: opened.append(1))
    for bomb in (jpeg[:2] + b"\xff\xef\x00\x02" * 300_000 + jpeg[2:],  # empty APP15 segments (Pillow keeps each)
                 jpeg[:2] + b"\xff" * 5_000_000 + jpeg[2:], jpeg[:2] + b"\x00" * 5_000_000 + jpeg[2:]):
        t0 = time.perf_counter()
        with pytest.raises(PayloadTooLarge) as refused:
            check_header(bomb, "image_a", max_pixels=1 << 30, min_height=32)
        assert refused.value.code == "image_too_many_chunks" and time.perf_counter() - t0 < 1.0
    assert opened == []
