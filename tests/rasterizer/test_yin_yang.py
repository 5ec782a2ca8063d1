"""ERP <-> Yin/Yang image resampling and ERP resizing."""

import numpy as np
import pytest

from bench.metrics import psnr
from rasterizer import geometry as geo
from rasterizer.yin_yang import blend_weight_yin, erp_to_yin_yang, grid_pixel, resize_erp, yin_yang_to_erp


def smooth_erp(h, w):
    """A smooth function of the viewing direction (continuous across seam and poles)."""
    d = geo.grid_directions("erp", h, w)
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    return np.stack([0.5 + 0.3 * x * z + 0.1 * y, 0.5 + 0.25 * np.sin(6 * x + 3 * y) * np.cos(5 * z),
                     0.5 + 0.2 * z * y - 0.1 * x], -1)


def test_shapes_and_direction_sampling():
    erp = smooth_erp(64, 128)
    yin, yang = erp_to_yin_yang(erp)
    assert yin.shape == yang.shape == (32, 96, 3) and yin.dtype == np.float32
    yin2d, _ = erp_to_yin_yang(erp[..., 0])
    assert yin2d.shape == (32, 96)
    # each Yin/Yang pixel holds the value of its own direction
    for kind, img in (("yin", yin), ("yang", yang)):
        d = geo.grid_directions(kind, 32, 96)
        x, y, z = d[..., 0], d[..., 1], d[..., 2]
        exact = 0.5 + 0.3 * x * z + 0.1 * y
        assert np.abs(img[..., 0] - exact).max() < 5e-3


def test_round_trip_psnr_of_a_smooth_image():
    erp = smooth_erp(256, 512)
    yin, yang = erp_to_yin_yang(erp)
    back = yin_yang_to_erp(yin, yang, 256, 512)
    value = psnr(back, erp)
    print(f"ERP -> Yin/Yang -> ERP round trip PSNR (smooth 256x512): {value:.1f} dB")
    assert value > 50


def test_blend_weights_cover_the_sphere_without_a_seam():
    d = geo.grid_directions("erp", 256, 512)
    feather = np.radians(0.7)
    w = blend_weight_yin(d, feather)
    assert w.min() >= 0 and w.max() <= 1
    in_yin, in_yang = geo.in_grid_domain("yin", d), geo.in_grid_domain("yang", d)
    assert np.all(in_yin | in_yang)
    # Yin alone where Yang does not reach (even with the feather), and vice versa
    assert np.all(w[~in_yin] < 1) and np.all(w[in_yin & ~in_yang] > 0)
    assert np.all(blend_weight_yin(d)[in_yin & ~in_yang] == 1) and np.all(blend_weight_yin(d)[~in_yin] == 0)
    overlap = (in_yin & in_yang).mean()
    assert 0.03 < overlap < 0.09  # the ~6% overlap where both contribute
    # continuous: neighbouring pixels never jump by much
    # continuous, or (where the edges coincide) spread over at least two pixels: no 0 -> 1 switch
    assert np.abs(np.diff(w, axis=1)).max() < 0.75 and np.abs(np.diff(w, axis=0)).max() < 0.75
    # a constant image survives the merge exactly (weights sum to 1)
    ones = np.ones((128, 384))
    assert np.allclose(yin_yang_to_erp(ones, ones, 256, 512), 1, atol=1e-6)


def test_resize_erp():
    img = smooth_erp(64, 128)
    half = resize_erp(img, 32, 64)
    assert half.shape == (32, 64, 3)
    # area averaging by 2: each output is the mean of its 2x2 block
    assert np.allclose(half, img.reshape(32, 2, 64, 2, 3).mean(axis=(1, 3)), atol=1e-6)
    # upsampling then area downsampling returns (almost) the original
    up = resize_erp(img, 128, 256)
    assert psnr(resize_erp(up, 64, 128), img) > 45
    # longitude wraps: a column shift commutes with resizing by an integer factor
    assert np.allclose(resize_erp(np.roll(img, 2, axis=1), 32, 64), np.roll(half, 1, axis=1), atol=1e-6)
    assert np.allclose(resize_erp(np.full((10, 20), 0.3), 7, 14), 0.3, atol=1e-6)
    with pytest.raises(ValueError):
        resize_erp(img, 0, 10)


def test_grid_pixel_is_the_owner_grids_nearest_pixel():
    h, w = 16, 48
    rng = np.random.default_rng(5)
    d = rng.standard_normal((20000, 3)) * rng.uniform(0.1, 30.0, (20000, 1))
    centres = np.concatenate([geo.grid_directions(k, h, w).reshape(-1, 3) for k in ("yin", "yang")])
    seams = geo.direction_from_lat_lon(np.linspace(-np.pi / 2, np.pi / 2, 101)[:, None],
                                       np.array([-3, -1, 0, 1, 3]) * np.pi / 4)
    p = np.concatenate([d, 2.5 * centres, seams.reshape(-1, 3)])
    # the definition: Yang where Yin's blend weight is below 0.5, each grid's projection rounded and clamped
    yang = blend_weight_yin(p) < 0.5
    want = []
    for kind in ("yin", "yang"):
        col, row = geo.project_to_grid(kind, p, h, w)
        want.append(np.clip(np.rint(row), 0, h - 1).astype(np.int64) * w + np.clip(np.rint(col), 0, w - 1).astype(np.int64))
    want = np.where(yang, h * w + want[1], want[0])
    got = grid_pixel(p, ("yin", "yang"), h, w)
    np.testing.assert_array_equal(got, want)
    # a pixel centre the blend gives to its own grid is its own nearest pixel
    n = centres.shape[0]
    own = np.where(yang[20000:20000 + n], np.arange(n) >= h * w, np.arange(n) < h * w)
    assert own.mean() > 0.9
    np.testing.assert_array_equal(got[20000:20000 + n][own], np.arange(n)[own])


def _dense_resize(img, height, width):
    """Reference: resize_erp as its two axis operators applied to the whole image at once (float64)."""
    h, w = img.shape[:2]
    rows = resize_erp(np.eye(h)[:, :, None], height, h)[:, :, 0].astype(np.float64)  # (height, h)
    cols = resize_erp(np.eye(w)[:, :, None], w, width)[:, :, 0].astype(np.float64)  # (w, width): row i = response to column i
    return np.einsum("owc,wx->oxc", np.einsum("oh,hwc->owc", rows, img.astype(np.float64), optimize=True), cols,
                     optimize=True)


@pytest.mark.parametrize("shape,size", [((1440, 2880, 3), (512, 1024)),  # shrink over several row blocks
                                        ((300, 600, 3), (512, 1024)),  # enlarge
                                        ((512, 1024, 3), (512, 1024))])  # same size
def test_resize_erp_blocks_equal_whole_image(shape, size):
    rng = np.random.default_rng(7)
    img = rng.integers(0, 256, shape, dtype=np.uint8)
    out = resize_erp(img, *size)
    assert out.dtype == np.float32 and out.shape == (*size, 3)
    assert np.abs(out - _dense_resize(img, *size)).max() < 1e-3  # float32 rounding of values up to 255
    # uint8 and its float copy resample alike (uint8 -> float32 is exact)
    assert np.array_equal(out, resize_erp(img.astype(np.float32), *size))


def test_resize_erp_never_holds_a_full_size_float_copy():
    import tracemalloc

    img = np.random.default_rng(8).integers(0, 256, (1440, 2880, 3), dtype=np.uint8)
    tracemalloc.start()
    try:
        resize_erp(img, 512, 1024)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < img.size * 4  # less than one float32 copy of the input
