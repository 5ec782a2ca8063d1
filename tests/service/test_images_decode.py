"""Decoding uploaded panoramas (service.images): EXIF orientation per format, camera JPEGs with an MPF
second image, colour modes, and the decode's memory."""

from __future__ import annotations

import io
import re
import tracemalloc

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from PIL import Image

from service import images, jpeg_data
from service.errors import BadInput, InvalidImage, PayloadTooLarge
from service.images import check_header, decode_rgb

LIMITS = {"max_pixels": 4096 * 2048, "min_height": 32}

#: for each EXIF orientation, the turn that gives the stored pixels of an image shown upright
#: (the inverse of what a viewer applies: 6 is shown turned 90 deg clockwise, so stored 90 deg counter-clockwise)
_STORE = {1: None, 2: Image.Transpose.FLIP_LEFT_RIGHT, 3: Image.Transpose.ROTATE_180, 4: Image.Transpose.FLIP_TOP_BOTTOM,
          5: Image.Transpose.TRANSPOSE, 6: Image.Transpose.ROTATE_90, 7: Image.Transpose.TRANSVERSE,
          8: Image.Transpose.ROTATE_270}
#: lossless settings where a format has them (the pixels can then be compared exactly)
_SAVE = {"PNG": {}, "TIFF": {}, "WEBP": {"lossless": True}, "JPEG": {"quality": 100, "subsampling": 0}}


def upright(height: int = 64) -> np.ndarray:
    """A smooth (JPEG-friendly), asymmetric 2:1 test panorama: no flip or turn of it looks like itself."""
    yy, xx = np.mgrid[0:height, 0:2 * height].astype(np.float64)
    rgb = np.stack([xx / (2 * height), yy / height, 0.5 + 0.4 * np.sin(xx / 9 + yy / 5)], axis=2)
    return (rgb * 255).astype(np.uint8)


def with_orientation(shown: np.ndarray, orientation: int, fmt: str) -> bytes:
    """The file a camera writes for ``shown``: the pixels stored turned back, and the tag that turns them."""
    im = Image.fromarray(shown)
    if _STORE[orientation] is not None:
        im = im.transpose(_STORE[orientation])
    exif = Image.Exif()
    exif[0x0112] = orientation
    buf = io.BytesIO()
    im.save(buf, format=fmt, exif=exif.tobytes(), **_SAVE[fmt])
    return buf.getvalue()


@pytest.mark.parametrize("fmt", sorted(_SAVE))
@pytest.mark.parametrize("orientation", range(1, 9))
def test_every_exif_orientation_is_applied_once_in_every_format(fmt, orientation):
    """The decoded pixels are the upright panorama (BMP holds no EXIF). Pillow turns a TIFF by itself on load:
    the service must not turn it a second time, nor swap the size it checks twice."""
    shown = upright()
    data = with_orientation(shown, orientation, fmt)
    header = check_header(data, "image_a", **LIMITS)
    assert (header.width, header.height, header.orientation) == (128, 64, orientation)
    rgb, _ = decode_rgb(data, "image_a", **LIMITS)
    assert rgb.shape == shown.shape
    err = np.abs(rgb.astype(int) - shown).mean()
    assert err < (2.0 if fmt == "JPEG" else 1e-9), err
    for wrong in (2, 3, 4):  # the right turn, not a close one: every same-shape wrong turn is far off
        turned = np.asarray(Image.fromarray(shown).transpose(_STORE[wrong]))
        assert np.abs(rgb.astype(int) - turned).mean() > 20


@pytest.mark.parametrize("orientation", range(5, 9))
def test_a_quarter_turn_is_not_applied_twice_when_the_decoder_keeps_the_tag(monkeypatch, orientation):
    """Should a decoder turn a TIFF on load and keep its tag, the image that already has the shown size is upright."""
    monkeypatch.setattr(images, "exif_orientation", lambda im: orientation)  # the tag is never dropped
    shown = upright()
    rgb, _ = decode_rgb(with_orientation(shown, orientation, "TIFF"), "image_a", **LIMITS)
    np.testing.assert_array_equal(rgb, shown)


