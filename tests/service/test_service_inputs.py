"""Input validation units: images, poses, options, render queries, body limit, work gate."""

from __future__ import annotations

import io
import json

import anyio
import httpx
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image
from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import JSONResponse
from starlette.routing import Route

from rasterizer.render import to_uint8
from service.errors import BadInput, Busy, InvalidImage, PayloadTooLarge
from service.images import check_header, decode_rgb, encode
from service.inputs import check_render_query, parse_c2w_query, parse_options, parse_poses
from service.limits import BodySizeLimit, WorkGate

LIMITS = {"max_pixels": 4096 * 2048, "min_height": 32}


def png(w: int, h: int, mode: str = "RGB") -> bytes:
    buf = io.BytesIO()
    Image.new(mode, (w, h), 128).save(buf, format="PNG")
    return buf.getvalue()


def test_decode_good_png_and_jpeg():
    arr, head = decode_rgb(png(256, 128), "image_a", **LIMITS)
    assert arr.shape == (128, 256, 3) and arr.dtype == np.uint8 and head.format == "PNG"
    buf = io.BytesIO()
    Image.new("L", (200, 100), 10).save(buf, format="JPEG")
    arr, head = decode_rgb(buf.getvalue(), "image_b", **LIMITS)
    assert arr.shape == (100, 200, 3) and head.format == "JPEG"


@pytest.mark.parametrize("w,h,exc,code", [
    (300, 128, BadInput, "bad_aspect_ratio"),
    (128, 128, BadInput, "bad_aspect_ratio"),
    (257, 128, BadInput, "bad_aspect_ratio"),
    (32, 16, BadInput, "image_too_small"),
])
def test_bad_sizes(w, h, exc, code):
    with pytest.raises(exc) as info:
        check_header(png(w, h), "image_a", **LIMITS)
    assert info.value.code == code and "image_a" in info.value.message


def test_pixel_cap_is_checked_from_the_header():
    # a 16384x8192 PNG of one colour is tiny on disk but 134M pixels decoded
    data = png(16384, 8192, "L")
    assert len(data) < 1_000_000
    with pytest.raises(PayloadTooLarge) as info:
        decode_rgb(data, "image_a", **LIMITS)
    assert info.value.code == "image_too_many_pixels"


@pytest.mark.parametrize("data", [b"", b"not an image at all", b"\x89PNG\r\n\x1a\n" + b"\0" * 40])
def test_unreadable(data):
    with pytest.raises(InvalidImage):
        decode_rgb(data, "image_b", **LIMITS)


