"""Gravity of an uploaded panorama: the vertical vanishing point of its line segments (OpenCV LSD on
perspective crops), or the camera's own reading (GPano XMP) checked against those segments;
geometry in :mod:`rasterizer.gravity`.

:func:`panorama_gravity` returns the down direction in the panorama's camera frame (OpenCV) and
where it came from: ``"lines"`` (the vertical vanishing point), ``"xmp"`` (the file's
``PosePitchDegrees`` / ``PoseRollDegrees``, used when the image has too few vertical lines for a
vanishing point of its own but most of those agree with it within :data:`XMP_AGREE_DEG`) or
``"none"`` (neither: the panorama is taken as level). A reading describes the pixels as stored, so
it is ignored when the file's EXIF orientation turns the image (every viewer, and the decoder, show
the turned one).
"""

from __future__ import annotations

import re
from typing import Any

import numpy as np

from rasterizer.geometry import lat_lon_from_direction, pinhole_rays
from rasterizer.gravity import down_from_pitch_roll, line_support, tilt_deg, vertical_from_lines
from rasterizer.relative_pose import yaw_rotation

from .images import file_orientation

#: Line crops' focal length in pixels: 4.1 px per degree at a crop's centre, a 100-deg view 560 px across.
LINE_CROP_FOCAL = 235.0
#: Segments shorter than this (pixels of a line crop, about 5.5 deg at its centre) are too imprecise to vote.
MIN_SEGMENT_PX = 22.4
#: Segments below this latitude (deg) are dropped: a tripod, a selfie stick, the photographer.
LOW_LAT_DEG = -55.0
#: A line segment agrees with the camera's reading when its great circle passes this close (deg) to it.
XMP_AGREE_DEG = 1.5
#: Tilts beyond this (deg) are not searched for: a panorama is held roughly upright.
MAX_TILT_DEG = 20.0
#: The lines are searched again this far (deg), only to tell a tilt beyond MAX_TILT_DEG (the pose estimate refuses
#: such a panorama, naming it; nothing is levelled by it): its vanishing point counts when it lies beyond
#: MAX_TILT_DEG and gathers this many times the inliers of the searched one (or that one was not found). None of the
#: 20 dev panoramas, level or turned by 15-20 deg, has one (docs/design.md, "A tilt beyond the search").
WIDE_TILT_DEG = 45.0
BEYOND_TILT_MARGIN = 1.5

_XMP_NUMBER = r"\s*=?\s*[\"']?\s*>?\s*(-?\d+(?:\.\d+)?)"


def xmp_pitch_roll(data: bytes | None) -> tuple[float, float] | None:
    """(pitch, roll) degrees from a file's GPano XMP packet (element or attribute form), or None."""
    if not data:
        return None
    start = data.find(b"<x:xmpmeta")
    if start < 0:
        return None
    end = data.find(b"</x:xmpmeta>", start)
    packet = data[start:end if end > 0 else start + 65536].decode("utf-8", "replace")
    out = []
    for key in ("PosePitchDegrees", "PoseRollDegrees"):
        m = re.search(r"GPano:" + key + _XMP_NUMBER, packet)
        if m is None:
            return None
        v = float(m.group(1))
        if not np.isfinite(v) or abs(v) > 90:
            return None
        out.append(v)
    return out[0], out[1]


def crop_size(focal: float, half_x_deg: float, half_y_deg: float) -> tuple[int, int]:
    """(width, height) in pixels of a pinhole crop of ``focal`` pixels reaching ``half_*_deg`` from its axis."""
    w, h = (int(round(2 * focal * np.tan(np.radians(a)))) for a in (half_x_deg, half_y_deg))
    return w, h


