"""Regression tests of the request audit: what a clumsy client sends that a route would otherwise read
silently in another way than meant (extra or repeated fields, image files a viewer shows otherwise)."""

from __future__ import annotations

import io
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image, ImageOps

from service.errors import BadInput
from service.images import check_header, decode_rgb
from tests.service._support import IDENTITY, POSES, edit_server, new_scene, panorama, stored_scene_count

MOVED = ",".join(str(v) for v in np.array([[1, 0, 0, 0.2], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]).ravel())


@pytest.fixture(scope="module")
def live(model_path, tmp_path_factory):
    with edit_server(model_path, tmp_path_factory.mktemp("store")) as server:  # renders up to 512 x 256
        yield server


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



@pytest.mark.parametrize("options", ['{"baseline": 3.0}', '{"camera_height": 1.6}', '{"baseline": 3.0, "refine_poses": true}'])
def test_scale_options_with_given_poses_are_422_not_ignored(client, live, options):
    """They scale estimated poses only: with given poses the scene kept the poses' scale without a word."""
    before = stored_scene_count(live.settings.store_dir)
    r = client.post("/v1/scenes", files={"image_a": ("a.png", panorama(seed=70)), "image_b": ("b.png", panorama(seed=71))},
                    data={"poses": POSES, "options": options})
    assert r.status_code == 422, r.text
    err = r.json()["error"]
    assert err["code"] == "invalid_options" and "given" in err["message"]
    assert err["message"].startswith("options.baseline" if "baseline" in options else "options.camera_height")
    assert stored_scene_count(live.settings.store_dir) == before


def test_refine_poses_without_poses_is_422_not_ignored():
    """Without poses they are estimated; refine_poses refines given ones, so the scene was the plain one under a
    new id. The API and the CLI share this check."""
    from service.errors import BadInput
    from service.inputs import check_scale_options
    from service.poses import PoseOptions

    with pytest.raises(BadInput) as err:
        check_scale_options(False, PoseOptions(refine_poses=True))
    assert err.value.status == 422 and err.value.code == "invalid_options"
    assert err.value.message.startswith("options.refine_poses")
    check_scale_options(True, PoseOptions(refine_poses=True))  # with poses: what the option is for


@pytest.mark.parametrize("path, body", [
    ("selections", {"segment": True}), ("selections", {"segment": 1.0}), ("selections", {"segment": "1"}),
    ("selections", {"view": "a", "points": [["0.5", 0.5]]}), ("selections", {"view": "a", "points": [[True, 0.5]]}),
    ("selections", {"view": "a", "points": [[0.5, 0.5]], "negative": [[False, 0.5]]}),
    ("selections", {"view": "a", "points": [[10**400, 0.5]]}),
    ("edits", {"selection": "0" * 32, "op": "recolor", "color": [True, 0, 0]}),
    ("edits", {"selection": "0" * 32, "op": "translate", "offset": ["1", 0, 0]}),
])
def test_selection_and_edit_numbers_are_strict(client, scene, path, body):
    """JSON true, false or "0.5" were read as 1, 0 or 0.5 (segment true selected segment 1)."""
    r = client.post(f"/v1/scenes/{scene}/{path}", json=body)
    assert r.status_code == 422, r.text
    assert r.json()["error"]["code"] == "invalid_request"


@pytest.mark.parametrize("path, body, key", [
    ("selections", '{"view": "a", "points": [[0.5, 0.5]], "view": "b"}', "view"),
    ("selections", '{"view": "a", "points": [[0.5, 0.5]], "negative": [], "negative": [[0.1, 0.1]]}', "negative"),
    ("edits", '{"selection": "%s", "op": "remove", "op": "recolor", "color": [1, 0, 0]}' % ("0" * 32), "op"),
    ("refine", '{"iterations": 1, "iterations": 50}', "iterations"),
])
def test_a_key_repeated_in_a_json_body_is_422_naming_it(client, scene, path, body, key):
    """The body's model kept the last of repeated keys without a word (view "b" selected in the other reference)."""
    r = client.post(f"/v1/scenes/{scene}/{path}", content=body, headers={"Content-Type": "application/json"})
    assert r.status_code == 422, r.text
    err = r.json()["error"]
    assert err["code"] == "invalid_request" and f"{key!r} is given more than once" in err["message"], err


