"""Decode and validate uploaded ERP panoramas; encode rendered images.

Checks, in order, so that nothing expensive happens before the cheap checks pass:
the header (format, size, 2:1 aspect as shown after the EXIF orientation, one frame, minimum
height, pixel cap against decompression bombs), then the full decode (corrupt or truncated data), then
what the pixels show (a camera's raw dual-fisheye frame is no panorama: :mod:`service.fisheye`; one flat colour
shows no scene: :func:`check_not_blank`; two uploads of one picture carry no depth: :func:`same_picture`).

A PNG's chunk list is walked first (:func:`scan_png`, a loop over chunk headers that stops at
the first limit passed, no decoding): Pillow keeps every ancillary chunk before the image data
in memory, so a file of millions of empty private chunks would cost seconds and hundreds of
MB before any pixel check. At most :data:`MAX_PNG_ANCILLARY_CHUNKS` ancillary chunks of
:data:`MAX_PNG_ANCILLARY_BYTES` in all, and :data:`MAX_PNG_CHUNKS` chunks in all plus one per
:data:`PNG_BYTES_PER_EXTRA_CHUNK` bytes of file (image data split into small chunks) are
accepted (413 beyond); a JPEG's marker segments likewise (:func:`scan_jpeg`). Before the full
decode, the PNG's compressed image data is inflated
and counted (not kept): Pillow stops without an error when the compressed stream ends early,
leaving the missing rows black, so a PNG whose data holds fewer rows than its header
declares is refused (400). A JPEG's scans are checked likewise (:mod:`service.jpeg_data`): libjpeg fills a scan
cut short with grey, or a progressive image cut between scans with a blur, and Pillow does not say.
"""

from __future__ import annotations

import io
import math
import struct
import warnings
import zlib
from dataclasses import dataclass

import numpy as np
from PIL import Image, UnidentifiedImageError

from rasterizer.render import to_uint8
from rasterizer.threads import map_threads

from .errors import BadInput, InvalidImage, PayloadTooLarge
from .fisheye import check_not_dual_fisheye
from .jpeg_data import check_jpeg_data, jpeg_segments

ACCEPTED_FORMATS = ("PNG", "JPEG", "WEBP", "TIFF", "BMP")
#: the first bytes of each accepted format's files (a WebP also has "WEBP" at byte 8)
_MAGIC = (("PNG", b"\x89PNG\r\n\x1a\n"), ("JPEG", b"\xff\xd8\xff"), ("WEBP", b"RIFF"), ("TIFF", b"II*\x00"),
          ("TIFF", b"MM\x00*"), ("BMP", b"BM"))


@dataclass(frozen=True)
class ImageHeader:
    field: str
    format: str
    width: int  # as displayed: after the EXIF orientation
    height: int
    orientation: int = 1  # EXIF orientation tag (1: as stored)
    reduction: int = 1  # a JPEG decoded at 1/reduction of its size in each axis (:func:`jpeg_reduction`)

    @property
    def decoded_size(self) -> tuple[int, int]:
        """(width, height) of the decoded image as displayed."""
        return self.width // self.reduction, self.height // self.reduction

    def describe(self) -> dict:
        out = {"format": self.format, "width": self.width, "height": self.height}
        if self.reduction > 1:
            out["decoded_width"], out["decoded_height"] = self.decoded_size
        return out if self.orientation == 1 else {**out, "exif_orientation": self.orientation}


#: JPEG's DCT scales that a decoder reads without decoding the whole raster (libjpeg's 1/2, 1/4 and 1/8)
JPEG_REDUCTIONS = (8, 4, 2)
#: A baseline JPEG decoded at a reduced scale may declare up to this many times the pixel cap (16384 x 8192 at the
#: default cap): the cap bounds what is decoded, this the entropy decoding, which reads every block (0.23-0.26 s at
#: 16384 x 8192, 20 MB above the output).
MAX_REDUCED_JPEG_FACTOR = 4


