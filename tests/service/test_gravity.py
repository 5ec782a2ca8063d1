"""Gravity of an uploaded panorama: XMP readings and the vertical lines of a synthetic tilted room."""

import io

import cv2
import numpy as np
import pytest
from PIL import Image

from rasterizer.geometry import direction_from_lat_lon, lat_lon_from_direction, pinhole_rays
from rasterizer.gravity import down_from_pitch_roll, level_rotation
from service import gravity
from service.gravity import crop_rotations, panorama_gravity, perspective_crops, xmp_pitch_roll


def _room_erp(down, height=1024):
    """uint8 gray ERP of a levelled 'room' (24 wall panels with vertical edges, bands in latitude) seen by a
    camera whose gravity is ``down`` (camera frame); drawn at twice the size and box-filtered (no staircases)."""
    height *= 2
    rows, cols = np.mgrid[0:height, 0:2 * height]
    lat = np.pi / 2 - (rows + 0.5) / height * np.pi
    lon = (cols + 0.5) / height * np.pi - np.pi
    d = direction_from_lat_lon(lat, lon) @ level_rotation(down).T  # bearings in the levelled frame
    lat_l, lon_l = lat_lon_from_direction(d)
    panel = np.floor((lon_l + np.pi) / (2 * np.pi) * 24).astype(int)
    band = np.floor(np.degrees(lat_l) / 25).astype(int)
    shade = 60 + 25 * (panel * 7 % 5) + 30 * (band % 2)
    return cv2.resize(shade.astype(np.float32), (height, height // 2), interpolation=cv2.INTER_AREA).astype(np.uint8)


def _jpeg_with_xmp(pitch, roll, attributes=False, base=None):
    """A small JPEG (``base``'s bytes, else a grey 16x8 one) with a GPano XMP segment after its SOI."""
    if base is None:
        ok, buf = cv2.imencode(".jpg", np.full((8, 16), 128, np.uint8))
        assert ok
        base = buf.tobytes()
    if attributes:
        desc = f'<rdf:Description GPano:PosePitchDegrees="{pitch}" GPano:PoseRollDegrees="{roll}"/>'
    else:
        desc = (f"<rdf:Description><GPano:PosePitchDegrees>{pitch}</GPano:PosePitchDegrees>"
                f"<GPano:PoseRollDegrees>{roll}</GPano:PoseRollDegrees></rdf:Description>")
    xmp = ('<?xpacket begin="" id="W5M0MpCehiHzreSzNTczkc9d"?><x:xmpmeta xmlns:x="adobe:ns:meta/">'
           '<rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#" '
           f'xmlns:GPano="http://ns.google.com/photos/1.0/panorama/">{desc}</rdf:RDF></x:xmpmeta>'
           '<?xpacket end="r"?>').encode()
    payload = b"http://ns.adobe.com/xap/1.0/\x00" + xmp
    return base[:2] + b"\xff\xe1" + (len(payload) + 2).to_bytes(2, "big") + payload + base[2:]


@pytest.mark.parametrize("attributes", [False, True])
def test_xmp_pitch_roll_from_a_jpeg(attributes):
    data = _jpeg_with_xmp(-3.4, 2.5, attributes)
    assert cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE).shape == (8, 16)  # still a JPEG
    assert xmp_pitch_roll(data) == (-3.4, 2.5)


def test_xmp_pitch_roll_absent_or_broken():
    ok, buf = cv2.imencode(".jpg", np.zeros((8, 8), np.uint8))
    assert xmp_pitch_roll(buf.tobytes()) is None and xmp_pitch_roll(None) is None
    assert xmp_pitch_roll(_jpeg_with_xmp(400, 0)) is None  # not an angle


@pytest.mark.parametrize("pitch, roll", [(4.0, -3.0), (-2.0, 5.0)])
def test_lines_recover_a_known_tilt(pitch, roll):
    down = down_from_pitch_roll(pitch, roll)
    est, info = panorama_gravity(_room_erp(down))
    assert info["source"] == "lines"
    assert np.degrees(np.arccos(np.clip(est @ down, -1, 1))) < 0.3
    assert abs(info["tilt_deg"] - np.hypot(pitch, roll)) < 0.4


def test_lines_win_over_a_wrong_reading_and_report_the_gap():
    down = down_from_pitch_roll(3.0, 2.0)
    est, info = panorama_gravity(_room_erp(down), _jpeg_with_xmp(-3.0, -2.0))
    assert info["source"] == "lines" and info["xmp"]["lines_gap_deg"] > 5
    assert np.degrees(np.arccos(np.clip(est @ down, -1, 1))) < 0.3


def test_reading_used_when_the_image_has_too_few_lines_but_they_agree():
    flat = np.full((256, 512), 120, np.uint8)
    flat[:, 100:110] = 30  # vertical edges in one direction only: no vanishing point
    flat[:, 140:150] = 30
    est, info = panorama_gravity(flat, _jpeg_with_xmp(0.0, 0.0))
    assert info["lines"].get("error") and info["source"] == "xmp" and np.allclose(est, [0, 1, 0])
    est, info = panorama_gravity(flat, _jpeg_with_xmp(8.0, 6.0))  # the edges disagree with this reading
    assert info["source"] == "none" and np.allclose(est, [0, 1, 0])


def test_reading_ignored_when_exif_turns_the_image():
    """A GPano reading describes the stored pixels; a file that EXIF turns (here by 180 deg) is shown, and
    decoded, turned, so the reading does not describe that panorama and is not used."""
    flat = np.full((256, 512), 120, np.uint8)
    flat[:, 100:110] = 30
    flat[:, 140:150] = 30
    buf = io.BytesIO()
    exif = Image.Exif()
    exif[0x0112] = 3
    Image.fromarray(np.full((8, 16), 128, np.uint8)).save(buf, "JPEG", exif=exif)
    plain = _jpeg_with_xmp(0.0, 0.0)
    turned = _jpeg_with_xmp(0.0, 0.0, base=buf.getvalue())
    assert xmp_pitch_roll(turned) == (0.0, 0.0)
    _, info = panorama_gravity(flat, plain)
    assert info["source"] == "xmp"
    est, info = panorama_gravity(flat, turned)
    assert info["source"] == "none" and "orientation 3" in info["xmp"]["ignored"]


def test_crops_shifted_per_yaw_equal_the_crops_of_their_own_rotation():
    """The lookup maps computed once per pitch and shifted per yaw give the pixels a per-crop evaluation gives."""
    erp = _room_erp(down_from_pitch_roll(3.0, -2.0), height=256)
    crops = ((0.0, (0.0, 45.0, 180.0, 337.5), (96, 64)), (-50.0, (67.5, 247.5), (80, 96)))
    focal = 40.0
    h, w = erp.shape
    for rot, crop in zip(crop_rotations(crops), perspective_crops(erp, crops, focal), strict=True):
        lat, lon = lat_lon_from_direction(pinhole_rays(crop.shape[1], crop.shape[0], focal) @ rot.T)
        mx = ((lon + np.pi) / (2 * np.pi) * w - 0.5).astype(np.float32)
        my = ((np.pi / 2 - lat) / np.pi * h - 0.5).astype(np.float32)
        direct = cv2.remap(erp, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
        assert np.array_equal(crop, direct)


def test_line_crops_hold_their_share_of_the_sphere():
    """A line crop keeps the segments whose midpoint is nearer its axis than any other's: every such direction
    between LOW_LAT_DEG and 45 deg up lies inside its crop, at least 2.5 deg from the sides it spans."""
    n = 200_000
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = np.pi * (1 + 5**0.5) * i
    d = np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], -1)
    lat = np.degrees(lat_lon_from_direction(d)[0])
    d = d[(lat > gravity.LOW_LAT_DEG) & (lat < 45.0)]
    rotations = gravity.LINE_CROP_ROTATIONS
    own = np.argmax(d @ rotations[:, :, 2].T, axis=1)
    sizes = [size for _, yaws, size in gravity.LINE_CROPS for _ in yaws]
    for k, (w, h) in enumerate(sizes):
        local = d[own == k] @ rotations[k]
        assert local.size and np.all(local[:, 2] > 0)
        for axis, side in ((0, w), (1, h)):
            need = np.degrees(np.arctan(np.abs(local[:, axis] / local[:, 2]).max()))
            half = np.degrees(np.arctan((side / 2) / gravity.LINE_CROP_FOCAL))
            assert half - need > 2.5, (k, axis, half, need)


@pytest.mark.parametrize("pitch, beyond", [(12.0, False), (30.0, True)])
def test_a_tilt_beyond_the_search_is_named_not_levelled(pitch, beyond):
    """Tilts up to MAX_TILT_DEG are searched and levelled as before; the lines of a panorama tilted further meet
    beyond the search, and that tilt is reported (for a refusal to name) without levelling by it."""
    from service.gravity import MAX_TILT_DEG

    down = down_from_pitch_roll(pitch, 0.0)
    est, info = panorama_gravity(_room_erp(down))
    assert ("beyond_search_deg" in info["lines"]) == beyond, info
    if beyond:
        assert abs(info["lines"]["beyond_search_deg"] - pitch) < 1.0
        assert info["tilt_deg"] <= MAX_TILT_DEG + 5 or info["source"] == "none"  # not levelled by the wide search
    else:
        assert info["source"] == "lines" and np.degrees(np.arccos(np.clip(est @ down, -1, 1))) < 0.3