@pytest.mark.parametrize("field", ["poses", "options"])
def test_oversize_text_field_is_413_saying_what_is_too_large(client, live, field):
    before = stored_scene_count(live.settings.store_dir)
    data = {"poses": POSES, field: '{"near": 0.5' + " " * (1 << 20) + "}"}
    r = client.post("/v1/scenes", files={"image_a": ("a.png", panorama(seed=72)), "image_b": ("b.png", panorama(seed=73))},
                    data=data)
    assert r.status_code == 413, r.text
    err = r.json()["error"]
    assert err["code"] == "form_field_too_large" and "text form field" in err["message"]
    assert stored_scene_count(live.settings.store_dir) == before


def test_a_refined_scene_can_be_selected_and_edited_like_its_parent(client, scene):
    """Refinement keeps the Gaussians' geometry, count and order: the parent's correspondences hold, and
    the refined scene answered selections and segments with a 409 'built by a model without matches'."""
    r = client.post(f"/v1/scenes/{scene}/refine", json={"iterations": 1, "height": 16, "cross_check": False})
    assert r.status_code == 202, r.text
    for _ in range(600):
        job = client.get(r.headers["location"]).json()
        if job["status"] in ("done", "failed"):
            break
        time.sleep(0.1)
    assert job["status"] == "done", job
    refined = job["scene_id"]
    links = client.get(f"/v1/scenes/{refined}").json()["links"]
    assert links["parent"] == f"/v1/scenes/{scene}" and links["selections"] == f"/v1/scenes/{refined}/selections"
    point = {"view": "a", "points": [[0.5, 0.6]]}
    parent_sel = client.post(f"/v1/scenes/{scene}/selections", json=point)
    refined_sel = client.post(f"/v1/scenes/{refined}/selections", json=point)
    assert refined_sel.status_code == 201, refined_sel.text
    assert refined_sel.json()["num_gaussians"] == parent_sel.json()["num_gaussians"]
    assert client.get(f"/v1/scenes/{refined}/segments", params={"view": "b", "width": 64}).status_code == 200
    edit = client.post(f"/v1/scenes/{refined}/edits", json={"selection": refined_sel.json()["id"], "op": "remove"})
    assert edit.status_code == 201, edit.text


def test_a_file_sent_as_text_or_text_as_a_file_is_422_saying_so(client):
    """The messages quoted the form library ("Value error, Expected UploadFile, received: <class 'str'>")."""
    r = client.post("/v1/scenes", files={"image_b": ("b.png", panorama(seed=74)), "poses": ("poses.json", POSES.encode())},
                    data={"image_a": "a.png"})
    assert r.status_code == 422, r.text
    message = r.json()["error"]["message"]
    assert "image_a: expected a file" in message and "poses: expected a text field, got a file" in message
    assert "UploadFile" not in message and "class" not in message


@pytest.mark.parametrize("extra", [{"projection": "perspective"}, {"fov_deg": "30"}, {"height": "32"}, {"projection": "erp"}])
def test_segments_of_a_reference_view_refuse_render_query_parameters(client, scene, extra):
    """view=a is reference A's own ERP: a projection, height or fov_deg beside it was dropped without a word."""
    r = client.get(f"/v1/scenes/{scene}/segments", params={"view": "a", "width": 64, **extra})
    assert r.status_code == 422, r.text
    err = r.json()["error"]
    assert err["code"] == "invalid_render_query" and err["message"].startswith(next(iter(extra)))
    with_c2w = {"c2w": IDENTITY, "width": 64, "projection": "perspective", **extra}
    assert client.get(f"/v1/scenes/{scene}/segments", params=with_c2w).status_code == 200


