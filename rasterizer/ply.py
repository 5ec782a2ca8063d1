"""Gaussian PLY files in the INRIA 3DGS layout (conventions section 5).

Layout: ``binary_little_endian``, ``\\n`` line endings, one ``vertex`` element
with float32 properties ``x y z nx ny nz f_dc_0..2 [f_rest_*] opacity
scale_0..2 rot_0..3``. Stored pre-activation: ``opacity = logit(alpha)``,
``scale_i = log(sigma_i)``, ``rot = (w, x, y, z)``; ``f_rest`` is
channel-major (all R coefficients, then G, then B). Normals are written as 0.

Writing builds one contiguous (N, F) float32 array and calls ``tobytes`` (no
Python object per value); :func:`ply_stream` makes the same bytes a block of
rows at a time. Rows with NaN/Inf in any field are dropped (or
refused with ``drop_invalid=False``); opacity is clamped to
[1e-12, 1 - 1e-12] before the logit and scales to >= 1e-30 before the log,
so 0, 1 and rank-deficient Gaussians stay finite on disk.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from .gaussians import Gaussians, GaussiansError

_OPACITY_EPS = 1e-12
_MIN_SCALE = 1e-30

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


class PlyError(ValueError):
    """A PLY file that is not a readable Gaussian PLY."""


def property_names(sh_coeffs: int) -> list[str]:
    """Vertex property names, in file order, for ``sh_coeffs`` SH coefficients per channel."""
    rest = [f"f_rest_{i}" for i in range(3 * (sh_coeffs - 1))]
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + rest
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def finite_rows(g: Gaussians) -> np.ndarray:
    """(N,) bool: rows whose every field is finite."""
    if all(np.isfinite(getattr(g, f)).all() for f in ("means", "scales", "quats", "opacities", "sh")):
        return np.ones(len(g), dtype=bool)  # the usual case: one flat pass per field, no per-row reductions
    ok = np.isfinite(g.means).all(1) & np.isfinite(g.scales).all(1) & np.isfinite(g.quats).all(1)
    ok &= np.isfinite(g.opacities) & np.isfinite(g.sh).all(axis=(1, 2))
    return ok


def _valid(g: Gaussians, drop_invalid: bool) -> Gaussians:
    """``g`` without rows holding NaN/Inf (or GaussiansError when ``drop_invalid`` is False)."""
    ok = finite_rows(g)
    if ok.all():
        return g
    if not drop_invalid:
        raise GaussiansError(f"{int((~ok).sum())} Gaussian rows contain NaN or Inf")
    return g.subset(ok)


def _table(g: Gaussians, start: int = 0, stop: int | None = None) -> np.ndarray:
    """The (rows, F) float32 property table of ``g[start:stop]`` (rows already finite)."""
    stop = len(g) if stop is None else min(stop, len(g))
    n, k = max(0, stop - start), g.sh.shape[1]
    rows = slice(start, start + n)
    table = np.zeros((n, 17 + 3 * (k - 1)), dtype=np.float32)
    table[:, 0:3] = g.means[rows]
    table[:, 6:9] = g.sh[rows, 0, :]
    col = 9
    if k > 1:
        # (n, K-1, 3) -> channel-major (n, 3, K-1) -> (n, 3(K-1))
        table[:, col:col + 3 * (k - 1)] = np.transpose(g.sh[rows, 1:, :], (0, 2, 1)).reshape(n, 3 * (k - 1))
        col += 3 * (k - 1)
    a = np.clip(g.opacities[rows].astype(np.float64), _OPACITY_EPS, 1.0 - _OPACITY_EPS)
    table[:, col] = np.log(a) - np.log1p(-a)
    table[:, col + 1:col + 4] = np.log(np.maximum(g.scales[rows].astype(np.float64), _MIN_SCALE))
    table[:, col + 4:col + 8] = g.quats[rows]
    return table


def ply_header(count: int, sh_coeffs: int) -> bytes:
    """The header of a PLY of ``count`` Gaussians with ``sh_coeffs`` SH coefficients per channel."""
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {count}"]
    header += [f"property float {name}" for name in property_names(sh_coeffs)]
    header += ["end_header"]
    return ("\n".join(header) + "\n").encode("ascii")


#: Gaussians per chunk of :func:`ply_stream` (about 7 MB of float32 rows at SH degree 1)
PLY_CHUNK_ROWS = 1 << 16


def ply_stream(g: Gaussians, *, drop_invalid: bool = True, rows: int = PLY_CHUNK_ROWS) -> tuple[int, Iterator[bytes]]:
    """(size in bytes, chunks) of the PLY of ``g``, made ``rows`` Gaussians at a time: the same bytes as
    :func:`ply_bytes`, never more than one chunk's table in memory."""
    g = _valid(g, drop_invalid)
    header = ply_header(len(g), g.sh.shape[1])
    size = len(header) + len(g) * 4 * len(property_names(g.sh.shape[1]))

    def chunks() -> Iterator[bytes]:
        yield header
        for start in range(0, len(g), max(1, int(rows))):
            yield _table(g, start, start + rows).astype("<f4", copy=False).tobytes()

    return size, chunks()


def ply_bytes(g: Gaussians, *, drop_invalid: bool = True) -> bytes:
    """The binary PLY file of ``g`` as bytes (see the module docstring)."""
    g = _valid(g, drop_invalid)
    return ply_header(len(g), g.sh.shape[1]) + _table(g).astype("<f4", copy=False).tobytes()


def write_ply(path: str | os.PathLike, g: Gaussians, *, drop_invalid: bool = True) -> Path:
    """Write ``g`` to ``path`` atomically (:func:`write_whole`); returns the path written."""
    return write_whole(path, ply_bytes(g, drop_invalid=drop_invalid))