def test_truncated_png():
    rng = np.random.default_rng(0)
    buf = io.BytesIO()
    Image.fromarray(rng.integers(0, 255, (128, 256, 3), dtype=np.uint8)).save(buf, format="PNG")
    data = buf.getvalue()
    check_header(data[: len(data) // 2], "image_a", **LIMITS)  # the header alone is fine...
    with pytest.raises(InvalidImage) as info:  # ...the pixels are not
        decode_rgb(data[: len(data) // 2], "image_a", **LIMITS)
    assert "truncated" in info.value.message or "corrupt" in info.value.message


def test_nan_never_reaches_pixels():
    colour = np.full((4, 8, 3), np.nan, np.float32)
    colour[0, 0] = [np.inf, -np.inf, 2.0]
    out = to_uint8(colour)
    assert out.dtype == np.uint8 and out[1, 1].tolist() == [0, 0, 0] and out[0, 0].tolist() == [255, 0, 255]
    assert Image.open(io.BytesIO(encode(out, "png"))).size == (8, 4)
    assert Image.open(io.BytesIO(encode(out, "jpeg"))).format == "JPEG"


I4 = np.eye(4).tolist()


def _poses(a, b, convention="opencv"):
    return json.dumps({"convention": convention, "c2w": [a, b]})


def _moved(x=0.5):
    m = np.eye(4)
    m[0, 3] = x
    return m.tolist()


def test_poses_ok_and_opengl():
    p = parse_poses(_poses(I4, _moved()))
    assert np.allclose(p.c2w_b[:3, 3], [0.5, 0, 0])
    g = parse_poses(_poses(I4, np.eye(4)[:3].tolist() and _moved(), "opengl"))
    assert np.allclose(g.c2w_a, np.diag([1, -1, -1, 1]))
    three_by_four = parse_poses(_poses(np.eye(4)[:3].tolist(), _moved()))
    assert three_by_four.c2w_a.shape == (4, 4)


@pytest.mark.parametrize("text,code", [
    ("{", "invalid_poses"),
    ("[]", "invalid_poses"),
    (json.dumps({"convention": "colmap", "c2w": [I4, I4]}), "invalid_poses"),
    (json.dumps({"c2w": [I4]}), "invalid_poses"),
    (_poses(I4, I4), "identical_camera_centres"),
    (_poses(I4, (2 * np.eye(4)).tolist()), "invalid_pose"),  # scaled, not rigid
    (_poses(I4, np.diag([1, 1, -1, 1]).tolist()), "invalid_pose"),  # mirror
    (_poses(I4, [[1, 0, 0]]), "invalid_pose"),
    (_poses(I4, [["a", 0, 0, 0]] * 4), "invalid_pose"),
    ('{"c2w": [[[NaN,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]], []]}', "invalid_poses"),
])
def test_bad_poses(text, code):
    with pytest.raises(BadInput) as info:
        parse_poses(text)
    assert info.value.code == code, info.value.message


@pytest.mark.parametrize("convention, shown", [(None, "null"), (True, "true"), ("OpenGL", '"OpenGL"'), (1, "1")])
def test_a_bad_convention_is_quoted_as_sent(convention, shown):
    """The message shows the convention in the JSON the client wrote (null, not Python's None)."""
    with pytest.raises(BadInput) as info:
        parse_poses(json.dumps({"convention": convention, "c2w": [I4, _moved()]}))
    assert info.value.message == f'poses.convention: expected "opencv" or "opengl", got {shown}'


@pytest.mark.parametrize("key", ["convension", "C2W", "c2w_b", "scale"])
def test_unknown_pose_keys_are_422_naming_them(key):
    obj = {"convention": "opengl", "c2w": [I4, _moved()], key: "opengl"}
    if key == "convension":  # the misspelt key must not silently leave the matrices read as OpenCV
        del obj["convention"]
    with pytest.raises(BadInput) as info:
        parse_poses(json.dumps(obj))
    assert info.value.code == "invalid_poses" and key in info.value.message


@pytest.mark.parametrize("parse, text, key", [
    (parse_poses, '{"convention": "opengl", "c2w": null, "convention": "opencv"}', "convention"),
    (parse_options, '{"near": 0.5, "far": 9, "near": 2}', "near"),
    (parse_options, '{"compaction": {"max_count": 5, "max_count": 6}}', "max_count"),
])
def test_a_json_key_given_twice_is_422_naming_it(parse, text, key):
    """json.loads keeps the last of two equal keys without a word."""
    with pytest.raises(BadInput) as info:
        parse(text)
    assert info.value.code.startswith("invalid_") and f"{key!r} is given more than once" in info.value.message


def test_metadata_poses_can_be_sent_back():
    given = parse_poses(_poses(I4, _moved(), "opengl"))
    meta = {**given.as_json(), "source": "given", "support": {"applied": False}}  # what GET /v1/scenes/{id} shows
    again = parse_poses(json.dumps(meta))
    assert np.array_equal(again.c2w_a, given.c2w_a) and np.array_equal(again.c2w_b, given.c2w_b)


def test_nan_pose_in_matrix():
    with pytest.raises(BadInput):
        parse_poses(json.dumps({"c2w": [I4, [[float("nan")] * 4] * 4]}).replace("NaN", "1e999"))


def test_options():
    assert parse_options(None, None)[0] == {}
    raw, parsed, _ = parse_options('{"near": 0.2, "far": 9}', {"near", "far"})
    assert raw == {"near": 0.2, "far": 9} and (parsed.near, parsed.far) == (0.2, 9)
    assert parsed.sh_degree == 1 and parse_options('{"sh_degree": 0}', None)[1].sh_degree == 0
    assert parsed.rig_cap_deg is None  # automatic: the encoder resolves it (rasterizer.rig.resolve_rig_cap)
    assert parse_options('{"rig_cap_deg": null}', None)[1].rig_cap_deg is None
    assert parse_options('{"rig_cap_deg": 20}', None)[1].rig_cap_deg == 20.0
    for bad in ['{"near": -1}', '{"near": 5, "far": 1}', '[1]', '{"x": [1]}', '{"near": "a"}',
                '{"min_opacity": "abc"}', '{"min_opacity": 1.5}', '{"near": true}', '{"sh_degree": 2}',
                '{"sh_degree": 0.5}', '{"sh_degree": -1}', '{"rig_cap_deg": 46}', '{"rig_cap_deg": -5}',
                '{"rig_cap_deg": "20"}', '{"rig_cap_deg": true}']:
        with pytest.raises(BadInput):
            parse_options(bad, None)
    with pytest.raises(BadInput) as info:
        parse_options('{"planes": 3}', {"near", "far"})
    assert "planes" in info.value.message


def test_c2w_query():
    assert parse_c2w_query(",".join(["1", "0", "0", "0", "0", "1", "0", "0", "0", "0", "1", "0"])).shape == (4, 4)
    for bad in ["1,2,3", "nan," * 15 + "nan", ",".join(["x"] * 16), ",".join(["2"] * 16), "inf" + ",0" * 15]:
        with pytest.raises(BadInput):
            parse_c2w_query(bad)


ROW_MAJOR_TAIL = ",0,1,0,0,0,0,1,0,0,0,0,1"


@pytest.mark.parametrize("first", ["1_0", "１", "٣", "1.0_0", "0x1", "", "1e", "--1"])
def test_c2w_numbers_are_plain_decimals(first):
    """A c2w entry Python's float reads but a decimal number is not (digit groups read as 10, non-ASCII digits) is a
    422 naming the entry: the viewer page, and most clients, read no number there."""
    with pytest.raises(BadInput, match="entry 4 .* is not a number"):
        parse_c2w_query("1,0,0," + first + ROW_MAJOR_TAIL)


def test_c2w_numbers_take_every_plain_decimal_spelling():
    for x, value in [("+0.5", 0.5), (".5", 0.5), ("5.", 5.0), ("-2.5E-1", -0.25), (" 3 ", 3.0), ("1e2", 100.0)]:
        assert parse_c2w_query("1,0,0," + x + ROW_MAJOR_TAIL)[0, 3] == value


IDENT = ",".join(str(v) for v in np.eye(4).ravel())


@pytest.mark.parametrize("projection,width,height,fov", [
    ("erp", 0, None, None), ("erp", 1023, None, None), ("erp", 10**9, None, None), ("yin", 100, None, None),
    ("perspective", 64, 0, 90), ("perspective", 64, 64, 0), ("perspective", 64, 64, float("nan")),
    ("erp", 64, 32, None), ("erp", 64, None, 90), ("yang", 96, None, 60), ("fisheye", 64, None, None),
])
def test_bad_render_queries(projection, width, height, fov):
    with pytest.raises(BadInput):
        check_render_query(IDENT, projection, width, height, fov, "png", max_width=4096, max_pixels=4096 * 2048)


def test_render_query_sizes():
    q = check_render_query(IDENT, "yin", 96, None, None, "png", max_width=4096, max_pixels=10**7)
    assert q.output_size() == (32, 96)
    q = check_render_query(IDENT, "perspective", 64, None, 60, "jpeg", max_width=4096, max_pixels=10**7)
    assert q.output_size() == (64, 64)
    with pytest.raises(BadInput):
        check_render_query(IDENT, "perspective", 4096, 4096, 60, "png", max_width=4096, max_pixels=4096 * 2048)


@pytest.mark.parametrize("offset", [1e6, -1e6, 1.01e6, 1e15, -1e300])
def test_render_cameras_lie_within_the_scene_extent(offset):
    """A render camera obeys the bound of the scenes' own cameras (float32 cannot resolve a room from 1e15 m
    away: the image would be noise, not the scene)."""
    from rasterizer.sweep import MAX_SCENE_EXTENT

    c2w = ",".join(str(v) for v in [1, 0, 0, offset, 0, 1, 0, 0.5, 0, 0, 1, 0, 0, 0, 0, 1])
    if abs(offset) <= MAX_SCENE_EXTENT:
        assert check_render_query(c2w, "erp", 64, None, None, "png", max_width=4096, max_pixels=10**7).c2w[0, 3] == offset
    else:
        with pytest.raises(BadInput, match="from the origin"):
            check_render_query(c2w, "erp", 64, None, None, "png", max_width=4096, max_pixels=10**7)


@settings(max_examples=200, deadline=None)
@given(st.integers(1, 4096), st.integers(1, 4096), st.floats(1.0, 170.0))
def test_perspective_views_never_span_more_than_the_fov_limit_vertically(width, height, fov):
    """A tall, narrow view (1 x 640 at 120 deg spans 179.9 deg vertically) rendered rows of black: refused."""
    vertical = np.degrees(2 * np.arctan(np.tan(np.radians(fov) / 2) * height / width))
    try:
        check_render_query(IDENT, "perspective", width, height, fov, "png", max_width=4096, max_pixels=4096 * 4096)
    except BadInput as exc:
        assert vertical > 170.0 - 1e-9 and "vertically" in exc.message and exc.code == "invalid_render_query"
    else:
        assert vertical <= 170.0 + 1e-9


# -- ASGI body limit and work gate, on a bare Starlette app ------------------------------

async def _echo(request: Request):
    try:
        body = await request.body()
    except Exception:
        return JSONResponse({"app": "error"}, status_code=400)
    return JSONResponse({"n": len(body)})


def _client(limit: int) -> httpx.AsyncClient:
    app = BodySizeLimit(Starlette(routes=[Route("/", _echo, methods=["POST"])]), limit)
    return httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://t")


def test_body_limit_content_length_and_streaming():
    async def main():
        async with _client(1000) as c:
            ok = await c.post("/", content=b"x" * 1000)
            assert ok.status_code == 200 and ok.json() == {"n": 1000}
            big = await c.post("/", content=b"x" * 1001)
            assert big.status_code == 413 and big.json()["error"]["code"] == "payload_too_large"

            async def chunks():
                for _ in range(10):
                    yield b"y" * 300

            streamed = await c.post("/", content=chunks())  # chunked: no Content-Length
            assert streamed.status_code == 413, streamed.text
            assert streamed.json()["error"]["code"] == "payload_too_large"

    anyio.run(main)


def test_work_gate_rejects_past_queue():
    async def main():
        gate = WorkGate("inference", concurrency=1, queue=1, retry_after=7)
        release = anyio.Event()
        results = []

        def block():
            anyio.from_thread.run(release.wait)
            return "done"

        async def job():
            try:
                results.append(await gate.run(block))
            except Busy as exc:
                results.append(exc)

        async with anyio.create_task_group() as tg:
            for _ in range(3):
                tg.start_soon(job)
            await anyio.sleep(0.2)
            assert gate.running == 1 and gate.waiting == 1
            release.set()
        busy = [r for r in results if isinstance(r, Busy)]
        assert results.count("done") == 2 and len(busy) == 1
        assert busy[0].status == 503 and busy[0].headers["Retry-After"] == "7"
        assert gate.admitted == 0 and gate.rejected == 1

    anyio.run(main)


# -- hardening regressions --------------------------------------------------------------

HUGE = "1" + "0" * 399


@pytest.mark.parametrize("options", [f'{{"near": {HUGE}}}', f'{{"far": {HUGE}}}', f'{{"min_opacity": {HUGE}}}',
                                     f'{{"adaptive_range": {{"margin": {HUGE}}}}}',
                                     f'{{"compaction": {{"max_count": {HUGE}}}}}'])
def test_huge_json_integers_are_422_before_any_work(options):
    with pytest.raises(BadInput) as info:
        parse_options(options, None)
    assert info.value.status == 422 and "digits" in info.value.message


def test_huge_integer_in_a_pose_is_422():
    a = np.eye(4).tolist()
    text = json.dumps({"c2w": [a, a]}).replace("0.0", HUGE, 1)
    with pytest.raises(BadInput) as info:
        parse_poses(text)
    assert "digits" in info.value.message


@pytest.mark.parametrize("t0, base", [(0.0, 1e20), (1e7, 0.5), (1e308, 1.0), (0.0, 1e-5), (1e5, 0.5)])
def test_poses_float32_cannot_resolve_are_422(t0, base):
    a, b = np.eye(4), np.eye(4)
    a[0, 3], b[0, 3] = t0, t0 + base
    with pytest.raises(BadInput) as info:
        parse_poses(json.dumps({"c2w": [a.tolist(), b.tolist()]}))
    assert "inf" not in info.value.message.lower()


def test_min_baseline_is_the_encoders():
    from rasterizer.sweep import MIN_BASELINE

    a, b = np.eye(4), np.eye(4)
    b[0, 3] = MIN_BASELINE
    parse_poses(json.dumps({"c2w": [a.tolist(), b.tolist()]}))  # the encoder accepts it too
    b[0, 3] = MIN_BASELINE * 0.99
    with pytest.raises(BadInput):
        parse_poses(json.dumps({"c2w": [a.tolist(), b.tolist()]}))


@pytest.mark.parametrize("options", ['{"near": 1e-300}', '{"far": 1e300}', '{"near": 1e-300, "far": 1e300}'])
def test_sweep_range_out_of_scale_is_422(options):
    from service.inputs import check_sweep_range

    poses = parse_poses(_poses(I4, _moved(0.5)))
    raw, *_ = parse_options(options, None)
    with pytest.raises(BadInput) as info:
        check_sweep_range(poses.c2w_a, poses.c2w_b, raw)
    assert "baseline" in info.value.message


@given(st.floats(min_value=-1e4, max_value=1e4), st.floats(min_value=1e-3, max_value=1e3))
@settings(max_examples=60, deadline=None)
def test_accepted_poses_keep_float32_precision(t0, base):
    """Any pose pair the API accepts has float32 positions resolving 1/1000 of the baseline."""
    a, b = np.eye(4), np.eye(4)
    a[0, 3], b[0, 3] = t0, t0 + base
    try:
        parse_poses(json.dumps({"c2w": [a.tolist(), b.tolist()]}))
    except BadInput:
        return
    reach = max(abs(t0), abs(t0 + base)) + 20 * base
    assert np.spacing(np.float32(reach)) <= 1e-3 * base


def _encoded(arr, fmt):
    buf = io.BytesIO()
    Image.fromarray(arr).save(buf, format=fmt)
    return buf.getvalue()


def test_16bit_greyscale_png_is_scaled_by_its_range():
    grey = (np.linspace(0, 65535, 64 * 128).reshape(64, 128)).astype(np.uint16)
    rgb, _ = decode_rgb(_encoded(grey, "PNG"), "image_a", **LIMITS)
    assert rgb.shape == (64, 128, 3)
    expected = np.rint(grey / 65535.0 * 255).astype(np.uint8)
    assert np.abs(rgb[..., 0].astype(int) - expected).max() <= 1
    assert 100 < rgb.mean() < 155  # not the 99.8 % white of a clipping conversion


def test_float_tiff_in_unit_range_is_scaled_and_out_of_range_refused():
    f = np.linspace(0, 1, 64 * 128, dtype=np.float32).reshape(64, 128)
    rgb, _ = decode_rgb(_encoded(f, "TIFF"), "image_a", **LIMITS)
    assert np.abs(rgb[..., 1].astype(int) - np.rint(f * 255)).max() <= 1 and rgb.max() == 255
    with pytest.raises(InvalidImage) as info:
        decode_rgb(_encoded(f * 300, "TIFF"), "image_a", **LIMITS)
    assert "[0, 1]" in info.value.message


def test_transparent_pixels_are_refused_and_opaque_alpha_passes():
    """The colour under a transparent pixel is undefined: refused with the share, not used silently."""
    rng = np.random.default_rng(0)
    rgba = np.concatenate([rng.integers(0, 255, (64, 128, 3), dtype=np.uint8), np.full((64, 128, 1), 255, np.uint8)], 2)
    rgb, _ = decode_rgb(_encoded(rgba, "PNG"), "image_a", **LIMITS)  # alpha 255 everywhere: an opaque export
    np.testing.assert_array_equal(rgb, rgba[..., :3])
    rgba[48:, :, 3] = 0  # a transparent nadir
    grey_alpha = np.stack([rgba[..., 0], rgba[..., 3]], axis=2)
    palette = Image.fromarray(rgba[..., :3]).quantize(16)
    palette.info["transparency"] = 0
    buf = io.BytesIO()
    palette.save(buf, format="PNG", transparency=0)
    for data in (_encoded(rgba, "PNG"), _encoded(grey_alpha, "PNG"), buf.getvalue()):
        with pytest.raises(BadInput) as info:
            decode_rgb(data, "image_b", **LIMITS)
        assert info.value.status == 422 and info.value.code == "transparent_image"
        assert info.value.message.startswith("image_b:") and "transparent" in info.value.message


def test_bomb_message_quotes_our_limit():
    from PIL import Image as PILImage

    big = _encoded(np.zeros((64, 128), np.uint8), "PNG")
    old = PILImage.MAX_IMAGE_PIXELS
    PILImage.MAX_IMAGE_PIXELS = 100  # Pillow's own guard fires first (2x its limit)
    try:
        with pytest.raises(PayloadTooLarge) as info:
            check_header(big, "image_a", max_pixels=5000, min_height=2)
    finally:
        PILImage.MAX_IMAGE_PIXELS = old
    assert "5000" in info.value.message and "100" not in info.value.message.replace("5000", "")
