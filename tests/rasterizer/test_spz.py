"""SPZ (version 2): the header and arrays as SPZ readers decode them, SPZ's RUB world, quantisation bounds,
renders of the decoded Gaussians against the originals, and refusals."""

import gzip
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rasterizer.gaussians import Gaussians
from rasterizer.render import render
from rasterizer.sh import sh_to_rgb
from rasterizer.spz import (
    MAX_FRACTIONAL_BITS,
    MAX_STEP_PER_SIZE,
    SPZ_MAGIC,
    SpzError,
    fractional_bits,
    read_spz,
    spz_bytes,
)


def scene(rng, n=300, k=4, radius=3.0):
    d = rng.normal(size=(n, 3))
    means = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(radius / 3, radius, (n, 1))
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return Gaussians(means, rng.uniform(0.02, 0.2, (n, 3)), q, rng.uniform(0, 1, n),
                     rng.uniform(-0.9, 0.9, (n, k, 3)))


def unpacked(data: bytes):
    """The header fields and the six arrays of an SPZ file, read with this test's own arithmetic."""
    raw = gzip.decompress(data)
    magic, version, n, degree, bits, flags, reserved = struct.unpack_from("<IIIBBBB", raw)
    at, arrays = 16, {}
    for name, size in (("positions", 9 * n), ("alphas", n), ("colours", 3 * n), ("scales", 3 * n),
                       ("rotations", 3 * n), ("sh", 9 * n * degree)):
        arrays[name] = np.frombuffer(raw, np.uint8, size, at)
        at += size
    assert at == len(raw)
    return (magic, version, n, degree, bits, flags, reserved), arrays


def test_header_and_one_gaussian_as_readers_decode_it():
    g = Gaussians(means=[[1.5, -2.25, 3.0]], scales=[[0.1, 0.01, 1.0]], quats=[[1.0, 0.0, 0.0, 0.0]],
                  opacities=[0.5], sh=np.array([[[0.4, -0.2, 0.0], [0.5, 0.0, 0.0], [0.0, 0.25, 0.0],
                                                 [0.0, 0.0, -0.75]]]))
    (magic, version, n, degree, bits, flags, reserved), a = unpacked(spz_bytes(g))
    assert (magic, version, n, degree, flags, reserved) == (SPZ_MAGIC, 2, 1, 1, 0, 0)
    assert magic.to_bytes(4, "little") == b"NGSP"
    assert bits == 21  # the most that keep 3.0 within 24 bits: 3 * 2^21 < 2^23 <= 3 * 2^22
    b = a["positions"].reshape(3, 3).astype(np.int64)
    fixed = b[:, 0] | (b[:, 1] << 8) | (b[:, 2] << 16)
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
    assert np.array_equal(fixed / 2.0**bits, [1.5, 2.25, -3.0])  # RUB: y and z turned
    assert a["alphas"][0] == 128  # round(127.5) half up
    assert np.array_equal(a["colours"], np.floor(255 * (0.15 * np.array([0.4, -0.2, 0.0]) + 0.5) + 0.5))
    assert np.allclose(np.exp(a["scales"] / 16.0 - 10.0), [0.1, 0.01, 1.0], rtol=0.032)
    assert np.array_equal(a["rotations"], [128, 128, 128])  # the identity: x = y = z = 0
    # degree-1 coefficients, coefficient-major; the y and z basis terms change sign in RUB, x does not
    sh = (a["sh"].reshape(3, 3).astype(np.float64) - 128) / 128
    assert np.allclose(sh, [[-0.5, 0.0, 0.0], [0.0, -0.25, 0.0], [0.0, 0.0, -0.75]], atol=1 / 256)