#: Line crops as (pitch, yaws, (width, height)) in degrees and pixels: 8 on the horizon and 4 looking 45 deg down
#: (+45 deg pitch). Gravity votes with near-vertical segments, and a crop keeps those whose midpoint is nearer its
#: axis than any other's: the horizon ring's crops reach 30 deg to the sides (their own 22.5 and a margin) and
#: 50 up and down, so a wall's vertical edge lies whole in one crop; the lower ring's reach 40 deg, a little past
#: their own share (down to :data:`LOW_LAT_DEG`). Segments around the zenith, above 48 deg, are not looked for.
LINE_CROPS = ((0.0, tuple(45.0 * k for k in range(8)), crop_size(LINE_CROP_FOCAL, 30.0, 50.0)),
              (45.0, tuple(22.5 + 90.0 * k for k in range(4)), crop_size(LINE_CROP_FOCAL, 40.0, 40.0)))


def _pitch_rotation(pitch_deg: float) -> np.ndarray:
    p = np.radians(pitch_deg)
    return np.array([[1, 0, 0], [0, np.cos(p), np.sin(p)], [0, -np.sin(p), np.cos(p)]])


def crop_rotations(crops) -> np.ndarray:
    """(n, 3, 3) crop-camera -> panorama-camera rotations of ``crops``: (pitch, yaws, ...) rings in degrees, a
    crop turned up by its pitch (about x), then about the panorama's y axis by each yaw, in that order."""
    return np.stack([yaw_rotation(np.radians(y)) @ _pitch_rotation(ring[0]) for ring in crops for y in ring[1]])


LINE_CROP_ROTATIONS = crop_rotations(LINE_CROPS)


def perspective_crops(gray: np.ndarray, crops, focal: float):
    """Yield the pinhole views (height, width) uint8 of an ERP image ``gray`` (H, 2H) uint8 along ``crops``
    ((pitch, yaws, (width, height)) rings in degrees and pixels, in :func:`crop_rotations` order), of
    ``focal`` pixels with the principal point at the centre, bilinear, wrapping across the seam.

    A turn about the panorama's y axis keeps latitude and adds the yaw to longitude, so the lookup
    maps are computed once per pitch (a latitude and longitude of every crop pixel costs more than the
    remap itself) and shifted for each yaw; they equal a per-crop evaluation to about 1e-15 rad.
    """
    import cv2

    h, w = gray.shape
    for pitch, yaws, (width, height) in crops:
        lat, lon0 = lat_lon_from_direction(pinhole_rays(width, height, focal) @ _pitch_rotation(pitch).T)
        my = ((np.pi / 2 - lat) / np.pi * h - 0.5).astype(np.float32)
        for yaw in yaws:
            lon = lon0 + np.radians(yaw)
            lon[lon > np.pi] -= 2 * np.pi
            mx = ((lon + np.pi) / (2 * np.pi) * w - 0.5).astype(np.float32)
            yield cv2.remap(gray, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)