def write_whole(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a hidden temporary file beside it, renamed over it when complete, so that a
    write that fails (a full disk, a file size limit, Ctrl-C, ``path`` a folder) leaves neither a truncated file nor
    a damaged older one; returns the path written. A symbolic link is written through (its target replaced), as a
    plain write would, not replaced by a file."""
    path = Path(path)
    if path.is_symlink():
        path = path.resolve()
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:12]}.tmp")
    try:
        tmp.write_bytes(data)
        os.replace(tmp, path)
    except BaseException:  # no half-written temp file is left beside it
        tmp.unlink(missing_ok=True)
        raise
    return path


def _parse_header(data: bytes) -> tuple[int, np.dtype, int]:
    """(vertex count, structured dtype of a vertex, byte offset of the body).

    Every malformed header (a line without its fields, a count that is no non-negative integer, a property
    named twice, an unsupported format or type) is a :class:`PlyError` naming the line."""
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise PlyError("not a PLY file (missing 'ply' magic or 'end_header')")
    newline = data.find(b"\n", end)
    body = len(data) if newline < 0 else newline + 1  # a header that ends the file holds no vertex
    lines = data[:end].decode("ascii", errors="replace").replace("\r", "").split("\n")
    count, fields, element, fmt = None, [], None, None
    for line in lines[1:]:
        parts = line.split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] in _HEADER_LINES and len(parts) < len(_HEADER_LINES[parts[0]].split()):
            raise PlyError(f"malformed PLY header line {line.strip()!r}: expected {_HEADER_LINES[parts[0]]!r}")
        if parts[0] == "format":
            fmt = parts[1]
        elif parts[0] == "element":
            element = parts[1]
            if element == "vertex":
                count = _vertex_count(parts[2])
            elif count is not None:
                break  # elements after vertex do not change the vertex layout
            else:
                raise PlyError(f"element {element!r} before 'vertex' is not supported")
        elif parts[0] == "property" and element == "vertex":
            if parts[1] == "list":
                raise PlyError("list properties in 'vertex' are not supported")
            if parts[1] not in _PLY_TYPES:
                raise PlyError(f"unknown property type {parts[1]!r}")
            if any(name == parts[2] for name, _ in fields):
                raise PlyError(f"PLY vertex property {parts[2]!r} is declared twice")
            fields.append((parts[2], "<" + _PLY_TYPES[parts[1]]))
    if fmt != "binary_little_endian":
        raise PlyError(f"only binary_little_endian PLY is supported, got {fmt!r}")
    if count is None:
        raise PlyError("PLY has no 'vertex' element")
    return count, np.dtype(fields), body


#: The form of each header line with fields: how many a line needs, and what a malformed one is told.
_HEADER_LINES = {"format": "format binary_little_endian 1.0", "element": "element NAME COUNT",
                 "property": "property TYPE NAME"}


def _vertex_count(text: str) -> int:
    """The vertex count of an ``element vertex`` line: a non-negative integer, else :class:`PlyError`."""
    if not (text.isascii() and text.isdigit()):  # ASCII digits only: no sign, no decimal point
        raise PlyError(f"PLY vertex count must be a non-negative integer, got {text!r}")
    return int(text)


def read_ply(source: str | os.PathLike | bytes | bytearray | memoryview) -> Gaussians:
    """Read a Gaussian PLY (path or bytes) into activated :class:`Gaussians`.

    Accepts any float/int property types and extra properties; requires
    x y z, f_dc_0..2, opacity, scale_0..2, rot_0..3. Missing f_rest means
    SH degree 0.
    """
    data = bytes(source) if isinstance(source, (bytes, bytearray, memoryview)) else Path(source).read_bytes()
    count, dtype, body = _parse_header(data)
    if len(data) - body < count * dtype.itemsize:
        raise PlyError(f"PLY body too short: {count} vertices need {count * dtype.itemsize} bytes")
    v = np.frombuffer(data, dtype=dtype, count=count, offset=body)
    names = set(dtype.names or ())
    required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
                "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    missing = [n for n in required if n not in names]
    if missing:
        raise PlyError(f"PLY lacks Gaussian properties {missing}")

    def cols(keys):
        return np.stack([v[k].astype(np.float64) for k in keys], axis=1) if keys else np.zeros((count, 0))

    n_rest = sum(1 for n in names if n.startswith("f_rest_"))
    k = 1 + n_rest // 3
    if n_rest % 3 or k not in (1, 4, 9, 16):
        raise PlyError(f"PLY has {n_rest} f_rest properties; expected 0, 9, 24 or 45")
    gaps = [f"f_rest_{i}" for i in range(n_rest) if f"f_rest_{i}" not in names]
    if gaps:
        raise PlyError(f"PLY's {n_rest} f_rest properties are not f_rest_0..{n_rest - 1}: it lacks {gaps[:5]}")
    sh = np.empty((count, k, 3), dtype=np.float32)
    sh[:, 0, :] = cols(["f_dc_0", "f_dc_1", "f_dc_2"])
    if k > 1:
        rest = cols([f"f_rest_{i}" for i in range(n_rest)])
        sh[:, 1:, :] = rest.reshape(count, 3, k - 1).transpose(0, 2, 1)
    logit = v["opacity"].astype(np.float64)
    opacity = 0.5 * (1.0 + np.tanh(0.5 * logit))  # overflow-free sigmoid
    return Gaussians(
        means=cols(["x", "y", "z"]),
        scales=np.exp(cols(["scale_0", "scale_1", "scale_2"])),
        quats=cols(["rot_0", "rot_1", "rot_2", "rot_3"]),
        opacities=opacity,
        sh=sh,
    )