def jpeg_reduction(fmt: str, width: int, height: int, min_width: int | None) -> int:
    """The divisor (8, 4, 2 or 1) at which a ``fmt`` image of ``width`` x ``height`` displayed pixels is decoded.

    A JPEG is decoded at the coarsest DCT scale that keeps at least ``min_width`` columns (the widest any
    later stage reads) and divides both sides exactly, so that it stays exactly 2:1; every other format, and
    ``min_width`` None, decode whole. A 5760 x 2880 JPEG read at 2880 x 1440 for a 2048-wide reader decodes in
    about a fifth of the time into a quarter of the memory, and the stages that resize it to 2048 or 1024 columns
    do a quarter of the work.
    """
    if min_width is None or fmt not in ("JPEG", "MPO"):
        return 1
    return next((r for r in JPEG_REDUCTIONS if width // r >= min_width and width % r == 0 and height % r == 0), 1)


#: EXIF orientation tag
_ORIENTATION = 0x0112


def exif_orientation(im: Image.Image) -> int:
    """The EXIF orientation (1..8; 1 = as stored) of an opened image, read from its header only.

    Every image viewer shows a file turned by this tag, so the panorama a user means is the turned one
    (5..8 swap width and height). A PNG whose EXIF chunk follows the pixels is read as stored (1):
    finding it would decode the image. An unreadable tag is 1, as viewers read it.
    """
    if im.format == "PNG" and "exif" not in im.info:
        return 1
    try:
        value = im.getexif().get(_ORIENTATION, 1)
    except Exception:  # noqa: BLE001 - damaged EXIF: shown as stored
        return 1
    return value if isinstance(value, int) and 1 <= value <= 8 else 1


#: the turn that shows an image stored with each EXIF orientation (the EXIF/TIFF definition, as ImageOps.exif_transpose)
_SHOW = {2: Image.Transpose.FLIP_LEFT_RIGHT, 3: Image.Transpose.ROTATE_180, 4: Image.Transpose.FLIP_TOP_BOTTOM,
         5: Image.Transpose.TRANSPOSE, 6: Image.Transpose.ROTATE_270, 7: Image.Transpose.TRANSVERSE,
         8: Image.Transpose.ROTATE_90}
#: TIFF ImageWidth and ImageLength tags
_TIFF_WIDTH, _TIFF_LENGTH = 256, 257


def stored_size(im: Image.Image) -> tuple[int, int]:
    """(width, height) of an opened image's raster as stored in the file, before any EXIF orientation.

    Pillow reports a TIFF's size already turned by its Orientation tag (and turns its pixels on load), every
    other format's as stored; a TIFF's own ImageWidth/ImageLength tags say the stored size whatever Pillow does.
    """
    if im.format == "TIFF":
        w, h = im.tag_v2.get(_TIFF_WIDTH), im.tag_v2.get(_TIFF_LENGTH)
        if isinstance(w, int) and isinstance(h, int):
            return w, h
    return im.size


def show_upright(im: Image.Image, orientation: int, shown: tuple[int, int]) -> Image.Image:
    """A loaded image turned by its EXIF ``orientation`` exactly once; ``shown``: its (width, height) as shown.

    A decoder that turns the pixels itself (Pillow's TIFF reader) drops the tag as it does, as
    ``ImageOps.exif_transpose`` does: a loaded image that no longer carries the tag is already upright, and so is
    one of a quarter turn (5..8) that already has the shown size (a 2:1 panorama is stored 1:2).
    """
    if orientation == 1 or exif_orientation(im) == 1 or (orientation >= 5 and im.size == shown):
        return im
    return im.transpose(_SHOW[orientation])


def file_orientation(data: bytes) -> int:
    """The EXIF orientation (:func:`exif_orientation`) of an image file's bytes; 1 when it cannot be read."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(io.BytesIO(data), formats=ACCEPTED_FORMATS) as im:
                return exif_orientation(im)
    except Exception:  # noqa: BLE001 - an unreadable header has no orientation
        return 1


def _too_many_pixels(field: str, w: int, h: int, max_pixels: int, jpeg_factor: int = 0) -> PayloadTooLarge:
    jpeg = f" ({jpeg_factor * max_pixels} for a baseline JPEG, which is decoded at a reduced scale)" if jpeg_factor else ""
    return PayloadTooLarge(f"{field}: {w}x{h} = {w * h} pixels exceeds the limit of {max_pixels} pixels{jpeg}",
                           code="image_too_many_pixels")


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: ancillary (lower-case first letter) chunks a PNG may hold, and their payload bytes in all
MAX_PNG_ANCILLARY_CHUNKS = 1024
MAX_PNG_ANCILLARY_BYTES = 16 * 1024 * 1024
#: chunks of any kind a PNG may hold, plus one per this many bytes of file
MAX_PNG_CHUNKS = 4096
PNG_BYTES_PER_EXTRA_CHUNK = 1024
#: channels per PNG colour type (greyscale, RGB, palette, grey + alpha, RGBA)
_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}
_ADAM7 = ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2))


@dataclass(frozen=True)
class PngLayout:
    """What :func:`scan_png` found: the IHDR fields and where the compressed image data lies."""

    width: int
    height: int
    bit_depth: int
    colour_type: int
    interlaced: bool
    idat: tuple[tuple[int, int], ...]  # (offset, length) of each IDAT payload, in file order

    def raw_bytes(self) -> int | None:
        """Bytes of filtered scanlines the header promises (None: an IHDR this check does not know)."""
        channels = _PNG_CHANNELS.get(self.colour_type)
        if channels is None or self.bit_depth not in (1, 2, 4, 8, 16):
            return None
        bits = channels * self.bit_depth
        passes = _ADAM7 if self.interlaced else ((0, 0, 1, 1),)
        total = 0
        for x0, y0, dx, dy in passes:
            w, h = -(-(self.width - x0) // dx), -(-(self.height - y0) // dy)
            if w > 0 and h > 0:
                total += h * (1 + -(-(w * bits) // 8))
        return total


def scan_png(data: bytes, field: str) -> PngLayout | None:
    """Walk a PNG's chunk list (headers only); 413 past the chunk limits. None: not a PNG, or
    one this walk cannot follow (Pillow then reports it)."""
    if not data.startswith(PNG_SIGNATURE):
        return None
    max_chunks = MAX_PNG_CHUNKS + len(data) // PNG_BYTES_PER_EXTRA_CHUNK
    pos, chunks, ancillary, ancillary_bytes = len(PNG_SIGNATURE), 0, 0, 0
    ihdr, idat = None, []
    while pos + 8 <= len(data):
        length, kind = struct.unpack_from(">I4s", data, pos)
        start = pos + 8
        chunks += 1
        if chunks > max_chunks:
            raise PayloadTooLarge(f"{field}: the PNG holds more than {max_chunks} chunks", code="image_too_many_chunks")
        if kind[:1].islower():
            ancillary += 1
            ancillary_bytes += length
            if ancillary > MAX_PNG_ANCILLARY_CHUNKS or ancillary_bytes > MAX_PNG_ANCILLARY_BYTES:
                raise PayloadTooLarge(f"{field}: the PNG holds more than {MAX_PNG_ANCILLARY_CHUNKS} ancillary chunks "
                                      f"or {MAX_PNG_ANCILLARY_BYTES} bytes of them (metadata, not pixels)",
                                      code="image_too_many_chunks")
        elif kind == b"IHDR" and length == 13 and start + 13 <= len(data):
            ihdr = struct.unpack_from(">IIBBBBB", data, start)
        elif kind == b"IDAT":
            idat.append((start, min(length, max(0, len(data) - start))))
        elif kind == b"IEND":
            break
        pos = start + length + 4  # payload and CRC
    if ihdr is None:
        return None
    width, height, depth, colour, _, _, interlace = ihdr
    return PngLayout(width, height, depth, colour, interlace == 1, tuple(idat))


def check_png_data(data: bytes, layout: PngLayout, field: str) -> None:
    """400 when the compressed image data inflates to fewer scanline bytes than the header declares."""
    need = layout.raw_bytes()
    if need is None:
        return
    inflate = zlib.decompressobj()
    got = 0
    view = memoryview(data)
    try:
        for offset, length in layout.idat:
            pending = view[offset:offset + length]
            while pending and got < need:
                got += len(inflate.decompress(pending, 1 << 20))  # counted, not kept
                pending = inflate.unconsumed_tail
            if got >= need or inflate.eof:
                break
    except zlib.error:
        raise InvalidImage(f"{field}: the PNG's image data is corrupt (it does not inflate)") from None
    if got < need:
        per_row = need / max(layout.height, 1)
        raise InvalidImage(f"{field}: the PNG's image data is truncated: it holds about {math.floor(got / per_row)} of "
                           f"the {layout.height} rows its header declares")


def scan_jpeg(data: bytes, field: str) -> None:
    """Walk a JPEG's marker segments up to the start of scan (headers only, :func:`service.jpeg_data.jpeg_segments`,
    which refuses millions of segments or of fill bytes); 413 past the limits.

    Pillow keeps every APPn/COM segment in memory and steps through padding byte by byte, so a file of millions of
    empty APP segments costs as much as the PNG chunk bomb: the APPn/COM segments count against the PNG's
    ancillary limits."""
    meta, meta_bytes = 0, 0
    for marker, length, _ in jpeg_segments(data, field, scans=False):
        if 0xE0 <= marker <= 0xEF or marker == 0xFE:
            meta += 1
            meta_bytes += length
            if meta > MAX_PNG_ANCILLARY_CHUNKS or meta_bytes > MAX_PNG_ANCILLARY_BYTES:
                raise PayloadTooLarge(f"{field}: the JPEG holds more than {MAX_PNG_ANCILLARY_CHUNKS} metadata segments "
                                      f"or {MAX_PNG_ANCILLARY_BYTES} bytes of them", code="image_too_many_chunks")


def _open(data: bytes, field: str, max_pixels: int) -> Image.Image:
    if not data:
        raise InvalidImage(f"{field}: the file is empty")
    scan_png(data, field)  # before Pillow reads the chunks
    scan_jpeg(data, field)
    try:
        with warnings.catch_warnings():  # Pillow warns from 89.5 M pixels: check_header's caps decide
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            return Image.open(io.BytesIO(data), formats=ACCEPTED_FORMATS)
    except Image.DecompressionBombError:
        # Pillow's own bomb guard (2x its MAX_IMAGE_PIXELS) fired before ours could: report ours
        raise PayloadTooLarge(f"{field}: the image has more than the limit of {max_pixels} pixels",
                              code="image_too_many_pixels") from None
    except UnidentifiedImageError:
        kind = next((name for name, magic in _MAGIC if data.startswith(magic) and (name != "WEBP" or data[8:12] == b"WEBP")),
                    None)
        if kind is not None:  # the format is one we take; this file of it is not
            raise InvalidImage(f"{field}: a {kind} file that cannot be decoded (cut short, damaged, or a sample format "
                               "such as 32-bit float colour); send 8- or 16-bit RGB") from None
        raise InvalidImage(
            f"{field}: not a readable image (accepted formats: {', '.join(ACCEPTED_FORMATS)})"
        ) from None
    except Exception as exc:  # noqa: BLE001 - any decoder failure is the file's fault
        raise InvalidImage(f"{field}: unreadable image header ({_fault(exc)})") from None


def _fault(exc: Exception) -> str:
    """What a decoder's exception says about the file, in the user's terms (no library internals)."""
    return "the file is truncated" if "truncated" in str(exc).lower() else "the file is damaged or not what it claims to be"


def check_header(data: bytes, field: str, *, max_pixels: int, min_height: int,
                 min_width: int | None = None) -> ImageHeader:
    """Parse only the header and check size and aspect ratio (no pixel decoding).

    ``max_pixels`` caps the pixels decoded: a baseline JPEG that :func:`jpeg_reduction` reads at a reduced scale
    for ``min_width`` counts at that scale, and may declare up to :data:`MAX_REDUCED_JPEG_FACTOR` times the cap.
    """
    im = _open(data, field, max_pixels)
    try:
        w, h = stored_size(im)
        fmt = im.format or "unknown"
        orientation = exif_orientation(im)
        # a JPEG with an MPF second image (a preview, a depth map, a stereo eye) is shown by its primary image,
        # the frame Pillow opens: only animations and multi-page files hold frames that are all "the image"
        frames = getattr(im, "is_animated", False) and fmt != "MPO"
        progressive = bool(im.info.get("progressive"))
    finally:
        im.close()
    if w <= 0 or h <= 0:
        raise InvalidImage(f"{field}: image has no pixels ({w}x{h})")
    reduction = jpeg_reduction(fmt, *((h, w) if orientation >= 5 else (w, h)), min_width)
    # a progressive JPEG keeps every DCT coefficient of the whole image until its last scan, at any output scale
    # (0.8 GB and 1.9 s at 16384 x 8192 against 20 MB and 0.26 s for a baseline one): only the header counts
    allowance = MAX_REDUCED_JPEG_FACTOR if reduction > 1 and not progressive else 0
    if w * h > max_pixels and (not allowance or (w // reduction) * (h // reduction) > max_pixels
                               or w * h > allowance * max_pixels):
        raise _too_many_pixels(field, w, h, max_pixels, allowance)
    if frames:  # only the first frame would be used, without a word
        raise BadInput(f"{field}: the {fmt} file holds several frames (an animation or pages); send one still "
                       "panorama", code="animated_image")
    if orientation >= 5:  # turned by a quarter: shown as h x w
        w, h = h, w
    if w != 2 * h:
        turned = f" (as shown, after its EXIF orientation {orientation})" if orientation != 1 else ""
        raise BadInput(
            f"{field}: an equirectangular panorama must be exactly twice as wide as high; got {w}x{h}{turned}",
            code="bad_aspect_ratio",
        )
    if h < min_height:
        raise BadInput(f"{field}: {w}x{h} is too small; the height must be at least {min_height} pixels",
                       code="image_too_small")
    return ImageHeader(field, fmt, w, h, orientation, reduction)


def decode_rgb(data: bytes, field: str, *, max_pixels: int, min_height: int,
               min_width: int | None = None) -> tuple[np.ndarray, ImageHeader]:
    """Decode to uint8 RGB (H, W, 3), turned by its EXIF orientation, after :func:`check_header`; corrupt
    data -> 400. A JPEG wider than twice ``min_width`` is decoded at a reduced DCT scale
    (:func:`jpeg_reduction`; the header's ``decoded_size``), every other image whole."""
    header = check_header(data, field, max_pixels=max_pixels, min_height=min_height, min_width=min_width)
    layout = scan_png(data, field)
    if layout is not None:
        check_png_data(data, layout, field)
    if header.format in ("JPEG", "MPO"):
        check_jpeg_data(data, field)
    im = _open(data, field, max_pixels)
    shown = header.decoded_size
    try:
        if header.reduction > 1:
            im.draft(im.mode, shown[::-1] if header.orientation >= 5 else shown)
        im.load()  # raises on truncated or corrupt data (LOAD_TRUNCATED_IMAGES stays False)
        arr = _rgb8(show_upright(im, header.orientation, shown), field)
    except (PayloadTooLarge, InvalidImage, BadInput):
        raise
    except Exception as exc:  # noqa: BLE001 - corrupt, truncated, unsupported mode...
        raise InvalidImage(f"{field}: the image data is corrupt or truncated ({_fault(exc)})") from None
    finally:
        im.close()
    if arr.shape != (shown[1], shown[0], 3):
        raise InvalidImage(f"{field}: decoded to unexpected shape {arr.shape}")
    check_not_dual_fisheye(arr, field)
    return np.ascontiguousarray(arr), header


#: rows of a greyscale image converted at a time (about this many pixels), so that no temporary is full-size
GREY_BLOCK_PIXELS = 1 << 20


def _rgb8(im: Image.Image, field: str) -> np.ndarray:
    """8-bit RGB (H, W, 3) of a decoded image; 16-bit and float greyscale are scaled by their full range.

    Pillow's ``convert("RGB")`` clips 16-bit values at 255 (a white image) and truncates
    floats in [0, 1] to 0 (a black one), so those modes are scaled here first.
    """
    if im.mode.startswith("I;16") or im.mode == "I":
        return _grey_rgb8(np.asarray(im), field, _grey16_block)
    if im.mode == "F":
        return _grey_rgb8(np.asarray(im), field, _float_block)
    _check_opaque(im, field)
    return np.asarray(im if im.mode == "RGB" else im.convert("RGB"), dtype=np.uint8)


def _grey_rgb8(grey: np.ndarray, field: str, block_to_uint8) -> np.ndarray:
    """(H, W) greyscale -> uint8 (H, W, 3), a block of rows at a time: the scaling's temporaries stay about
    :data:`GREY_BLOCK_PIXELS` pixels, not several full-size float64 copies (~1 GB for an 8192x4096 image)."""
    h, w = grey.shape
    out = np.empty((h, w, 3), np.uint8)
    rows = max(1, GREY_BLOCK_PIXELS // max(w, 1))
    for top in range(0, h, rows):
        out[top:top + rows] = block_to_uint8(grey[top:top + rows], field)[:, :, None]
    return out


def _grey16_block(grey: np.ndarray, field: str) -> np.ndarray:
    """16-bit (or 32-bit integer holding 16-bit) grey -> uint8, v * 255 / 65535 = v / 257 rounded half up."""
    if grey.size and (grey.min() < 0 or grey.max() > 65535):
        raise InvalidImage(f"{field}: 32-bit integer images are not supported (values beyond 16 bits); "
                           "send 8- or 16-bit PNG/TIFF", code="unsupported_image_mode")
    return ((grey.astype(np.uint32) * 2 + 257) // 514).astype(np.uint8)


def _float_block(grey: np.ndarray, field: str) -> np.ndarray:
    """Float grey in [0, 1] -> uint8 (:func:`to_uint8`); anything else (NaN, out of range) is refused."""
    if not np.all(np.isfinite(grey)) or (grey.size and (grey.min() < 0 or grey.max() > 1)):
        raise InvalidImage(f"{field}: float images must hold finite values in [0, 1]", code="unsupported_image_mode")
    return to_uint8(grey)


#: Pillow modes with an alpha band (premultiplied ones included)
_ALPHA_MODES = ("RGBA", "RGBa", "LA", "La", "PA")


def _check_opaque(im: Image.Image, field: str) -> None:
    """Refuse transparent pixels: the colour stored under them is undefined (often black), and a panorama
    needs one at every pixel. Alpha 255 everywhere (an opaque RGBA export) passes. Only a mode's alpha band counts:
    LAB's "A" band is a colour (a*)."""
    if im.mode in _ALPHA_MODES:
        alpha = np.asarray(im.getchannel("A"))
    elif im.mode == "P" and "transparency" in im.info:
        alpha = np.asarray(im.convert("RGBA").getchannel("A"))
    else:
        return
    clear = int(np.count_nonzero(alpha < 255))
    if clear:
        raise BadInput(f"{field}: {clear} pixels ({clear / alpha.size:.1%}) are transparent; a panorama needs a colour "
                       "at every pixel: flatten it onto a background first", code="transparent_image")


MEDIA_TYPES = {"png": "image/png", "jpeg": "image/jpeg"}


def encode(rgb: np.ndarray, fmt: str) -> bytes:
    """uint8 RGB -> PNG or JPEG (quality 92) bytes.

    The PNG's deflate stream uses zlib's run-length strategy after PNG's own row filters: on the service's
    renders 10-17% fewer bytes than zlib's default strategy in 20-45% less time (a 1280x720 view 576 -> 476 kB,
    93-99 -> 57-79 ms; a 2048-wide ERP 1.61 -> 1.41 MB, 258-277 -> 155-179 ms), and a third fewer for masks.
    """
    buf = io.BytesIO()
    im = Image.fromarray(np.ascontiguousarray(rgb))
    if fmt == "png":
        im.save(buf, format="PNG", compress_level=3, compress_type=zlib.Z_RLE)
    elif fmt == "jpeg":
        im.save(buf, format="JPEG", quality=92)
    else:  # pragma: no cover - guarded by the query model
        raise BadInput(f"unknown image format {fmt!r}")
    return buf.getvalue()


#: A panorama whose every channel spans at most this many levels (of 255) over the whole image shows one flat colour
#: (a capped lens, a blank export, or 8-bit values stored in a 16-bit file, which read as black): it shows no scene.
BLANK_LEVELS = 2


def check_not_blank(erp: np.ndarray, field: str) -> None:
    """422 ``blank_image`` when an ERP (uint8, or float in [0, 1]) shows one flat colour (:data:`BLANK_LEVELS`): the
    reconstruction would be a scene of that colour, with nothing matched or triangulated."""
    erp = np.asarray(erp)
    channels = [erp] if erp.ndim == 2 else [erp[..., c] for c in range(erp.shape[-1])]
    scale = 1.0 if erp.dtype == np.uint8 else 255.0
    # a coarse look settles any real panorama; the whole image is read only when that look is flat
    for step in (8, 1):
        if max(float(ch[::step, ::step].max()) - float(ch[::step, ::step].min()) for ch in channels) * scale > BLANK_LEVELS:
            return
    raise BadInput(f"{field}: every pixel shows the same colour (within {BLANK_LEVELS} levels of 255): a panorama "
                   "of a scene shows its detail; check the file (a covered lens, a blank export, or 8-bit values "
                   "stored in a 16-bit image, which read as black)", code="blank_image")


#: Two panoramas whose grey thumbnails correlate this well are one picture: a JPEG re-encoding (quality 30), a
#: resize, noise of sd 0.08 or a gamma of 0.7 of a dev panorama correlate at 0.993 or more with the original, while
#: two captures of a dev room, however near (0.36 m: 0.65) or alike in heading, reach at most 0.75.
SAME_PICTURE_ZNCC = 0.99
#: Rows of the thumbnails :func:`same_picture` compares (1.4 deg a pixel).
SAME_PICTURE_HEIGHT = 128


def same_picture(erp_a: np.ndarray, erp_b: np.ndarray) -> bool:
    """Whether two ERPs (any sizes, RGB or grey, uint8 or [0, 1] float) are one picture: equal, or their grey
    thumbnails' zero-mean normalised correlation at least :data:`SAME_PICTURE_ZNCC` (the same view pixel for pixel;
    two places differ by their parallax)."""
    import cv2

    def thumbnail(erp):  # area-averaged before the grey conversion, which costs ~0.7 s at 5760x2880 full size
        small = cv2.resize(np.asarray(erp), (2 * SAME_PICTURE_HEIGHT, SAME_PICTURE_HEIGHT), interpolation=cv2.INTER_AREA)
        small = small.astype(np.float32)
        grey = cv2.cvtColor(small, cv2.COLOR_RGB2GRAY) if small.ndim == 3 else small
        return grey.astype(np.float64) - grey.mean()

    a, b = map_threads(thumbnail, (erp_a, erp_b))
    den = np.sqrt(np.sum(a * a) * np.sum(b * b))
    if den == 0:  # a flat thumbnail: the same picture only if equal
        return bool(np.array_equal(erp_a, erp_b))  # False for different shapes
    return bool(np.sum(a * b) >= SAME_PICTURE_ZNCC * den)