@pytest.mark.parametrize("projection", ["erp", "yin"])
def test_fov_deg_on_a_panoramic_render_is_422_as_height_is(client, scene, projection):
    """fov_deg=30 on an ERP render answered the full panorama without a word."""
    width = {"erp": 64, "yin": 66}[projection]
    r = client.get(f"/v1/scenes/{scene}/render", params={"c2w": IDENTITY, "width": width, "projection": projection,
                                                         "fov_deg": "30"})
    assert r.status_code == 422, r.text
    assert r.json()["error"]["message"].startswith("fov_deg: only a perspective render")


_ROTATIONS = st.one_of(st.sampled_from([(0.0, 90.0), (0.0, -90.0), (180.0, 0.0), (-180.0, 89.999), (179.999, -89.999)]),
                       st.tuples(st.floats(-180, 180), st.floats(-90, 90)))


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(look=_ROTATIONS, roll=st.floats(-180, 180), where=st.one_of(st.integers(0, 10**9), st.floats(-6, 6)),
       projection=st.sampled_from(["erp", "perspective", "yin", "yang"]))
def test_any_rigid_camera_renders_finite_pixels(live, scene, monkeypatch, look, roll, where, projection):
    """Cameras at a Gaussian's centre, at the poles and the seam, up to 1e6 away: finite colour (before the 8-bit
    conversion, which would turn a NaN into black) and an image of the asked size."""
    from scipy.spatial.transform import Rotation

    from rasterizer.render import to_uint8
    from service import scenes
    from service.inputs import check_render_query

    finite = []

    def checked(colour):
        finite.append(bool(np.all(np.isfinite(colour))))
        return to_uint8(colour)

    monkeypatch.setattr(scenes, "to_uint8", checked)
    store = live.app.state.store
    c2w = np.eye(4)
    c2w[:3, :3] = Rotation.from_euler("yxz", [look[0], look[1], roll], degrees=True).as_matrix()
    if isinstance(where, int):  # exactly at a stored Gaussian
        means = store.gaussians(scene).means
        c2w[:3, 3] = means[where % len(means)]
    else:
        c2w[:3, 3] = [10.0 ** where, -(10.0 ** (where / 2)), 0.5]
    width = {"erp": 32, "perspective": 24, "yin": 30, "yang": 30}[projection]
    fov = 90.0 if projection == "perspective" else None
    query = check_render_query(",".join(repr(float(v)) for v in c2w.ravel()), projection, width, None, fov, "png",
                               max_width=512, max_pixels=512 * 256)
    data, _ = scenes.render_scene(store, scene, query)
    image = np.asarray(Image.open(io.BytesIO(data)))
    assert finite == [True] and image.shape == (*query.output_size(), 3)

# -- uploads a viewer shows otherwise than they are stored ---------------------------------------

LIMITS = {"max_pixels": 4096 * 2048, "min_height": 32}
#: what Pillow's exif_transpose does for each EXIF orientation, and its inverse (to make the stored file)
_TURN = {2: Image.Transpose.FLIP_LEFT_RIGHT, 3: Image.Transpose.ROTATE_180, 4: Image.Transpose.FLIP_TOP_BOTTOM,
         5: Image.Transpose.TRANSPOSE, 6: Image.Transpose.ROTATE_270, 7: Image.Transpose.TRANSVERSE,
         8: Image.Transpose.ROTATE_90}
_UNDO = {**_TURN, 6: Image.Transpose.ROTATE_90, 8: Image.Transpose.ROTATE_270}


def _with_orientation(shown: Image.Image, orientation: int, fmt: str = "PNG") -> bytes:
    """The file a camera writes for ``shown``: the pixels turned back, and the tag that turns them."""
    exif = Image.Exif()
    exif[0x0112] = orientation
    buf = io.BytesIO()
    shown.transpose(_UNDO[orientation]).save(buf, format=fmt, exif=exif.tobytes())
    return buf.getvalue()


