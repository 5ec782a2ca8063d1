"""Regression tests of the API audit: query parameters a route would drop, conditional requests on the
immutable responses (render, PLY), and messages that named library internals or misled."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.service._support import IDENTITY, POSES, edit_server, new_scene, panorama, stored_scene_count

PERSPECTIVE = [("c2w", IDENTITY), ("projection", "perspective"), ("width", "32")]
ERP = [("c2w", IDENTITY), ("width", "64")]


@pytest.fixture(scope="module")
def live(model_path, tmp_path_factory):
    with edit_server(model_path, tmp_path_factory.mktemp("store")) as server:  # renders up to 512 x 256
        yield server


@pytest.fixture(scope="module")
def scene(client) -> str:
    return new_scene(client, seed=81, shift=4)


@pytest.fixture(scope="module")
def selection(client, scene) -> str:
    r = client.post(f"/v1/scenes/{scene}/selections", json={"view": "a", "points": [[0.5, 0.6]]})
    assert r.status_code == 201, r.text
    return r.json()["id"]


# -- unknown query parameters ---------------------------------------------------------------------------

@pytest.mark.parametrize("path, params, extra, accepted", [
    ("render", PERSPECTIVE, ("fov", "30"), "fov_deg"),  # the parameter is fov_deg
    ("render", ERP, ("fromat", "jpeg"), "format"),
    ("render", ERP, ("Width", "32"), "width"),
    ("MASK", [("view", "a"), ("width", "64")], ("format", "jpeg"), "view"),  # a mask is always a PNG
    ("MASK", [("view", "a"), ("width", "64")], ("compositing", "va"), "view"),
    ("MASK", ERP, ("rig", "true"), "c2w"),
    ("segments", [("view", "a"), ("width", "64")], ("format", "jpeg"), "view"),
    ("gaussians.ply", [], ("format", "ply"), "no query parameters"),
    ("", [], ("verbose", "1"), "no query parameters"),
    ("viewer", [], ("fov", "60"), "fov_deg"),
])
def test_unknown_query_parameter_is_422_naming_it_and_the_accepted_ones(client, scene, selection, path, params,
                                                                         extra, accepted):
    """A misspelt parameter was dropped: fov=30 rendered the default 90 degrees, fromat=jpeg a PNG."""
    path = f"selections/{selection}/mask" if path == "MASK" else path
    url = f"/v1/scenes/{scene}/{path}".rstrip("/")
    if path != "viewer":  # the viewer page needs the npm packages; the query is checked before
        assert client.get(url, params=params).status_code == 200
    r = client.get(url, params=params + [extra])
    assert r.status_code == 422, r.text
    err = r.json()["error"]
    assert err["code"] == "unknown_query_parameter" and repr(extra[0]) in err["message"], err
    assert accepted in err["message"], err


def test_unknown_query_parameter_on_jobs_and_post_routes_is_422(client, scene):
    r = client.get(f"/v1/jobs/{'0' * 32}", params={"wait": "1"})
    assert r.status_code == 422 and r.json()["error"]["code"] == "unknown_query_parameter", r.text
    r = client.post(f"/v1/scenes/{scene}/refine", params={"iterations": "5"}, json={"iterations": 1})
    assert r.status_code == 422 and "'iterations'" in r.json()["error"]["message"], r.text


def test_viewer_takes_its_documented_query(client, scene):
    """The page's script reads c2w, fov_deg, width and height: they are accepted, not refused as unknown."""
    r = client.get(f"/v1/scenes/{scene}/viewer", params={"c2w": IDENTITY, "fov_deg": "60", "width": "640",
                                                          "height": "480"})
    assert r.status_code in (200, 503), r.text  # 503: the npm packages are not installed here
    assert r.status_code == 200 or r.json()["error"]["code"] == "viewer_unavailable"


# -- conditional requests -------------------------------------------------------------------------------

def _etag_variants(etag: str) -> list[str]:
    return [etag, f"W/{etag}", f'"nope", {etag}', f'W/"x",W/{etag}', "*"]


@pytest.mark.parametrize("path, params", [("render", ERP), ("render", PERSPECTIVE + [("format", "jpeg")]),
                                          ("gaussians.ply", [])])