def line_normals(gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Great-circle normals (N, 3) of the line segments of an ERP (uint8 gray (H, 2H)) and their
    lengths (N,) in radians; each segment is kept by the crop whose axis is nearest its midpoint."""
    import cv2

    lsd = cv2.createLineSegmentDetector()
    f = LINE_CROP_FOCAL
    sizes = [size for _, yaws, size in LINE_CROPS for _ in yaws]
    axes = LINE_CROP_ROTATIONS[:, :, 2]
    normals, lengths = [], []
    for k, crop in enumerate(perspective_crops(gray, LINE_CROPS, f)):
        rot, (w, h) = LINE_CROP_ROTATIONS[k], sizes[k]
        cx, cy = (w - 1) / 2, (h - 1) / 2
        segs = lsd.detect(crop)[0]
        if segs is None:
            continue
        s = segs.reshape(-1, 4).astype(np.float64)
        s = s[np.hypot(s[:, 2] - s[:, 0], s[:, 3] - s[:, 1]) >= MIN_SEGMENT_PX]
        p1 = np.stack([(s[:, 0] - cx) / f, (s[:, 1] - cy) / f, np.ones(len(s))], -1) @ rot.T
        p2 = np.stack([(s[:, 2] - cx) / f, (s[:, 3] - cy) / f, np.ones(len(s))], -1) @ rot.T
        p1 /= np.linalg.norm(p1, axis=-1, keepdims=True)
        p2 /= np.linalg.norm(p2, axis=-1, keepdims=True)
        mid = p1 + p2
        own = (np.argmax(mid @ axes.T, axis=1) == k) & (lat_lon_from_direction(mid)[0] > np.radians(LOW_LAT_DEG))
        n = np.cross(p1[own], p2[own])
        nn = np.linalg.norm(n, axis=-1)
        normals.append(n / np.maximum(nn, 1e-12)[:, None])
        lengths.append(np.arcsin(np.clip(nn, 0, 1)))
    if not normals:
        return np.zeros((0, 3)), np.zeros(0)
    return np.concatenate(normals), np.concatenate(lengths)


def panorama_gravity(gray: np.ndarray, data: bytes | None = None) -> tuple[np.ndarray, dict[str, Any]]:
    """Down direction (3,) in the panorama's camera frame and ``info`` (``source``, ``tilt_deg``, the
    camera's reading and the lines' estimate when present). ``gray``: uint8 ERP (H, 2H); ``data``: the
    file's bytes, for its XMP.

    The lines' vanishing point wins when found: on a hand-held set its tilts agree with structure from
    motion within 0.2 deg rms against the camera's readings' 1.5 deg. The camera's reading is used when
    the image has too few vertical lines for a vanishing point but most of those it has agree with it.
    ``info["lines"]["beyond_search_deg"]``: the tilt of a clearly stronger vanishing point beyond
    :data:`MAX_TILT_DEG` (up to :data:`WIDE_TILT_DEG`), when there is one; the pose estimate refuses it.
    """
    info: dict[str, Any] = {}
    reading = xmp_pitch_roll(data)
    turn = file_orientation(data) if reading is not None else 1
    if turn != 1:  # the reading describes the pixels as stored, not the panorama as shown
        info["xmp"] = {"pitch_deg": reading[0], "roll_deg": reading[1],
                       "ignored": f"the file's EXIF orientation {turn} turns the image the reading describes"}
        reading = None
    normals, lengths = line_normals(gray)
    lines_down = None
    try:
        lines_down, linfo = vertical_from_lines(normals, lengths, max_tilt_deg=MAX_TILT_DEG)
        info["lines"] = {**linfo, "tilt_deg": tilt_deg(lines_down)}
    except ValueError as exc:
        info["lines"] = {"error": str(exc)}
    try:
        wide_down, winfo = vertical_from_lines(normals, lengths, max_tilt_deg=WIDE_TILT_DEG)
    except ValueError:
        wide_down = None
    if wide_down is not None and tilt_deg(wide_down) > MAX_TILT_DEG and \
            winfo["inliers"] >= BEYOND_TILT_MARGIN * info["lines"].get("inliers", 0):
        info["lines"]["beyond_search_deg"] = tilt_deg(wide_down)  # told, not used to level
    if reading is not None:
        xmp_down = down_from_pitch_roll(*reading)
        info["xmp"] = {"pitch_deg": reading[0], "roll_deg": reading[1]}
        if lines_down is not None:
            info["xmp"]["lines_gap_deg"] = float(np.degrees(np.arccos(np.clip(xmp_down @ lines_down, -1, 1))))
        else:
            count, share = line_support(normals, lengths, xmp_down, agree_deg=XMP_AGREE_DEG, max_tilt_deg=MAX_TILT_DEG)
            info["xmp"].update(agreeing_lines=count, agreeing_share=share)
            if count >= 3 and share >= 0.5:
                return xmp_down, {"source": "xmp", "tilt_deg": tilt_deg(xmp_down), **info}
    if lines_down is not None:
        return lines_down, {"source": "lines", "tilt_deg": tilt_deg(lines_down), **info}
    return np.array([0.0, 1.0, 0.0]), {"source": "none", "tilt_deg": 0.0, **info}
