"""Gaussians as SPZ, Niantic's compressed splat format (version 2), about a fifth of the PLY's bytes.

A scene's PLY holds 26 float32 per Gaussian (104 bytes); SPZ holds 28 bytes, gzip-compressed:

============  ======================  ==========================================================
array         bytes per Gaussian      encoding (decoded as every SPZ reader decodes it)
============  ======================  ==========================================================
positions     3 x 3                   24-bit signed fixed point, ``fractional_bits`` per header
alphas        1                       round(255 opacity)
colours       3                       round(255 (0.15 f_dc + 0.5)), f_dc the SH DC coefficient
scales        3                       round(16 (ln sigma + 10)): steps of 6.4% from 4.5e-5 to 380
rotations     3                       (x, y, z) of the unit quaternion with w >= 1/2, round(127.5 (v + 1))
sh            3 per coefficient       degree-1 coefficients, round(128 v + 128), coefficient-major
============  ======================  ==========================================================

after a 16-byte header (magic ``NGSP``, version, count, SH degree, fractional bits, flags, reserved).
SPZ's world is RUB (x right, y up, z back, as OpenGL and three.js); this project's is OpenCV's RDF
(``docs/conventions.md`` section 1), so positions and rotations are turned by diag(1, -1, -1) and the
degree-1 SH coefficients of y and z change sign. Values beyond an array's range are clamped (a scale
under 4.5e-5 scene units, an SH coefficient beyond +-1, a DC colour beyond +-3.3); the fixed point's
fractional bits are the most that hold the scene's largest coordinate. A scene far from the origin
(georeferenced poses) gets a coarse step: a file whose step exceeds :data:`MAX_STEP_PER_SIZE` of the
Gaussians' median size (middle scale) is refused (:func:`check_position_step`), as readers would show its
splats moved; the PLY's float32 positions round its farthest coordinates half as coarsely, nearer ones finer.
"""

from __future__ import annotations

import gzip
import struct
import zlib

import numpy as np

from .gaussians import MAX_STEP_PER_SIZE, Gaussians, GaussiansError, quat_to_rotmat, step_share, typical_size
from .ply import finite_rows

#: "NGSP" read as a little-endian uint32.
SPZ_MAGIC = 0x5053474E
SPZ_VERSION = 2
_HEADER = struct.Struct("<IIIBBBB")
_COLOUR_SCALE = 0.15
_POSITION_LIMIT = (1 << 23) - 1  # the largest magnitude of a 24-bit signed integer
#: Most fractional bits a file gets (readers compute 1 << bits in 32-bit integers).
MAX_FRACTIONAL_BITS = 24
#: gzip level: level 6 makes a file 3% smaller than level 1 for 1.6 times the compression time.
GZIP_LEVEL = 1
#: The RDF -> RUB turn diag(1, -1, -1), applied to positions and to a quaternion's (x, y, z).
_FLIP = np.array([1.0, -1.0, -1.0])
#: Sign of each degree-1 SH coefficient under that turn (basis order y, z, x of the INRIA layout).
_SH1_FLIP = np.array([-1.0, -1.0, 1.0])


#: The 12 turns that map the coordinate axes onto each other (the tetrahedral group) as unit quaternions
#: (w, x, y, z): a Gaussian turned by one, its scales permuted to match, is the same Gaussian.
_AXIS_TURNS = np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
                       + [[0.5, x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])
#: For each turn, the old axis each new axis is: column j of R g is +-column _TURN_AXES[., j] of R.
_TURN_AXES = np.argmax(np.abs(quat_to_rotmat(_AXIS_TURNS)), axis=1)


class SpzError(ValueError):
    """Gaussians SPZ cannot hold (too large a coordinate, too coarse a position step for the Gaussians' size,
    an SH degree above 1), or bytes that are not SPZ."""


def fractional_bits(means: np.ndarray) -> int:
    """The most fractional bits (at most :data:`MAX_FRACTIONAL_BITS`) whose 24-bit fixed point holds every
    coordinate of (N, 3) ``means``; raises :class:`SpzError` when not even 0 bits do."""
    largest = float(np.abs(means).max()) if means.size else 0.0
    if largest > _POSITION_LIMIT:
        raise SpzError(f"a Gaussian lies {largest:.4g} scene units from the origin; SPZ's 24-bit positions "
                       f"hold at most {_POSITION_LIMIT}: use the PLY, or send poses nearer the origin")
    if largest == 0.0:
        return MAX_FRACTIONAL_BITS
    return int(min(MAX_FRACTIONAL_BITS, np.floor(np.log2(_POSITION_LIMIT / largest))))