def test_if_none_match_is_304_without_a_body(client, scene, path, params):
    url = f"/v1/scenes/{scene}/{path}"
    full = client.get(url, params=params)
    assert full.status_code == 200 and full.headers["accept-ranges"] == "none"
    etag = full.headers["etag"]
    for value in _etag_variants(etag):
        r = client.get(url, params=params, headers={"If-None-Match": value})
        assert r.status_code == 304, (value, r.status_code)
        assert r.content == b"" and r.headers["etag"] == etag
        assert r.headers["cache-control"] == full.headers["cache-control"]
    for value in ('"other"', 'W/"other", "nope"', etag[:-2] + '"'):
        r = client.get(url, params=params, headers={"If-None-Match": value})
        assert r.status_code == 200 and r.content == full.content, value


@pytest.mark.parametrize("path, params", [("render", ERP), ("gaussians.ply", []), ("gaussians.spz", [])])
def test_scene_files_are_cached_by_the_browser_only(client, scene, path, params):
    """A shared cache (a proxy, a CDN) may keep a ``public`` answer to a request with a key or the viewer's cookie
    and give it to anyone without one, and keeps a deleted scene's files for a year: ``private``."""
    r = client.get(f"/v1/scenes/{scene}/{path}", params=params)
    assert r.status_code == 200, r.text
    directives = {d.strip() for d in r.headers["cache-control"].split(",")}
    assert directives == {"private", "max-age=31536000", "immutable"}, directives


def test_render_304_does_not_render(client, live, scene, monkeypatch):
    etag = client.get(f"/v1/scenes/{scene}/render", params=ERP).headers["etag"]
    from service import scenes as work

    def no_render(*args, **kwargs):
        raise AssertionError("rendered for a 304")

    monkeypatch.setattr(work, "render_scene", no_render)
    r = client.get(f"/v1/scenes/{scene}/render", params=ERP, headers={"If-None-Match": etag})
    assert r.status_code == 304
    other = client.get(f"/v1/scenes/{scene}/render", params=[("c2w", IDENTITY), ("width", "32")],
                       headers={"If-None-Match": etag})
    assert other.status_code == 500  # another view: its ETag differs, so it renders (here: the stub)


def test_a_render_etag_changes_with_the_renderer(client, scene, monkeypatch):
    """Immutable renders are cached by their ETag: a renderer whose images differ (its settings or its code)
    must not answer a client's old copy with a 304."""
    from service import http_cache, inputs

    url = f"/v1/scenes/{scene}/render"
    etag = client.get(url, params=ERP).headers["etag"]
    monkeypatch.setattr(inputs, "RENDER_CUT_SIGMA", 3.0)
    cut = client.get(url, params=ERP, headers={"If-None-Match": etag})
    assert cut.status_code == 200 and cut.headers["etag"] != etag
    monkeypatch.undo()
    from service.routes import scenes as routes

    monkeypatch.setattr(routes, "renderer_digest", lambda: "another renderer")
    code = client.get(url, params=ERP, headers={"If-None-Match": etag})
    assert code.status_code == 200 and code.headers["etag"] not in (etag, cut.headers["etag"])
    monkeypatch.undo()
    assert client.get(url, params=ERP, headers={"If-None-Match": etag}).status_code == 304
    assert len(http_cache.renderer_digest()) == 16


def test_head_of_a_render_answers_its_headers_without_rendering(client, scene, monkeypatch):
    get = client.get(f"/v1/scenes/{scene}/render", params=PERSPECTIVE + [("format", "jpeg")])
    from service import scenes as work

    def no_render(*args, **kwargs):
        raise AssertionError("rendered for a HEAD")

    monkeypatch.setattr(work, "render_scene", no_render)
    head = client.head(f"/v1/scenes/{scene}/render", params=PERSPECTIVE + [("format", "jpeg")])
    assert head.status_code == 200 and head.content == b""
    for name in ("etag", "content-type", "cache-control"):
        assert head.headers[name] == get.headers[name], name
    assert "content-length" not in head.headers  # known only once the image is encoded (RFC 9110 9.3.2)
    bad = client.head(f"/v1/scenes/{scene}/render", params=[("c2w", "1,2,3"), ("width", "32")])
    assert bad.status_code == 422  # the checks of the GET come first


def test_if_none_match_on_an_unknown_scene_is_404(client):
    r = client.get(f"/v1/scenes/{'0' * 32}/gaussians.ply", headers={"If-None-Match": "*"})
    assert r.status_code == 404