@pytest.mark.parametrize("fmt", sorted(_SAVE))
@pytest.mark.parametrize("orientation", range(5, 9))
def test_a_quarter_turn_that_shows_a_portrait_is_422_naming_the_shown_size(fmt, orientation):
    """Stored 128x64 (2:1) with a quarter-turn tag: shown 64x128, not a panorama; the message quotes the shown size."""
    portrait = np.ascontiguousarray(upright().transpose(1, 0, 2))  # 64 wide, 128 high
    data = with_orientation(portrait, orientation, fmt)
    with pytest.raises(BadInput) as info:
        check_header(data, "image_b", **LIMITS)
    assert info.value.code == "bad_aspect_ratio"
    assert "got 64x128" in info.value.message and f"orientation {orientation}" in info.value.message


@pytest.mark.parametrize("second", ["preview", "full"])
def test_a_camera_jpeg_with_an_mpf_second_image_gives_its_primary_image(second):
    """360 cameras and phones append a preview, a depth map or a second eye to the JPEG (MPF, read by Pillow as
    MPO); every viewer shows the first image, and so does the service."""
    shown = upright()
    extra = Image.fromarray(shown[:, ::-1].copy())  # far from the primary: taking it would show
    extra = extra.resize((64, 32)) if second == "preview" else extra
    buf = io.BytesIO()
    Image.fromarray(shown).save(buf, format="MPO", save_all=True, append_images=[extra], quality=95)
    data = buf.getvalue()
    assert Image.open(io.BytesIO(data)).n_frames == 2
    header = check_header(data, "image_a", **LIMITS)
    assert (header.width, header.height) == (128, 64)
    rgb, _ = decode_rgb(data, "image_a", **LIMITS)
    assert np.abs(rgb.astype(int) - shown).mean() < 2.0
    half, header = decode_rgb(data, "image_a", **LIMITS, min_width=64)  # the primary image at a reduced scale too
    assert half.shape == (32, 64, 3) and header.reduction == 2
    assert np.abs(half.astype(int) - np.asarray(Image.fromarray(shown).resize((64, 32), Image.Resampling.BOX))).mean() < 2.0


# APNG, animated WebP and multi-page TIFF stay refused: test_hardening_requests.test_animated_or_multi_page_images_are_422


