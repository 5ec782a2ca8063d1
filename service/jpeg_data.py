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

import numpy as np
import simplejpeg

from .errors import InvalidImage, PayloadTooLarge

#: start-of-frame markers whose scans each send all 64 coefficients of their components (baseline, extended,
#: arithmetic sequential), and those whose scans send bands of coefficients and bits (progressive, Huffman and
#: arithmetic); other frames (lossless, hierarchical) are left to the decoder
_SEQUENTIAL_SOF = frozenset((0xC0, 0xC1, 0xC9))
_PROGRESSIVE_SOF = frozenset((0xC2, 0xCA))
_SOS, _EOI = 0xDA, 0xD9
#: the one libjpeg warning that loses no pixel: junk bytes between the last scan and the end-of-image marker
_HARMLESS_WARNING = re.compile(r"extraneous bytes before marker 0xd9", re.IGNORECASE)


def _marker_positions(data: bytes) -> np.ndarray:
    """Sorted offsets of every 0xFF byte that starts a marker a scan can end at: followed by neither a stuffed
    0x00, a restart marker (0xD0..0xD7, inside a scan) nor another 0xFF (fill, counted at its last byte)."""
    buf = np.frombuffer(data, np.uint8)
    ff = np.flatnonzero(buf[:-1] == 0xFF)
    nxt = buf[ff + 1]
    return ff[(nxt != 0x00) & (nxt != 0xFF) & ((nxt < 0xD0) | (nxt > 0xD7))]


def _next_marker(markers: np.ndarray, start: int) -> int:
    """Offset of the first marker (:func:`_marker_positions`) at or after ``start``; past the end when none is."""
    i = int(np.searchsorted(markers, start))
    return int(markers[i]) if i < len(markers) else 1 << 62


def missing_coefficients(data: bytes, field: str, max_segments: int) -> str | None:
    """What the scans of a sequential or progressive JPEG leave unsent, in words; None when every coefficient
    (64 per component) is sent to its last bit, or the file is one this walk does not follow (the decoder judges).

    Walks the markers from the start-of-image to the first end-of-image marker (a camera's MPF preview after it
    is another image), skipping each segment by its length and each scan's entropy-coded data to the next marker;
    413 past ``max_segments`` segments (a loop in Python per segment). A sequential scan covers all 64
    coefficients of its components; a progressive one the band Ss..Se, and to the last bit only when its Al
    (the bit it stops at) is 0.
    """
    if not data.startswith(b"\xff\xd8"):
        return None
    markers = _marker_positions(data)
    components: list[int] = []  # the frame's component ids, in frame order
    sof = None
    scans: list[tuple[list[int], int, int, int]] = []  # (component ids, Ss, Se, Al)
    pos, segments = 2, 0
    while pos + 4 <= len(data):
        segments += 1
        if segments > max_segments:
            raise PayloadTooLarge(f"{field}: the JPEG holds more than {max_segments} segments", code="image_too_many_chunks")
        marker = data[pos + 1]
        if data[pos] != 0xFF or marker in (0x00, 0xFF):  # junk or fill: on to the next marker, as libjpeg reads
            pos = _next_marker(markers, pos + 1)
            continue
        if marker == _EOI:
            break
        if marker == 0x01 or 0xD0 <= marker <= 0xD7:  # markers without a length
            pos += 2
            continue
        length = (data[pos + 2] << 8) | data[pos + 3]
        body = data[pos + 4:pos + 2 + length]
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC) and len(body) >= 6:  # a frame header
            sof = marker
            components = [body[6 + 3 * i] for i in range(body[5]) if 6 + 3 * i < len(body)]
        elif marker == _SOS and body and len(body) >= 4 + 2 * body[0]:
            ns = body[0]
            ss, se, approx = body[1 + 2 * ns], body[2 + 2 * ns], body[3 + 2 * ns]
            scans.append(([body[1 + 2 * i] for i in range(ns)], ss, se, approx & 0x0F))
        pos = pos + 2 + length if marker != _SOS else _next_marker(markers, pos + 2 + length)  # past the scan's data
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


def check_jpeg_data(data: bytes, field: str, max_segments: int) -> None:
    """400 when a JPEG's image data is truncated or corrupt in a way libjpeg would paper over (module doc); 413
    past ``max_segments`` marker segments."""
    problem = missing_coefficients(data, field, max_segments) or libjpeg_warning(data)
    if problem is not None:
        raise InvalidImage(f"{field}: the JPEG data is truncated or corrupt ({problem}); send the whole file")