def test_head_of_the_ply_sends_its_length_without_making_it(client, scene, monkeypatch):
    get = client.get(f"/v1/scenes/{scene}/gaussians.ply")
    from service import scenes as work

    made = []
    real = work.ply_stream

    def counting(store, scene_id):
        size, blocks = real(store, scene_id)

        def counted():
            for block in blocks:
                made.append(len(block))
                yield block
        return size, counted()

    monkeypatch.setattr(work, "ply_stream", counting)
    head = client.head(f"/v1/scenes/{scene}/gaussians.ply")
    assert head.status_code == 200 and head.content == b""
    assert head.headers["content-length"] == get.headers["content-length"] == str(len(get.content))
    assert head.headers["etag"] == get.headers["etag"] and made == []


# -- messages -------------------------------------------------------------------------------------------

def _post(client, poses=POSES, options=None, seed=90):
    data = {"poses": poses} if poses is not None else {}
    if options is not None:
        data["options"] = options
    return client.post("/v1/scenes", files={"image_a": ("a.png", panorama(seed=seed)),
                                            "image_b": ("b.png", panorama(seed=seed, shift=4))}, data=data)


def test_ragged_pose_row_names_the_matrix_and_row(client, live):
    before = stored_scene_count(live.settings.store_dir)
    c2w = json.loads(POSES)["c2w"]
    c2w[1][2] = c2w[1][2][:3]
    r = _post(client, poses=json.dumps({"c2w": c2w}))
    assert r.status_code == 422, r.text
    msg = r.json()["error"]["message"]
    assert "c2w[B]" in msg and "row 3" in msg and "3 numbers" in msg, msg
    assert "inhomogeneous" not in msg and "sequence" not in msg
    assert stored_scene_count(live.settings.store_dir) == before


@pytest.mark.parametrize("path, body", [("selections", '{"view": "a", "points": [[0.5, 0.6]]}'),
                                        ("edits", '{"selection": "%s", "op": "remove"}' % ("0" * 32)),
                                        ("refine", '{"iterations": 1}')])
@pytest.mark.parametrize("content_type", ["text/plain", None, "application/x-www-form-urlencoded"])
def test_json_body_without_json_content_type_is_415_saying_so(client, scene, path, body, content_type):
    headers = {"Content-Type": content_type} if content_type else {}
    r = client.post(f"/v1/scenes/{scene}/{path}", content=body.encode(), headers=headers)
    assert r.status_code == 415, r.text
    err = r.json()["error"]
    assert err["code"] == "unsupported_media_type" and "Content-Type: application/json" in err["message"], err
    assert "dictionary" not in err["message"]


def test_json_body_that_is_not_an_object_says_so(client, scene):
    r = client.post(f"/v1/scenes/{scene}/selections", json=[[0.5, 0.6]])
    assert r.status_code == 422, r.text
    msg = r.json()["error"]["message"]
    assert "JSON object" in msg and "dictionary" not in msg, msg


@pytest.mark.parametrize("field", ["poses", "options"])
def test_json_form_fields_may_start_with_a_bom(client, field):
    options = '{"sh_degree": 0}'
    plain = _post(client, options=options, seed=92)
    assert plain.status_code == 201, plain.text
    bom = "\ufeff"
    r = _post(client, poses=bom + POSES if field == "poses" else POSES,
              options=bom + options if field == "options" else options, seed=92)
    assert r.status_code == 201, r.text
    assert r.json()["id"] == plain.json()["id"]


def test_render_camera_just_beyond_the_limit_prints_two_different_numbers(client, scene):
    c2w = np.eye(4)
    c2w[0, 3] = 1_000_001.0
    r = client.get(f"/v1/scenes/{scene}/render", params={"c2w": ",".join(map(str, c2w.ravel())), "width": "64"})
    assert r.status_code == 422, r.text
    msg = r.json()["error"]["message"]
    assert "1000001" in msg and "1000000" in msg, msg


def test_scene_scale_message_prints_two_different_numbers():
    from rasterizer.sweep import SweepRangeError, check_scene_scale

    a, b = np.eye(4), np.eye(4)
    a[0, 3], b[0, 3] = 1_000_001.0, 1_000_000.5
    with pytest.raises(SweepRangeError) as err:
        check_scene_scale(a, b)
    assert "1000001" in str(err.value) and "1000000" in str(err.value), err.value


