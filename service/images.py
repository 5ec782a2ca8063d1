"""Decode and validate uploaded ERP panoramas; encode rendered images.

Checks, in order, so that nothing expensive happens before the cheap checks pass:
the header (format, size, 2:1 aspect, minimum height, pixel cap against decompression
bombs), then the full decode (corrupt or truncated data).
"""

from __future__ import annotations

import io
import warnings
from dataclasses import dataclass

import numpy as np
from PIL import Image, UnidentifiedImageError

from .errors import BadInput, InvalidImage, PayloadTooLarge

ACCEPTED_FORMATS = ("PNG", "JPEG", "WEBP", "TIFF", "BMP")


@dataclass(frozen=True)
class ImageHeader:
    field: str
    format: str
    width: int
    height: int

    def describe(self) -> dict:
        return {"format": self.format, "width": self.width, "height": self.height}


def _open(data: bytes, field: str) -> Image.Image:
    if not data:
        raise InvalidImage(f"{field}: the file is empty")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            return Image.open(io.BytesIO(data), formats=ACCEPTED_FORMATS)
    except (Image.DecompressionBombError, Image.DecompressionBombWarning) as exc:
        raise PayloadTooLarge(f"{field}: {exc}", code="image_too_many_pixels") from None
    except UnidentifiedImageError:
        raise InvalidImage(
            f"{field}: not a readable image (accepted formats: {', '.join(ACCEPTED_FORMATS)})"
        ) from None
    except Exception as exc:  # noqa: BLE001 - any decoder failure is the file's fault
        raise InvalidImage(f"{field}: unreadable image header ({exc})") from None


def check_header(data: bytes, field: str, *, max_pixels: int, min_height: int) -> ImageHeader:
    """Parse only the header and check size and aspect ratio (no pixel decoding)."""
    im = _open(data, field)
    try:
        w, h = im.size
        fmt = im.format or "unknown"
    finally:
        im.close()
    if w <= 0 or h <= 0:
        raise InvalidImage(f"{field}: image has no pixels ({w}x{h})")
    if w * h > max_pixels:
        raise PayloadTooLarge(
            f"{field}: {w}x{h} = {w * h} pixels exceeds the limit of {max_pixels} pixels",
            code="image_too_many_pixels",
        )
    if w != 2 * h:
        raise BadInput(
            f"{field}: an equirectangular panorama must be exactly twice as wide as high; got {w}x{h}",
            code="bad_aspect_ratio",
        )
    if h < min_height:
        raise BadInput(f"{field}: {w}x{h} is too small; the height must be at least {min_height} pixels",
                       code="image_too_small")
    return ImageHeader(field, fmt, w, h)


def decode_rgb(data: bytes, field: str, *, max_pixels: int, min_height: int) -> tuple[np.ndarray, ImageHeader]:
    """Fully decode to uint8 RGB (H, W, 3) after :func:`check_header`; corrupt data -> 400."""
    header = check_header(data, field, max_pixels=max_pixels, min_height=min_height)
    im = _open(data, field)
    try:
        im.load()  # raises on truncated or corrupt data (LOAD_TRUNCATED_IMAGES stays False)
        if im.mode != "RGB":
            im = im.convert("RGB")
        arr = np.asarray(im, dtype=np.uint8)
    except PayloadTooLarge:
        raise
    except Exception as exc:  # noqa: BLE001 - corrupt, truncated, unsupported mode...
        raise InvalidImage(f"{field}: the image data is corrupt or truncated ({exc})") from None
    finally:
        im.close()
    if arr.shape != (header.height, header.width, 3):
        raise InvalidImage(f"{field}: decoded to unexpected shape {arr.shape}")
    return np.ascontiguousarray(arr), header


def to_uint8_safe(colour: np.ndarray) -> np.ndarray:
    """Float colour (H, W, 3) -> uint8, NaN/Inf mapped to black/white so no image carries NaN."""
    c = np.nan_to_num(np.asarray(colour, dtype=np.float32), nan=0.0, posinf=1.0, neginf=0.0)
    return (np.clip(c, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


MEDIA_TYPES = {"png": "image/png", "jpeg": "image/jpeg"}


def encode(rgb: np.ndarray, fmt: str) -> bytes:
    """uint8 RGB -> PNG (fast compression) or JPEG (quality 92) bytes."""
    buf = io.BytesIO()
    im = Image.fromarray(np.ascontiguousarray(rgb))
    if fmt == "png":
        im.save(buf, format="PNG", compress_level=3)
    elif fmt == "jpeg":
        im.save(buf, format="JPEG", quality=92)
    else:  # pragma: no cover - guarded by the query model
        raise BadInput(f"unknown image format {fmt!r}")
    return buf.getvalue()
