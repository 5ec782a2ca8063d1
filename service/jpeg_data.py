"""Whether an uploaded JPEG's image data is whole: libjpeg makes up what a damaged file lacks without an error.

A JPEG cut short and closed with an end-of-image marker decodes through Pillow without a word: libjpeg warns
("premature end of data segment") and fills the rest of a baseline scan with grey 128, or of a progressive
scan with what the earlier scans gave, and Pillow silences libjpeg's warnings. A progressive JPEG cut between two
scans draws no warning at all: the refinement scans that never came leave a blurred image. Two checks refuse
both with a 400 before Pillow decodes the file:

- :func:`missing_coefficients`: the scan headers up to the end-of-image marker must send every DCT coefficient
  of every component down to its last bit (a walk over the file's markers, no decoding);
- :func:`libjpeg_warning`: libjpeg-turbo (through simplejpeg) decodes the file at 1/8 scale in grey with its
  warnings reported; at that scale it still reads every block of every component (the entropy decoding, where
  a cut or corrupt scan is found) but computes one value per block.

The only warning taken as harmless is junk before the end-of-image marker: it is read after every block.
The check costs about what libjpeg's entropy decoding does, which Pillow's decode then repeats: 5 ms for a
2048 x 1024 camera JPEG, 20-45 ms for a 5760 x 2880 baseline one, 150-200 ms for a progressive one (every scan
is decoded at any scale), 0.37 s for a noisy 16384 x 8192 baseline one.
"""

from __future__ import annotations

import re
from collections.abc import Iterator

import numpy as np
import simplejpeg

from .errors import InvalidImage, PayloadTooLarge

#: segments a JPEG may hold (headers and scans), and bytes of padding or junk between them: each is a step of a
#: loop in Python, so a file of millions of empty segments or of fill is refused (413) before it is walked
MAX_JPEG_SEGMENTS = 4096
MAX_JPEG_GAP_BYTES = 1024 * 1024
#: start-of-frame markers whose scans each send all 64 coefficients of their components (baseline, extended,
#: arithmetic sequential), and those whose scans send bands of coefficients and bits (progressive, Huffman and
#: arithmetic); other frames (lossless, hierarchical) are left to the decoder
_SEQUENTIAL_SOF = frozenset((0xC0, 0xC1, 0xC9))
_PROGRESSIVE_SOF = frozenset((0xC2, 0xCA))
_SOS, _EOI = 0xDA, 0xD9
#: the one libjpeg warning that loses no pixel: junk bytes between the last scan and the end-of-image marker
_HARMLESS_WARNING = re.compile(r"extraneous bytes before marker 0xd9", re.IGNORECASE)
_NOT_FF = re.compile(rb"[^\xff]")
#: where a scan's entropy-coded data ends: the last 0xFF before a byte that makes it a marker (neither a stuffed
#: 0x00, a restart marker 0xD0..0xD7 inside the scan, nor more fill)
_SCAN_END = re.compile(rb"\xff(?=[^\x00\xff\xd0-\xd7])")


def jpeg_segments(data: bytes, field: str, *, scans: bool) -> Iterator[tuple[int, int, bytes]]:
    """(marker, declared length, body) of each marker segment of a JPEG, in file order, from its start-of-image
    marker: up to its first start of scan (``scans`` False: the headers, which Pillow reads) or through its scans
    to the first end-of-image marker (True; a camera's MPF preview after it is another image), each scan's
    entropy-coded data skipped to the marker that ends it. Nothing for data that is no JPEG.

    Between segments, junk and 0xFF fill are stepped over as libjpeg does; a 413 past :data:`MAX_JPEG_SEGMENTS`
    segments or :data:`MAX_JPEG_GAP_BYTES` bytes of fill and junk (a loop in Python per segment). The one walker
    of the JPEG structure: :func:`service.images.scan_jpeg` and :func:`missing_coefficients` read it.
    """
    if not data.startswith(b"\xff\xd8"):
        return
    pos, segments, gap = 2, 0, 0
    while pos + 4 <= len(data):
        horizon = min(len(data), pos + MAX_JPEG_GAP_BYTES - gap + 2)  # no search past the limit
        if data[pos] != 0xFF:  # junk up to the next marker
            nxt = data.find(b"\xff", pos, horizon)
            nxt = horizon if nxt < 0 else nxt
            gap, pos = gap + nxt - pos, nxt
        else:
            found = _NOT_FF.search(data, pos + 1, horizon)  # fill bytes: 0xFF repeated before a marker
            end = found.start() if found else horizon
            gap, pos = gap + end - pos - 1, end - 1
        if gap > MAX_JPEG_GAP_BYTES:
            raise PayloadTooLarge(f"{field}: the JPEG holds more than {MAX_JPEG_GAP_BYTES} bytes of padding between "
                                  "its segments", code="image_too_many_chunks")
        if pos + 4 > len(data):
            return
        if data[pos] != 0xFF or data[pos + 1] == 0xFF:
            continue  # at the marker after junk, or a fill run the search's horizon cut: step over its fill first
        marker = data[pos + 1]
        if marker == 0x00:  # a stuffed zero outside a scan: junk, as libjpeg reads it
            gap, pos = gap + 2, pos + 2
            continue
        if marker == _EOI or (marker == _SOS and not scans):
            return
        if marker == 0x01 or 0xD0 <= marker <= 0xD8:  # markers without a length
            pos += 2
            continue
        length = (data[pos + 2] << 8) | data[pos + 3]
        segments += 1
        if segments > MAX_JPEG_SEGMENTS:
            raise PayloadTooLarge(f"{field}: the JPEG holds more than {MAX_JPEG_SEGMENTS} segments",
                                  code="image_too_many_chunks")
        yield marker, length, data[pos + 4:pos + 2 + length]
        pos += 2 + length
        if marker == _SOS:  # past the scan's entropy-coded data
            end = _SCAN_END.search(data, pos)
            pos = end.start() if end else len(data)