def test_near_without_far_names_the_automatic_far(client, live):
    """POSES are 0.5 apart: the automatic far is 20 x 0.5 = 10."""
    before = stored_scene_count(live.settings.store_dir)
    r = _post(client, options='{"near": 30}', seed=94)
    assert r.status_code == 422, r.text
    err = r.json()["error"]
    assert err["code"] == "invalid_options" and "automatic far" in err["message"] and "10" in err["message"], err
    r = _post(client, options='{"far": 0.1}', seed=94)
    assert r.status_code == 422, r.text
    err = r.json()["error"]
    assert err["code"] == "invalid_options" and "automatic near" in err["message"] and "0.15" in err["message"], err
    assert stored_scene_count(live.settings.store_dir) == before


def test_baseline_option_below_the_minimum_names_the_option(client):
    r = _post(client, poses=None, options='{"baseline": 1e-05}', seed=95)
    assert r.status_code == 422, r.text
    err = r.json()["error"]
    assert err["code"] == "invalid_options" and err["message"].startswith("options.baseline"), err
    assert "1e-05" in err["message"] and "coincide" not in err["message"]


def test_camera_height_that_scales_the_cameras_together_names_the_option(client, monkeypatch):
    """The estimate is scaled by camera_height; a tiny height gave the encoder's "the camera centres coincide"."""
    from service import scenes as work

    def tiny_estimate(erp_a, erp_b, poses, opts, data):
        b = np.eye(4)
        b[0, 3] = 2e-10
        return np.eye(4), b, {"source": "estimated"}

    monkeypatch.setattr(work, "poses_for_scene", tiny_estimate)
    r = _post(client, poses=None, options='{"camera_height": 1e-09}', seed=96)
    assert r.status_code == 422, r.text
    err = r.json()["error"]
    assert err["code"] == "invalid_options" and "options.camera_height=1e-09" in err["message"], err
    assert "baseline of 2e-10" in err["message"], err


def test_openapi_declares_the_api_keys_401_where_it_is_checked(client):
    """Every /v1 route answers 401 when the server has a key; the schema said so nowhere."""
    schema = client.get("/openapi.json").json()
    paths = schema["paths"]
    for path in ("/v1/scenes", "/v1/scenes/{scene_id}/render", "/v1/info", "/metrics"):
        for operation in paths[path].values():
            assert operation["responses"]["401"]["content"]["application/json"]["schema"]["$ref"].endswith("ErrorResponse")
            assert {"apiKey": []} in operation["security"] and {} in operation["security"]
    for path in ("/healthz", "/readyz"):
        assert all("401" not in op["responses"] for op in paths[path].values())
    assert schema["components"]["securitySchemes"]["apiKey"]["scheme"] == "bearer"
    assert "ErrorResponse" in schema["components"]["schemas"]


# -- odd inputs: never a 500, and a message that names the input at fault --------------------------------

def test_an_adaptive_range_without_a_confident_pixel_keeps_the_default(client):
    """min_confidence 1 with min_fraction 0 leaves no pixel for the percentiles: the default range, not a 500."""
    options = '{"adaptive_range": {"enabled": true, "min_confidence": 1.0, "min_fraction": 0}}'
    r = _post(client, options=options, seed=95)
    assert r.status_code == 201, r.text
    adaptive = client.get(f"/v1/scenes/{r.json()['id']}").json()["info"]["adaptive_range"]
    assert adaptive["confident_fraction"] == 0.0 and "reason" in adaptive, adaptive


def test_a_scene_emptied_by_min_opacity_names_it_not_the_poses(client, live):
    """The 422 empty_scene names the option that removed every Gaussian, not near/far, poses or images."""
    r = _post(client, options='{"min_opacity": 0.999999}', seed=94)
    assert r.status_code == 422, r.text
    err = r.json()["error"]
    assert err["code"] == "empty_scene" and "min_opacity" in err["message"], err
    assert "near/far" not in err["message"] and "poses" not in err["message"], err


@pytest.mark.parametrize("field", ["poses", "options"])
def test_an_integer_too_long_for_python_is_named_by_its_digits(client, live, field):
    """Past 4300 digits Python's own words tell the client to call sys.set_int_max_str_digits(): not shown."""
    huge = "1" + "0" * 5000
    poses, options = (POSES.replace("0.5", huge), None) if field == "poses" else (POSES, f'{{"near": {huge}}}')
    r = _post(client, poses=poses, options=options)
    assert r.status_code == 422, r.text
    msg = r.json()["error"]["message"]
    assert msg.startswith(field) and "5001 digits" in msg and "sys." not in msg, msg


