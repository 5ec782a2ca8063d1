"""Dual-fisheye frames (two image circles on black) are refused as panoramas; panoramas, dark ones included, are not."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from service.errors import BadInput
from service.fisheye import looks_dual_fisheye
from service.images import decode_rgb

from ._support import panorama


def erp(height: int = 256, seed: int = 0) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(panorama(height, seed=seed))).convert("RGB"))


def dual_fisheye(pano: np.ndarray, fov_deg: float = 190.0, diameter: float = 1.0) -> np.ndarray:
    """A camera's raw frame of the scene ``pano`` shows: two equidistant fisheye circles (front, back) on black,
    each ``diameter`` times the frame's height."""
    h, w = pano.shape[:2]
    out = np.zeros_like(pano)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    radius = 0.5 * h * diameter
    for k, cx in enumerate((0.5 * h, 1.5 * h)):
        u, v = (xx - cx) / radius, (yy - 0.5 * h) / radius
        r = np.hypot(u, v)
        inside = (r <= 1.0) & (np.abs(xx - cx) <= 0.5 * h)
        theta, phi = r * np.radians(fov_deg) / 2.0, np.arctan2(v, u)
        d = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)
        if k:  # the back lens looks along -z
            d[..., 0], d[..., 2] = -d[..., 0], -d[..., 2]
        lon, lat = np.arctan2(d[..., 0], d[..., 2]), np.arcsin(np.clip(-d[..., 1], -1, 1))
        col = np.clip(((lon + np.pi) / (2 * np.pi) * w).astype(int), 0, w - 1)
        row = np.clip(((0.5 - lat / np.pi) * h).astype(int), 0, h - 1)
        out[inside] = pano[row[inside], col[inside]]
    return out


def _jpeg(rgb: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="JPEG", quality=85)
    return buf.getvalue()


@pytest.mark.parametrize("diameter", [0.94, 1.0, 1.05])
@pytest.mark.parametrize("seed", [0, 1])
def test_a_dual_fisheye_frame_is_recognised(diameter, seed):
    assert looks_dual_fisheye(dual_fisheye(erp(seed=seed), diameter=diameter))


def test_a_dual_fisheye_upload_is_a_422_that_says_what_to_send():
    data = _jpeg(dual_fisheye(erp(512)))
    with pytest.raises(BadInput) as err:
        decode_rgb(data, "image_a", max_pixels=10**8, min_height=64)
    assert err.value.code == "dual_fisheye" and err.value.status == 422
    assert "image_a" in err.value.message and "equirectangular" in err.value.message


def test_panoramas_with_dark_poles_or_black_nadir_pass():
    pano = erp(256, seed=3)
    h = pano.shape[0]
    night = pano.copy()
    night[: int(0.15 * h)] = 0  # a black sky near the zenith
    night[-int(0.15 * h):] = 0  # and a black nadir patch
    letterbox = pano.copy()
    letterbox[: h // 4] = 0
    letterbox[-h // 4:] = 0
    for image in (pano, night, letterbox, np.zeros_like(pano), np.full_like(pano, 255)):
        assert not looks_dual_fisheye(image)
    decode_rgb(_jpeg(night), "image_a", max_pixels=10**8, min_height=64)  # no exception


def test_a_dual_fisheye_frame_with_dark_things_at_its_rim_is_recognised():
    """A dark door or shadow where the two circles meet leaves part of the rim dark; the frame is still one."""
    pano = erp(256, seed=4).copy()
    h, w = pano.shape[:2]
    for lon_deg in (-90, 90):  # the circles' sides at the equator: two doors 20 deg wide, from -40 to +30 deg
        c = int((lon_deg + 180) / 360 * w)
        pano[int(h * 60 / 180): int(h * 130 / 180), c - w // 36: c + w // 36] //= 8
    assert looks_dual_fisheye(dual_fisheye(pano))


def test_the_dev_panoramas_pass_and_their_dual_fisheye_frames_do_not(m3d_dir, zind_dir, zind2k_dir,
                                                                      bedroom_theta_dir):
    dirs = (m3d_dir, zind_dir, zind2k_dir, bedroom_theta_dir)
    files = [f for d in dirs for f in sorted((d / "images").iterdir())]
    assert len(files) >= 20
    for f in files:
        pano = np.asarray(Image.open(f).convert("RGB"))
        assert not looks_dual_fisheye(pano), f
        assert looks_dual_fisheye(dual_fisheye(pano)), f