def test_rub_world_shows_the_same_colours_from_the_turned_directions():
    """SPZ's RUB coefficients, evaluated from the camera turned into RUB, give the RDF colours."""
    rng = np.random.default_rng(4)
    g = scene(rng, 200)
    (_, _, n, _, bits, _, _), a = unpacked(spz_bytes(g))
    b = a["positions"].reshape(n, 3, 3).astype(np.int64)
    fixed = b[:, :, 0] | (b[:, :, 1] << 8) | (b[:, :, 2] << 16)
    rub_means = np.where(fixed & 0x800000, fixed - (1 << 24), fixed) / 2.0**bits
    assert np.allclose(rub_means, g.means * [1, -1, -1], atol=2.0**-bits)
    rub_sh = g.sh.copy()
    rub_sh[:, 0] = (a["colours"].reshape(n, 3) / 255 - 0.5) / 0.15
    rub_sh[:, 1:] = (a["sh"].reshape(n, 3, 3) - 128.0) / 128.0
    eye = np.array([0.3, -1.2, 0.7])
    rdf = sh_to_rgb(g.sh, g.means, eye)
    rub = sh_to_rgb(rub_sh, rub_means, eye * [1, -1, -1])
    assert np.abs(rdf - rub).max() < 0.012  # the 8-bit steps of DC (1.9/255) and band 1


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), radius=st.sampled_from([1e-3, 0.5, 3.0, 250.0, 5e5]),
       degree=st.sampled_from([0, 1]))
def test_round_trip_within_the_quantisation(seed, radius, degree):
    rng = np.random.default_rng(seed)
    g = scene(rng, 64, 1 + 3 * degree, radius)
    g = g.with_(scales=g.scales * radius)  # footprints that follow the scene's size
    back = read_spz(spz_bytes(g))
    assert len(back) == len(g) and back.sh.shape == g.sh.shape
    bits = fractional_bits(g.means * [1, -1, -1])
    assert np.abs(back.means - g.means).max() <= 0.5 * 2.0**-bits * (1 + 1e-9)
    assert np.abs(back.opacities - g.opacities).max() <= 0.5 / 255 + 1e-6
    # the scales as a set: a Gaussian's axes may come back permuted with its rotation (rasterizer.spz._largest_w)
    sigma, sigma_back = np.sort(g.scales, axis=1), np.sort(back.scales, axis=1)
    inside = (sigma > np.exp(-10)) & (sigma < np.exp(255 / 16 - 10))
    ratio = sigma_back[inside] / sigma[inside]
    assert np.all(np.abs(np.log(ratio)) <= 1 / 32 + 1e-6)
    assert np.abs(back.sh[:, 0] - g.sh[:, 0]).max() <= 0.5 / (255 * 0.15) + 1e-6
    if degree:
        assert np.abs(back.sh[:, 1:] - g.sh[:, 1:]).max() <= 0.5 / 128 + 1e-6
    # the same Gaussian: covariances within the rotation's and the scales' steps (about a degree, 3%)
    whole = inside.all(axis=1)
    cov, cov_back = g.covariances()[whole], back.covariances()[whole]
    size = np.linalg.norm(cov, axis=(1, 2))
    assert np.all(np.linalg.norm(cov_back - cov, axis=(1, 2)) <= 0.12 * size)


def test_chunks_give_the_same_file():
    g = scene(np.random.default_rng(2), 100)
    assert spz_bytes(g, rows=7) == spz_bytes(g, rows=1000) == spz_bytes(g)


def test_render_of_the_decoded_scene_matches_the_original():
    rng = np.random.default_rng(7)
    g = scene(rng, 3000)
    back = read_spz(spz_bytes(g))
    for projection, width, height in (("erp", 256, 128), ("perspective", 160, 120)):
        a = render(g, np.eye(4), projection=projection, width=width, height=height, normalize=False).colour
        b = render(back, np.eye(4), projection=projection, width=width, height=height, normalize=False).colour
        mse = np.mean((np.clip(a, 0, 1) - np.clip(b, 0, 1)) ** 2)
        assert 10 * np.log10(1 / mse) > 40, projection


