"""Gaussian PLY: INRIA layout, read back with plyfile, round trip, invalid rows."""

import io
import re

import numpy as np
import pytest
from plyfile import PlyData

from rasterizer.gaussians import Gaussians, GaussiansError
from rasterizer.ply import PlyError, ply_bytes, property_names, read_ply, write_ply
from rasterizer.render import render


def scene(rng, n=300, k=16):
    d = rng.normal(size=(n, 3))
    means = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(1, 3, (n, 1))
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return Gaussians(means, rng.uniform(0.02, 0.2, (n, 3)), q, rng.uniform(0, 1, n),
                     rng.normal(size=(n, k, 3)) * 0.3)


def test_header_layout_is_the_inria_one():
    data = ply_bytes(scene(np.random.default_rng(0), 5, 16))
    head = data[: data.index(b"end_header\n") + len(b"end_header\n")].decode("ascii")
    assert "\r" not in head
    lines = head.split("\n")
    assert lines[:3] == ["ply", "format binary_little_endian 1.0", "element vertex 5"]
    props = [ln.split() for ln in lines if ln.startswith("property")]
    assert all(p[1] == "float" for p in props)
    names = [p[2] for p in props]
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert names[9:54] == [f"f_rest_{i}" for i in range(45)]
    assert names[54:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert names == property_names(16)
    assert len(data) == len(head) + 5 * 62 * 4


@pytest.mark.parametrize("k", [1, 4, 16])
def test_plyfile_reads_our_values(k):
    g = scene(np.random.default_rng(k), 50, k)
    v = PlyData.read(io.BytesIO(ply_bytes(g)))["vertex"]
    assert v.count == 50
    assert np.allclose(np.stack([v["x"], v["y"], v["z"]], 1), g.means)
    assert np.allclose(1 / (1 + np.exp(-v["opacity"])), g.opacities, atol=1e-6)
    assert np.allclose(np.exp(np.stack([v[f"scale_{i}"] for i in range(3)], 1)), g.scales, rtol=1e-6)
    assert np.allclose(np.stack([v[f"rot_{i}"] for i in range(4)], 1), g.quats)
    assert np.allclose(np.stack([v[f"f_dc_{i}"] for i in range(3)], 1), g.sh[:, 0])
    if k > 1:  # channel-major: all R coefficients, then G, then B
        assert np.allclose(v["f_rest_0"], g.sh[:, 1, 0])
        assert np.allclose(v[f"f_rest_{k - 1}"], g.sh[:, 1, 1])
        assert np.allclose(v[f"f_rest_{3 * (k - 1) - 1}"], g.sh[:, k - 1, 2])


def test_round_trip_file_and_bytes_rerenders_identically(tmp_path):
    g = scene(np.random.default_rng(3), 400, 4)
    path = write_ply(tmp_path / "s.ply", g)
    for back in (read_ply(path), read_ply(path.read_bytes())):
        assert len(back) == len(g) and back.sh.shape == g.sh.shape
        assert np.allclose(back.means, g.means) and np.allclose(back.sh, g.sh)
        assert np.allclose(back.scales, g.scales, rtol=1e-6)
        assert np.allclose(back.opacities, g.opacities, atol=1e-6)
        a = render(g, np.eye(4), projection="erp", width=128, method="direct")
        b = render(back, np.eye(4), projection="erp", width=128, method="direct")
        assert a.alpha.max() > 0.5
        assert np.allclose(a.colour, b.colour, atol=1e-4) and np.allclose(a.alpha, b.alpha, atol=1e-4)


def test_extreme_values_stay_finite_and_invalid_rows_are_dropped():
    g = scene(np.random.default_rng(4), 6, 1)
    op = g.opacities.copy()
    op[:2] = [0.0, 1.0]
    sc = g.scales.copy()
    sc[2] = 0.0  # rank-deficient
    means = g.means.copy()
    means[5, 1] = np.nan
    bad = Gaussians(means, sc, g.quats, op, g.sh)
    v = PlyData.read(io.BytesIO(ply_bytes(bad)))["vertex"]
    assert v.count == 5
    table = np.stack([v[n] for n in v.data.dtype.names], 1)
    assert np.all(np.isfinite(table))
    back = read_ply(ply_bytes(bad))
    assert back.opacities[0] < 1e-6 and back.opacities[1] > 1 - 1e-6
    assert np.all(back.scales[2] >= 0) and np.all(back.scales[2] < 1e-20)
    with pytest.raises(GaussiansError, match="NaN"):
        ply_bytes(bad, drop_invalid=False)


def test_reader_refuses_bad_files():
    with pytest.raises(PlyError):
        read_ply(b"not a ply")
    data = ply_bytes(scene(np.random.default_rng(5), 3, 1))
    with pytest.raises(PlyError, match="short"):
        read_ply(data[:-4])
    with pytest.raises(PlyError, match="binary_little_endian"):
        read_ply(data.replace(b"binary_little_endian", b"ascii", 1))


def test_empty_gaussians_round_trip():
    back = read_ply(ply_bytes(Gaussians.empty()))
    assert len(back) == 0


def test_a_failed_write_leaves_no_temp_file(tmp_path):
    (tmp_path / "out.ply").mkdir()  # the target is a folder: the rename fails
    with pytest.raises(OSError):
        write_ply(tmp_path / "out.ply", scene(np.random.default_rng(0), n=10))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.ply"]


def _edited(data: bytes, old: bytes, new: bytes) -> bytes:
    """``data`` with its header's first ``old`` replaced by ``new`` (the body untouched)."""
    end = data.index(b"end_header")
    return data[:end].replace(old, new, 1) + data[end:]


@pytest.mark.parametrize("old, new, says", [
    (b"element vertex 3", b"element vertex -1", "non-negative integer, got '-1'"),
    (b"element vertex 3", b"element vertex 3.0", "non-negative integer, got '3.0'"),
    (b"element vertex 3", b"element vertex three", "non-negative integer, got 'three'"),
    (b"element vertex 3", b"element vertex", "expected 'element NAME COUNT'"),
    (b"format binary_little_endian 1.0", b"format", "expected 'format binary_little_endian 1.0'"),
    (b"property float y\n", b"property float\n", "expected 'property TYPE NAME'"),
    (b"property float y\n", b"property float x\n", "'x' is declared twice"),
    (b"f_rest_8\n", b"f_rest_80\n", "lacks ['f_rest_8']"),
])
def test_a_malformed_header_is_a_ply_error_naming_its_line(old, new, says):
    """A header line without its fields, a negative or non-integer count, a property named twice or a gap in the
    f_rest numbering is a PlyError that says what is wrong (not an IndexError or a bare numpy error)."""
    data = _edited(ply_bytes(scene(np.random.default_rng(5), 3, 4)), old, new)
    with pytest.raises(PlyError, match=re.escape(says)):
        read_ply(data)


def test_a_header_that_ends_the_file_is_a_ply_without_vertices():
    data = ply_bytes(Gaussians.empty())
    assert data.endswith(b"end_header\n") and len(read_ply(data[:-1])) == 0
    with pytest.raises(PlyError, match="too short"):
        read_ply(ply_bytes(scene(np.random.default_rng(5), 1, 1)).split(b"end_header")[0] + b"end_header")