def missing_coefficients(data: bytes, field: str) -> str | None:
    """What the scans of a sequential or progressive JPEG leave unsent, in words; None when every coefficient
    (64 per component) is sent to its last bit, or the file is one this walk does not follow (the decoder judges).

    Reads the frame and scan headers of :func:`jpeg_segments` (through the scans). A sequential scan covers all 64
    coefficients of its components; a progressive one the band Ss..Se, and to the last bit only when its Al (the
    bit it stops at) is 0.
    """
    components: list[int] = []  # the frame's component ids, in frame order
    sof = None
    scans: list[tuple[list[int], int, int, int]] = []  # (component ids, Ss, Se, Al)
    for marker, _, body in jpeg_segments(data, field, scans=True):
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC) and len(body) >= 6:  # a frame header
            sof = marker
            components = [body[6 + 3 * i] for i in range(body[5]) if 6 + 3 * i < len(body)]
        elif marker == _SOS and body and len(body) >= 4 + 2 * body[0]:
            ns = body[0]
            ss, se, approx = body[1 + 2 * ns], body[2 + 2 * ns], body[3 + 2 * ns]
            scans.append(([body[1 + 2 * i] for i in range(ns)], ss, se, approx & 0x0F))
    if sof not in _SEQUENTIAL_SOF | _PROGRESSIVE_SOF or not components:
        return None
    sent = np.zeros((len(components), 64), bool)  # [component, coefficient in zig-zag order]
    for ids, ss, se, al in scans:
        rows = [components.index(c) for c in ids if c in components]
        if sof in _SEQUENTIAL_SOF:
            sent[rows] = True
        elif al == 0 and ss <= se < 64:
            sent[rows, ss:se + 1] = True
    if sent.all():
        return None
    missing = int(np.count_nonzero(~sent))
    return (f"its scans stop before {missing} of the {sent.size} DCT coefficients of its {len(components)} colour "
            "components are sent in full")


def libjpeg_warning(data: bytes) -> str | None:
    """libjpeg's first warning on decoding ``data`` (at 1/8 scale, grey: every block is still entropy-decoded),
    or None when it has none or only junk before the end-of-image marker. A file libjpeg-turbo cannot decode
    at all (a fatal error) is None too: the full decode reports it."""
    try:
        simplejpeg.decode_jpeg(data, colorspace="GRAY", min_height=1, min_width=1, strict=True)
        return None
    except ValueError as exc:
        message = str(exc)
    if _HARMLESS_WARNING.search(message):
        return None
    try:  # a warning lets the decode finish when warnings are allowed; a fatal error does not
        simplejpeg.decode_jpeg(data, colorspace="GRAY", min_height=1, min_width=1, strict=False)
    except ValueError:
        return None
    return f"its decoder reports: {message}"


def check_jpeg_data(data: bytes, field: str) -> None:
    """400 when a JPEG's image data is truncated or corrupt in a way libjpeg would paper over (module doc); 413
    past the walk's limits (:func:`jpeg_segments`)."""
    problem = missing_coefficients(data, field) or libjpeg_warning(data)
    if problem is not None:
        raise InvalidImage(f"{field}: the JPEG data is truncated or corrupt ({problem}); send the whole file")