def _png(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(arr).save(buf, format="PNG")
    return buf.getvalue()


def _decode_peak(data: bytes) -> int:
    """Bytes of the largest Python/numpy allocation total while decoding (tracemalloc)."""
    tracemalloc.start()
    try:
        decode_rgb(data, "image_a", max_pixels=1 << 25, min_height=32)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_16bit_greyscale_decodes_in_about_the_memory_of_8bit_rgb():
    """A tiny 16-bit grey PNG of a large size (it compresses ~500x) must not cost several full-size float64 copies:
    its decode peak stays within 2x that of 8-bit RGB of the same size (~4.8x with float64 temporaries)."""
    h, w = 1024, 2048
    grey16 = _png((np.arange(h * w) % 65536).astype(np.uint16).reshape(h, w))
    rgb8 = _png((np.arange(h * w * 3) % 251).astype(np.uint8).reshape(h, w, 3))
    assert Image.open(io.BytesIO(grey16)).mode.startswith("I;16")
    assert _decode_peak(grey16) <= 2 * _decode_peak(rgb8)


@pytest.mark.parametrize("block_pixels", [1000, 1 << 20])
def test_16bit_greyscale_is_scaled_exactly_in_every_block(monkeypatch, block_pixels):
    """Every 16-bit value v maps to round(v * 255 / 65535) (half up), across the row blocks of the conversion;
    a 32-bit integer TIFF with a value beyond 16 bits in its last rows is refused."""
    monkeypatch.setattr(images, "GREY_BLOCK_PIXELS", block_pixels)
    values = np.arange(65536, dtype=np.uint16)
    grey = np.concatenate([values, values[::-1]]).reshape(256, 512)
    rgb, _ = decode_rgb(_png(grey), "image_a", **LIMITS)
    expected = np.floor(grey.astype(np.float64) * 255 / 65535 + 0.5).astype(np.uint8)
    for c in range(3):
        np.testing.assert_array_equal(rgb[..., c], expected)
    wide = grey.astype(np.int32)
    wide[-1, -1] = 70000
    buf = io.BytesIO()
    Image.fromarray(wide).save(buf, format="TIFF")
    with pytest.raises(InvalidImage) as info:
        decode_rgb(buf.getvalue(), "image_a", **LIMITS)
    assert info.value.code == "unsupported_image_mode"


@pytest.mark.parametrize("mode", ["LAB", "CMYK", "YCbCr"])
def test_lab_cmyk_and_ycbcr_tiffs_convert_to_their_rgb(mode):
    """Colour spaces without alpha decode to their RGB; LAB's "A" band is the a* colour axis, not transparency."""
    shown = upright()
    buf = io.BytesIO()
    Image.fromarray(shown).convert(mode).save(buf, format="TIFF")
    assert Image.open(io.BytesIO(buf.getvalue())).mode == mode
    rgb, header = decode_rgb(buf.getvalue(), "image_a", **LIMITS)
    assert header.format == "TIFF" and rgb.shape == shown.shape
    assert np.abs(rgb.astype(int) - shown).mean() < 2.0


def test_a_file_of_an_accepted_format_that_cannot_be_decoded_says_its_format():
    """A cut-short LZW TIFF was 'not a readable image (accepted formats: ... TIFF ...)'."""
    buf = io.BytesIO()
    Image.fromarray(upright()).save(buf, format="TIFF", compression="tiff_lzw")
    with pytest.raises(InvalidImage) as info:
        check_header(buf.getvalue()[:-200], "image_a", **LIMITS)
    assert "a TIFF file that cannot be decoded" in info.value.message
    with pytest.raises(InvalidImage) as info:
        check_header(b"not an image at all", "image_a", **LIMITS)
    assert "not a readable image (accepted formats" in info.value.message


def test_same_picture_is_one_view_however_it_was_encoded():
    """One panorama re-encoded, resized or noisy is one picture; a turned or mirrored copy is another view;
    flat images are one picture only when equal."""
    import cv2

    from service.images import same_picture

    rng = np.random.default_rng(0)
    base = cv2.GaussianBlur(rng.random((256, 512)).astype(np.float32), (0, 0), 3)  # smooth texture, like a room
    img = np.repeat(((base - base.min()) / np.ptp(base) * 255).astype(np.uint8)[..., None], 3, axis=2)
    ok, jpeg = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 40])
    noisy = np.clip(img + rng.normal(0.0, 8.0, img.shape), 0, 255).astype(np.uint8)
    half = cv2.resize(img, (256, 128), interpolation=cv2.INTER_AREA)
    for copy in (img.copy(), cv2.imdecode(jpeg, cv2.IMREAD_COLOR), noisy, half, img.astype(np.float32) / 255.0):
        assert same_picture(img, copy)
    assert not same_picture(img, np.roll(img, 64, axis=1))  # turned by 45 deg: another view
    assert not same_picture(img, img[:, ::-1].copy())
    flat = np.full((64, 128, 3), 0.5, np.float32)
    assert same_picture(flat, flat.copy()) and not same_picture(flat, flat * 0.9)


@pytest.mark.parametrize(("fmt", "width", "height", "min_width", "expected"), [
    ("JPEG", 5760, 2880, 2048, 2),  # a 5.7K camera JPEG for the 2048-wide pose features
    ("JPEG", 4096, 2048, 2048, 2),
    ("JPEG", 4094, 2047, 2048, 1),  # half would be narrower than the reader
    ("JPEG", 16384, 8192, 2048, 8),
    ("JPEG", 11904, 5952, 2048, 4),
    ("MPO", 11904, 5952, 2048, 4),  # a camera JPEG with an MPF second image
    ("JPEG", 5762, 2881, 1024, 1),  # no scale divides 2881 rows: the decode would not stay exactly 2:1
    ("JPEG", 5760, 2880, None, 1),  # no reader width given: whole
    ("PNG", 5760, 2880, 2048, 1),  # only JPEG has DCT scales
])
def test_jpeg_reduction_keeps_the_reader_width_and_exact_2_to_1(fmt, width, height, min_width, expected):
    assert images.jpeg_reduction(fmt, width, height, min_width) == expected


@pytest.mark.parametrize("orientation", [1, 3, 6, 8])
def test_a_wide_jpeg_decodes_at_a_reduced_scale_upright(orientation):
    """A JPEG four times wider than the reader needs decodes at a quarter of each side, turned by its EXIF
    orientation once, and close to the whole decode box-reduced; the header keeps the file's own size and says
    what was decoded."""
    shown = upright(256)
    data = with_orientation(shown, orientation, "JPEG")
    rgb, header = decode_rgb(data, "image_a", **LIMITS, min_width=128)
    assert rgb.shape == (64, 128, 3)
    assert header.describe()["width"] == 512 and header.describe()["decoded_width"] == 128
    whole, whole_header = decode_rgb(data, "image_a", **LIMITS)
    assert whole.shape == shown.shape and "decoded_width" not in whole_header.describe()
    reduced = np.asarray(Image.fromarray(whole).resize((128, 64), Image.Resampling.BOX)).astype(int)
    err = np.abs(rgb.astype(int) - reduced).mean()
    assert err < 2.0, err