@pytest.mark.parametrize("path, body, words", [
    ("selections", "[" * 100_000 + "]" * 100_000, "nested too deeply"),
    ("selections", '{"segment": 1' + "0" * 5000 + "}", "more than 4300 digits"),
    ("refine", '{"iterations": 1' + "0" * 5000 + "}", "more than 4300 digits"),
    ("edits", '{"selection": "' + "0" * 32 + '", "op": "translate", "offset": [1' + "0" * 5000 + ", 0, 0]}",
     "more than 4300 digits"),
    ("selections", b'{"view": "\xff", "points": [[0.5, 0.6]]}', "not UTF-8"),
])
def test_a_json_body_the_parser_refuses_is_422_saying_why(client, scene, path, body, words):
    """Not the parser's generic "There was an error parsing the body": what in the body it could not read."""
    r = client.post(f"/v1/scenes/{scene}/{path}", content=body, headers={"Content-Type": "application/json"})
    assert r.status_code == 422, r.text
    msg = r.json()["error"]["message"]
    assert msg.startswith("request body: not valid JSON") and words in msg and "parsing the body" not in msg, msg
    assert "sys." not in msg and client.get("/healthz").status_code == 200


def test_a_form_refused_while_it_is_read_is_answered_at_once(live):
    """A text field sent twice is refused as the form is read; the answer to the parse error does not read the
    body again (that read would wait for the client to hang up: the body has all arrived)."""
    boundary = "b0undary"
    parts = [("Ai", None, b"true"), ("Ai", None, b"[]"), ("image_a", "a", b"\x87w"), ("image_b", "b", b">")]
    body = b"".join(f'--{boundary}\r\nContent-Disposition: form-data; name="{name}"'.encode()
                    + (f'; filename="{file}"'.encode() if file else b"") + b"\r\n\r\n" + value + b"\r\n"
                    for name, file, value in parts) + f"--{boundary}--\r\n".encode()
    with live.client() as c:
        r = c.post("/v1/scenes", content=body, headers={"Content-Type": f"multipart/form-data; boundary={boundary}"},
                   timeout=20)
    assert r.status_code == 422 and r.json()["error"]["code"] == "duplicate_field", r.text


@pytest.mark.parametrize("content, content_type", [(b'{"image_a": "a.png"}', "application/json"),
                                                    (panorama(seed=93), "image/png"), (b"", None)])
def test_a_scene_upload_that_is_no_form_is_415_naming_what_was_sent(client, live, content, content_type):
    """A JSON object or a bare image: the answer names the Content-Type, not only the missing image_a and image_b."""
    before = stored_scene_count(live.settings.store_dir)
    r = client.post("/v1/scenes", content=content, headers={"Content-Type": content_type} if content_type else {})
    assert r.status_code == 415, r.text
    err = r.json()["error"]
    assert err["code"] == "unsupported_media_type" and "multipart/form-data" in err["message"], err
    assert (repr(content_type) if content_type else "no Content-Type") in err["message"], err
    assert stored_scene_count(live.settings.store_dir) == before


@pytest.mark.parametrize("params, name", [({"fov_deg": "999"}, "fov_deg"), ({"fov_deg": "0.001"}, "fov_deg"),
                                          ({"fov_deg": "nan"}, "fov_deg"),
                                          ({"c2w": "2,0,0,0,0,2,0,0,0,0,2,0,0,0,0,1"}, "c2w"),
                                          ({"c2w": "1,0,0"}, "c2w"), ({"fov_deg": "9_0"}, "fov_deg"),
                                          ({"fov_deg": "\u0669\u0660"}, "fov_deg"), ({"width": "-5"}, "width"),
                                          ({"width": "abc"}, "width"), ({"height": "0"}, "height"),
                                          ({"height": "1e400"}, "height"), ({"width": "6_4"}, "width"),
                                          ({"c2w": "1,0,0,0,0,1,0,0,0,0,1,1e300"}, "c2w"),
                                          ({"c2w": "1,0,0,-2e6,0,1,0,0,0,0,1,0"}, "c2w")])
def test_viewer_camera_the_render_api_refuses_is_422_naming_it(client, scene, params, name):
    """The page would take fov_deg 999 and draw its view turned over, without a word; a fov_deg or canvas size
    its script reads as no number (9_0, Arabic-Indic digits, which Python's float reads as 90) or not positive
    showed a page that failed in the browser only (unseen with bare=1); a camera 1e300 from the origin, which
    the render API refuses, a page whose float32 camera cannot be placed."""
    r = client.get(f"/v1/scenes/{scene}/viewer", params=params)
    assert r.status_code == 422, r.text
    assert r.json()["error"]["message"].startswith(name), r.text