def check_position_step(bits: int, means: np.ndarray, scales: np.ndarray) -> None:
    """Raise :class:`SpzError` when the position step of ``bits`` fractional bits, 2^-bits scene units, exceeds
    :data:`~rasterizer.gaussians.MAX_STEP_PER_SIZE` of the :func:`~rasterizer.gaussians.typical_size` of (N, 3)
    ``scales``; (N, 3) ``means`` are the scene's, for the message."""
    if not len(scales):
        return
    size = typical_size(scales)
    step = 2.0 ** -bits
    if step > MAX_STEP_PER_SIZE * size:
        largest = float(np.abs(means).max())
        raise SpzError(f"SPZ's 24-bit positions would round this scene's Gaussians (reaching {largest:.4g} scene "
                       f"units from the origin) to steps of {step:.3g}, {step_share(step, size)} their median size "
                       f"{size:.3g} (at most {MAX_STEP_PER_SIZE:g} keeps the splats in place): use the PLY, or send "
                       "poses nearer the origin")


def _largest_w(q: np.ndarray, scales: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each Gaussian's unit quaternion (N, 4) and scales (N, 3) re-expressed, among the 12 equal forms of
    :data:`_AXIS_TURNS`, with the largest |w| (at least 1/2).

    SPZ stores only x, y, z and readers take w = sqrt(1 - |xyz|^2): near w = 0 a byte's rounding moves w,
    and the rotation, by several degrees; from |w| >= 1/2 on, by at most about a degree."""
    conj = _AXIS_TURNS * np.array([1.0, -1.0, -1.0, -1.0])
    best = np.argmax(np.abs(q @ conj.T), axis=1)  # w of q g = q . conj(g)
    g = _AXIS_TURNS[best]
    w1, x1, y1, z1 = q.T
    w2, x2, y2, z2 = g.T
    turned = np.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                       w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], axis=1)
    return turned, np.take_along_axis(scales, _TURN_AXES[best], axis=1)


def _bytes_u8(values: np.ndarray) -> np.ndarray:
    """Round half up and clamp to uint8 (NaN never reaches here: rows are finite)."""
    return np.clip(np.floor(values + 0.5), 0, 255).astype(np.uint8)


#: Gaussians quantised at a time: the float temporaries stay at tens of MB whatever the scene's size.
SPZ_CHUNK_ROWS = 1 << 16


def _quantised_rows(g: Gaussians, bits: int) -> list[np.ndarray]:
    """The SPZ arrays of all of ``g``'s rows (finite), each (n, k) uint8 in file order: positions, alphas,
    colours, scales, rotations, then the degree-1 SH if ``g`` has them."""
    means = g.means.astype(np.float64) * _FLIP
    fixed = np.floor(means * float(1 << bits) + 0.5).astype(np.int64)
    positions = ((fixed[:, :, None] >> np.array([0, 8, 16])) & 0xFF).astype(np.uint8)  # little-endian, two's complement
    alphas = _bytes_u8(255.0 * g.opacities.astype(np.float64))[:, None]
    colours = _bytes_u8(255.0 * (_COLOUR_SCALE * g.sh[:, 0, :].astype(np.float64) + 0.5))
    q = g.quats.astype(np.float64)  # (w, x, y, z)
    q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-30)
    q, sigma = _largest_w(q, g.scales.astype(np.float64))
    scales = _bytes_u8(16.0 * (np.log(np.maximum(sigma, 1e-30)) + 10.0))
    xyz = q[:, 1:] * _FLIP * np.where(q[:, :1] < 0, -1.0, 1.0)  # -q is q: readers take w >= 0
    rotations = _bytes_u8(127.5 * (xyz + 1.0))
    parts = [positions.reshape(len(g), 9), alphas, colours, scales, rotations]
    if g.sh.shape[1] == 4:
        sh = g.sh[:, 1:, :].astype(np.float64) * _SH1_FLIP[None, :, None]  # (n, 3 coefficients, 3 channels)
        parts.append(_bytes_u8(128.0 * sh + 128.0).reshape(len(g), 9))
    return parts


def spz_bytes(g: Gaussians, *, rows: int = SPZ_CHUNK_ROWS) -> bytes:
    """The SPZ file of ``g`` (rows with NaN/Inf dropped, as in the PLY). SH degree 0 or 1.

    Quantised ``rows`` Gaussians at a time into the file's arrays (28 bytes a Gaussian at degree 1), which
    SPZ lays out whole, one after another; then gzip."""
    if g.sh.shape[1] not in (1, 4):
        raise SpzError(f"SPZ here holds SH degree 0 or 1, not {g.sh_degree}")
    ok = finite_rows(g)
    g = g if ok.all() else g.subset(ok)
    n, sh_degree = len(g), 1 if g.sh.shape[1] == 4 else 0
    bits = fractional_bits(g.means)  # the turn to RUB changes no coordinate's magnitude
    check_position_step(bits, g.means, g.scales)
    widths = [9, 1, 3, 3, 3] + [9] * sh_degree
    arrays = [np.empty((n, k), dtype=np.uint8) for k in widths]
    for start in range(0, n, max(1, int(rows))):
        part = g.subset(slice(start, start + rows))
        for array, values in zip(arrays, _quantised_rows(part, bits)):
            array[start:start + len(part)] = values
    gz = zlib.compressobj(GZIP_LEVEL, zlib.DEFLATED, 31)  # 31: a gzip stream (header mtime 0)
    out = [gz.compress(_HEADER.pack(SPZ_MAGIC, SPZ_VERSION, n, sh_degree, bits, 0, 0))]
    out += [gz.compress(array) for array in arrays]
    return b"".join(out + [gz.flush()])


def read_spz(data: bytes | bytearray | memoryview) -> Gaussians:
    """Gaussians of an SPZ file (version 2, SH degree 0 or 1) in this project's RDF world, decoded as
    readers decode it (the inverse of :func:`spz_bytes` up to its quantisation)."""
    try:
        raw = gzip.decompress(bytes(data))
    except (OSError, EOFError) as exc:
        raise SpzError(f"not a gzip stream: {exc}") from None
    if len(raw) < _HEADER.size:
        raise SpzError("SPZ header truncated")
    magic, version, n, sh_degree, bits, _, _ = _HEADER.unpack_from(raw)
    if magic != SPZ_MAGIC or version != SPZ_VERSION:
        raise SpzError(f"not an SPZ version {SPZ_VERSION} file (magic {magic:#x}, version {version})")
    if sh_degree not in (0, 1):
        raise SpzError(f"SH degree {sh_degree}: this reader takes 0 or 1")
    sizes = [9 * n, n, 3 * n, 3 * n, 3 * n, 9 * n * sh_degree]
    if len(raw) != _HEADER.size + sum(sizes):
        raise SpzError(f"SPZ body holds {len(raw) - _HEADER.size} bytes, {n} Gaussians need {sum(sizes)}")
    arrays, at = [], _HEADER.size
    for size in sizes:
        arrays.append(np.frombuffer(raw, np.uint8, size, at).astype(np.float64))
        at += size
    pos, alpha, colour, scale, rot, sh1 = arrays
    b = pos.reshape(n, 3, 3)
    fixed = b[:, :, 0] + 256.0 * b[:, :, 1] + 65536.0 * b[:, :, 2]
    fixed = np.where(fixed >= 1 << 23, fixed - (1 << 24), fixed)
    xyz = rot.reshape(n, 3) / 127.5 - 1.0
    w = np.sqrt(np.maximum(0.0, 1.0 - np.sum(xyz * xyz, axis=1)))
    sh = np.empty((n, 1 + 3 * sh_degree, 3), dtype=np.float32)
    sh[:, 0, :] = (colour.reshape(n, 3) / 255.0 - 0.5) / _COLOUR_SCALE
    if sh_degree:
        sh[:, 1:, :] = (sh1.reshape(n, 3, 3) - 128.0) / 128.0 * _SH1_FLIP[None, :, None]
    try:
        return Gaussians(means=fixed / float(1 << bits) * _FLIP, scales=np.exp(scale.reshape(n, 3) / 16.0 - 10.0),
                         quats=np.concatenate([w[:, None], xyz * _FLIP], axis=1), opacities=alpha / 255.0, sh=sh)
    except GaussiansError as exc:
        raise SpzError(str(exc)) from None