def test_the_pixel_cap_counts_what_a_reduced_jpeg_decodes():
    """A baseline JPEG over the pixel cap passes when its reduced decode fits the cap and it declares at most
    MAX_REDUCED_JPEG_FACTOR times the cap; a PNG of the same size, the JPEG read whole, one declaring more or a
    progressive one is a 413 that names the limits."""
    shown = upright(512)  # 1024 x 512 = 524,288 pixels
    jpeg, png = with_orientation(shown, 1, "JPEG"), with_orientation(shown, 1, "PNG")
    cap = 200_000
    rgb, header = decode_rgb(jpeg, "image_a", max_pixels=cap, min_height=32, min_width=256)
    assert rgb.shape == (128, 256, 3) and header.reduction == 4
    for data, min_width in ((png, 256), (jpeg, None)):
        with pytest.raises(PayloadTooLarge, match=f"limit of {cap} pixels$"):
            check_header(data, "image_a", max_pixels=cap, min_height=32, min_width=min_width)
    small_cap = 524_288 // images.MAX_REDUCED_JPEG_FACTOR - 1
    with pytest.raises(PayloadTooLarge, match=f"{images.MAX_REDUCED_JPEG_FACTOR * small_cap} for a baseline JPEG"):
        check_header(jpeg, "image_a", max_pixels=small_cap, min_height=32, min_width=256)
    buf = io.BytesIO()  # a progressive JPEG holds the whole image's coefficients at any scale: its header counts
    Image.fromarray(shown).save(buf, format="JPEG", progressive=True)
    with pytest.raises(PayloadTooLarge, match=f"limit of {cap} pixels$"):
        check_header(buf.getvalue(), "image_a", max_pixels=cap, min_height=32, min_width=256)
    rgb, header = decode_rgb(buf.getvalue(), "image_a", max_pixels=1 << 20, min_height=32, min_width=256)
    assert rgb.shape == (128, 256, 3) and header.reduction == 4  # within the cap it still decodes reduced


def test_a_truncated_jpeg_is_refused_at_a_reduced_scale_too():
    """libjpeg reads every block at any scale: a cut file is a 400, not an image with grey rows."""
    data = with_orientation(upright(256), 1, "JPEG")
    for cut in (len(data) // 2, len(data) - 50):
        with pytest.raises(InvalidImage, match="truncated"):
            decode_rgb(data[:cut], "image_a", **LIMITS, min_width=128)


@given(height=st.integers(1, 40_000), min_width=st.integers(1, 20_000))
def test_jpeg_reduction_is_the_coarsest_exact_scale_that_keeps_the_width(height, min_width):
    """Whatever the size: the divisor divides both sides (the decode stays exactly 2:1), keeps at least
    ``min_width`` columns unless it is 1, and no coarser scale of libjpeg's would do both."""
    width = 2 * height
    r = images.jpeg_reduction("JPEG", width, height, min_width)
    assert r in (1, *images.JPEG_REDUCTIONS) and width % r == 0 and height % r == 0
    assert r == 1 or width // r >= min_width
    assert not any(q > r and width % q == 0 and height % q == 0 and width // q >= min_width
                   for q in images.JPEG_REDUCTIONS)


def _noise_jpeg(progressive: bool, height: int = 256, **save) -> bytes:
    """A 2:1 JPEG of random pixels (quality 90): every block holds data, so any cut lands inside a scan."""
    rgb = np.random.default_rng(7).integers(0, 256, (height, 2 * height, 3), dtype=np.uint8)
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="JPEG", quality=90, progressive=progressive, **save)
    return buf.getvalue()


@pytest.mark.parametrize("progressive", [False, True])
@pytest.mark.parametrize("kept", [0.3, 0.6, 0.9])
def test_a_jpeg_cut_short_and_closed_with_an_end_marker_is_400(progressive, kept):
    """libjpeg decodes such a file without an error (the rest of a baseline scan grey 128, a progressive image
    blurred) and Pillow hides its warning: the decode is refused, at a reduced scale too."""
    data = _noise_jpeg(progressive)
    cut = data[:int(len(data) * kept)] + b"\xff\xd9"
    Image.open(io.BytesIO(cut)).load()  # what the check must catch: Pillow alone decodes it
    for min_width in (None, 128):
        with pytest.raises(InvalidImage, match="the JPEG data is truncated or corrupt") as info:
            decode_rgb(cut, "image_a", max_pixels=10**9, min_height=64, min_width=min_width)
        assert info.value.status == 400 and info.value.message.startswith("image_a: ")


