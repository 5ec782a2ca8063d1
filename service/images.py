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

from rasterizer.render import to_uint8

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


def _too_many_pixels(field: str, w: int, h: int, max_pixels: int) -> PayloadTooLarge:
    return PayloadTooLarge(f"{field}: {w}x{h} = {w * h} pixels exceeds the limit of {max_pixels} pixels",
                           code="image_too_many_pixels")


def _open(data: bytes, field: str, max_pixels: int) -> Image.Image:
    if not data:
        raise InvalidImage(f"{field}: the file is empty")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            return Image.open(io.BytesIO(data), formats=ACCEPTED_FORMATS)
    except (Image.DecompressionBombError, Image.DecompressionBombWarning):
        # Pillow's own bomb guard (2x its MAX_IMAGE_PIXELS) fired before ours could: report ours
        raise PayloadTooLarge(f"{field}: the image has more than the limit of {max_pixels} pixels",
                              code="image_too_many_pixels") from None
    except UnidentifiedImageError:
        raise InvalidImage(
            f"{field}: not a readable image (accepted formats: {', '.join(ACCEPTED_FORMATS)})"
        ) from None
    except Exception as exc:  # noqa: BLE001 - any decoder failure is the file's fault
        raise InvalidImage(f"{field}: unreadable image header ({exc})") from None


def check_header(data: bytes, field: str, *, max_pixels: int, min_height: int) -> ImageHeader:
    """Parse only the header and check size and aspect ratio (no pixel decoding)."""
    im = _open(data, field, max_pixels)
    try:
        w, h = im.size
        fmt = im.format or "unknown"
    finally:
        im.close()
    if w <= 0 or h <= 0:
        raise InvalidImage(f"{field}: image has no pixels ({w}x{h})")
    if w * h > max_pixels:
        raise _too_many_pixels(field, w, h, max_pixels)
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
    im = _open(data, field, max_pixels)
    try:
        im.load()  # raises on truncated or corrupt data (LOAD_TRUNCATED_IMAGES stays False)
        arr = _rgb8(im, field)
    except (PayloadTooLarge, InvalidImage):
        raise
    except Exception as exc:  # noqa: BLE001 - corrupt, truncated, unsupported mode...
        raise InvalidImage(f"{field}: the image data is corrupt or truncated ({exc})") from None
    finally:
        im.close()
    if arr.shape != (header.height, header.width, 3):
        raise InvalidImage(f"{field}: decoded to unexpected shape {arr.shape}")
    return np.ascontiguousarray(arr), header


def _rgb8(im: Image.Image, field: str) -> np.ndarray:
    """8-bit RGB of a decoded image; 16-bit and float greyscale are scaled by their full range.

    Pillow's ``convert("RGB")`` clips 16-bit values at 255 (a white image) and truncates
    floats in [0, 1] to 0 (a black one), so those modes are scaled here first.
    """
    if im.mode.startswith("I;16") or im.mode == "I":
        grey = np.asarray(im).astype(np.float64)
        if grey.size and (grey.min() < 0 or grey.max() > 65535):
            raise InvalidImage(f"{field}: 32-bit integer images are not supported (values beyond 16 bits); "
                               "send 8- or 16-bit PNG/TIFF", code="unsupported_image_mode")
        grey = to_uint8(grey / 65535.0)
    elif im.mode == "F":
        grey = np.asarray(im)
        if not np.all(np.isfinite(grey)) or (grey.size and (grey.min() < 0 or grey.max() > 1)):
            raise InvalidImage(f"{field}: float images must hold finite values in [0, 1]",
                               code="unsupported_image_mode")
        grey = to_uint8(grey)
    else:
        return np.asarray(im if im.mode == "RGB" else im.convert("RGB"), dtype=np.uint8)
    return np.repeat(grey[:, :, None], 3, axis=2)


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