def test_beyond_the_ranges_values_clamp_and_stay_finite():
    g = Gaussians(means=[[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], scales=[[1e-9, 1e-9, 1e-9], [1e4, 1.0, 1.0]],
                  quats=[[-1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 2.0]], opacities=[0.0, 1.0],
                  sh=np.array([[[9.0, -9.0, 0.0], [3.0, -3.0, 0.0], [0, 0, 0], [0, 0, 0]]] * 2))
    back = read_spz(spz_bytes(g))
    assert all(np.isfinite(getattr(back, f)).all() for f in ("means", "scales", "quats", "opacities", "sh"))
    assert np.allclose(back.scales[0], np.exp(-10.0)) and np.isclose(back.scales[1].max(), np.exp(255 / 16 - 10))
    assert np.allclose(back.sh[:, 0, :2], [[0.5 / 0.15, -0.5 / 0.15]] * 2)
    assert np.allclose(back.opacities, [0.0, 1.0])
    assert np.allclose(np.abs(back.quats[0]), [1, 0, 0, 0], atol=0.01)  # w < 0 is the same rotation


def test_rows_with_nan_are_dropped_and_empty_scenes_are_files():
    g = scene(np.random.default_rng(1), 10)
    means = g.means.copy()
    means[3] = np.nan
    assert len(read_spz(spz_bytes(g.with_(means=means)))) == 9
    empty = read_spz(spz_bytes(Gaussians.empty(sh_degree=1)))
    assert len(empty) == 0 and empty.sh.shape == (0, 4, 3)


def test_fractional_bits():
    assert fractional_bits(np.zeros((0, 3))) == MAX_FRACTIONAL_BITS
    assert fractional_bits(np.array([[1e-6, 0, 0]])) == MAX_FRACTIONAL_BITS
    assert fractional_bits(np.array([[(1 << 23) - 1, 0, 0]])) == 0
    assert fractional_bits(np.array([[1.0, -4.0, 0]])) == 20
    with pytest.raises(SpzError, match="24-bit"):
        fractional_bits(np.array([[0, 0, -1e7]]))


def test_refusals():
    with pytest.raises(SpzError, match="degree"):
        spz_bytes(scene(np.random.default_rng(0), 5, 9))
    with pytest.raises(SpzError, match="24-bit"):
        spz_bytes(scene(np.random.default_rng(0), 5).with_(means=np.full((5, 3), 2e7)))
    good = spz_bytes(scene(np.random.default_rng(0), 5))
    raw = gzip.decompress(good)
    for bad, word in ((b"not gzip", "gzip"), (gzip.compress(raw[:10]), "truncated"),
                      (gzip.compress(raw[:-1]), "need"), (gzip.compress(b"XXXX" + raw[4:]), "version"),
                      (gzip.compress(raw[:12] + b"\x03" + raw[13:]), "degree")):
        with pytest.raises(SpzError, match=word):
            read_spz(bad)


@pytest.mark.parametrize("unit", [2.0**-10, 1.0, 2.0**10])
def test_a_scene_far_from_the_origin_is_refused_when_its_step_exceeds_an_eighth_of_its_gaussians_size(unit):
    """Georeferenced poses put a room thousands of units from the origin, where SPZ's 24-bit step grows past the
    splats' own size and readers would show them moved. Gaussians of sigmas (1e-4, 1e-2, 5e-2) (median middle
    axis 1e-2; the thinnest and widest axes would decide at the origin or never): a step of 2^-10 (1/10.24 of
    1e-2) up to 8191 units out is kept, 2^-9 (1/5.12) beyond is refused; in any (power of 2) unit alike."""
    assert MAX_STEP_PER_SIZE == 1 / 8
    rng = np.random.default_rng(3)
    room = scene(rng, 200, radius=5.0)
    room = room.with_(scales=np.tile([1e-4, 1e-2, 5e-2], (200, 1))[:, rng.permutation(3)])  # any axis order

    def at(offset):
        return room.with_(means=(room.means + offset) * unit, scales=room.scales * unit)

    for offset in (0.0, 1e3, 8000.0):
        back = read_spz(spz_bytes(at(offset)))  # within half a step, and float32's rounding of the result
        assert np.abs(back.means - at(offset).means).max() <= (2.0**-11 + 2.0**-12) * unit
    for offset in (9000.0, 1e5, 1e6):
        with pytest.raises(SpzError) as info:
            spz_bytes(at(offset))
        assert "use the PLY, or send poses nearer the origin" in str(info.value)
        held = (offset + 5) * unit < 2**23  # else beyond SPZ's 24 bits altogether
        assert ("median size" if held else "24-bit positions hold at most") in str(info.value)


def test_gaussians_of_median_size_zero_are_refused_with_an_spz_error():
    """Points (all scales 0, which Gaussians allow) have a median size of 0, which every position step exceeds:
    the refusal's message divided by it, a ZeroDivisionError instead of the SpzError."""
    points = scene(np.random.default_rng(4), 20).with_(scales=np.zeros((20, 3)))
    with pytest.raises(SpzError, match="more than their median size 0 "):
        spz_bytes(points)