def test_a_progressive_jpeg_cut_between_two_scans_is_400():
    """Cut at a scan boundary libjpeg has no warning at all: the scan headers show the coefficients never sent."""
    data = _noise_jpeg(True)
    starts = [m.start() for m in re.finditer(rb"\xff\xda", data)]
    assert len(starts) >= 6
    for start in starts[1:]:
        with pytest.raises(InvalidImage, match="DCT coefficients"):
            decode_rgb(data[:start] + b"\xff\xd9", "image_a", **LIMITS)


def _with_segment(data: bytes, marker: int, payload: bytes) -> bytes:
    """``data`` with a marker segment inserted after its start-of-image marker."""
    return data[:2] + bytes((0xFF, marker)) + (len(payload) + 2).to_bytes(2, "big") + payload + data[2:]


def _valid_jpegs() -> dict[str, bytes]:
    shown = upright(128)
    exif = Image.Exif()
    exif[0x010F] = "camera"

    def save(im, **kw):
        buf = io.BytesIO()
        im.save(buf, **{"format": "JPEG", **kw})
        return buf.getvalue()

    im = Image.fromarray(shown)
    cases = {}
    for progressive in (False, True):
        p = {"progressive": progressive}
        cases |= {f"RGB {p}": save(im, **p), f"grey {p}": save(im.convert("L"), **p),
                  f"CMYK {p}": save(im.convert("CMYK"), **p),
                  f"restart markers {p}": save(im, restart_marker_blocks=3, **p),
                  f"4:4:4, optimised, EXIF {p}": save(im, subsampling=0, optimize=True, exif=exif.tobytes(), **p),
                  f"MPF preview {p}": save(im, format="MPO", save_all=True, append_images=[im.resize((64, 32))], **p)}
    thumbnail = cases["RGB {'progressive': True}"]
    cut_thumbnail = thumbnail[:thumbnail.index(b"\xff\xda", 400)] + b"\xff\xd9"  # an APP segment's content is no scan
    cases["EXIF thumbnail cut between scans"] = _with_segment(cases["RGB {'progressive': False}"], 0xE1,
                                                              b"Exif\x00\x00" + cut_thumbnail)
    cases["junk before the end marker"] = cases["RGB {'progressive': False}"][:-2] + b"\x00\x00\x00\xff\xd9"
    return cases


@pytest.mark.parametrize("name", sorted(_valid_jpegs()))
def test_whole_jpegs_of_every_kind_pass_the_data_check(name):
    """No valid JPEG is refused: grey, CMYK, restart markers, progressive, a camera's MPF preview after the end
    marker, an APP segment holding a cut JPEG, junk before the end marker (read after every pixel); each decodes
    to its picture whole and at 1/8 scale."""
    data = _valid_jpegs()[name]
    rgb, header = decode_rgb(data, "image_a", **LIMITS)
    assert header.format in ("JPEG", "MPO") and rgb.shape == (128, 256, 3)
    shown = Image.fromarray(upright(128))
    shown = np.asarray(shown.convert("L").convert("RGB") if name.startswith("grey") else shown)
    assert np.abs(rgb.astype(int) - shown).mean() < 4.0
    small, header = decode_rgb(data, "image_a", **LIMITS, min_width=32)
    assert header.reduction == 8 and small.shape == (16, 32, 3)


def test_the_jpeg_walk_is_bounded_by_the_segment_limit():
    """Segments after the first scan are walked in Python: past MAX_JPEG_SEGMENTS of them the file is a 413."""
    data = _noise_jpeg(False, height=64)
    eoi = len(data) - 2
    padded = data[:eoi] + b"\xff\xfe\x00\x02" * (jpeg_data.MAX_JPEG_SEGMENTS + 1) + data[eoi:]
    with pytest.raises(PayloadTooLarge) as info:
        decode_rgb(padded, "image_a", **LIMITS)
    assert info.value.code == "image_too_many_chunks"
    decode_rgb(data[:eoi] + b"\xff\xfe\x00\x02" * 10 + data[eoi:], "image_a", **LIMITS)  # a few comments pass