@pytest.mark.parametrize("orientation", range(2, 9))
def test_exif_orientation_is_applied_as_every_viewer_does(orientation):
    shown = Image.open(io.BytesIO(panorama(height=64, seed=64)))
    data = _with_orientation(shown, orientation)
    assert np.array_equal(np.asarray(ImageOps.exif_transpose(Image.open(io.BytesIO(data)))), np.asarray(shown))
    rgb, header = decode_rgb(data, "image_a", **LIMITS)
    assert np.array_equal(rgb, np.asarray(shown))  # before: the stored pixels, upside down or a 1:2 refusal
    assert (header.width, header.height, header.describe()["exif_orientation"]) == (128, 64, orientation)


def test_exif_orientation_that_shows_a_non_panorama_is_422_saying_so():
    portrait = Image.open(io.BytesIO(panorama(height=64, seed=65))).transpose(Image.Transpose.ROTATE_90)  # 64x128
    data = _with_orientation(portrait, 6)  # stored 128x64 (2:1), shown 64x128
    with pytest.raises(BadInput) as info:
        check_header(data, "image_b", **LIMITS)
    assert info.value.code == "bad_aspect_ratio" and "64x128" in info.value.message and "orientation 6" in info.value.message


def _frames(fmt: str) -> bytes:
    frames = [Image.open(io.BytesIO(panorama(height=64, seed=s))).convert("RGB") for s in (66, 67)]
    buf = io.BytesIO()
    frames[0].save(buf, format=fmt, save_all=True, append_images=frames[1:])
    return buf.getvalue()


@pytest.mark.parametrize("fmt", ["PNG", "WEBP", "TIFF"])
def test_animated_or_multi_page_images_are_422(fmt):
    """Only the first frame would have been used, without a word."""
    with pytest.raises(BadInput) as info:
        check_header(_frames(fmt), "image_a", **LIMITS)
    assert info.value.code == "animated_image" and "image_a" in info.value.message


def test_turned_jpeg_upload_makes_the_scene_of_the_shown_panorama(client, live):
    shown = Image.open(io.BytesIO(panorama(seed=68)))
    turned = _with_orientation(shown, 6, "JPEG")  # stored 128 x 256: refused as 1:2 before
    r = client.post("/v1/scenes", files={"image_a": ("a.jpg", turned), "image_b": ("b.png", panorama(seed=68, shift=4))},
                    data={"poses": POSES})
    assert r.status_code == 201, r.text
    meta = client.get(f"/v1/scenes/{r.json()['id']}").json()
    assert meta["inputs"]["image_a"]["width"] == 256 and meta["inputs"]["image_a"]["exif_orientation"] == 6
    r = client.post("/v1/scenes", files={"image_a": ("a.webp", _frames("WEBP")), "image_b": ("b.png", panorama(seed=69))},
                    data={"poses": POSES})
    assert r.status_code == 422 and r.json()["error"]["code"] == "animated_image"


def test_a_jpeg_wider_than_any_stage_reads_is_decoded_at_a_reduced_scale(client, live):
    """A 4096-wide JPEG is read at 2048 columns, what the pose features read (the test model reads 256): the scene
    metadata keeps the file's size and says what was decoded."""
    big = Image.open(io.BytesIO(panorama(seed=70))).convert("RGB").resize((4096, 2048), Image.Resampling.BILINEAR)
    buf = io.BytesIO()
    big.save(buf, format="JPEG", quality=90)
    r = client.post("/v1/scenes", files={"image_a": ("a.jpg", buf.getvalue()), "image_b": ("b.png", panorama(seed=70, shift=4))},
                    data={"poses": POSES})
    assert r.status_code == 201, r.text
    described = client.get(f"/v1/scenes/{r.json()['id']}").json()["inputs"]["image_a"]
    assert (described["width"], described["height"]) == (4096, 2048)
    assert (described["decoded_width"], described["decoded_height"]) == (2048, 1024)
