"""Property-based stability of the renderer over extreme Gaussians and cameras."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rasterizer import geometry as geo
from rasterizer.composite import COLOUR_MAX, T_MIN
from rasterizer.gaussians import Gaussians, GaussiansError, rgb_to_sh_dc
from rasterizer.render import render, to_uint8
from rasterizer.sh import sh_to_rgb
from rasterizer.splat import ALPHA_MIN

CAMERAS = [dict(projection="erp", width=48, method="direct"), dict(projection="erp", width=48),
           dict(projection="yin", width=48), dict(projection="yang", width=48),
           dict(projection="perspective", width=32, height=24, fov_deg=100)]


def check(out):
    for arr in out:
        assert np.all(np.isfinite(arr))
    assert np.all((out.alpha >= 0) & (out.alpha <= 1))
    assert np.all(out.range >= 0)


special_dirs = st.sampled_from([(0, -1, 0), (0, 1, 0), (0, 0, -1), (0, 0, 1), (1, 0, 0), (1e-9, -1, 0),
                                (-1e-9, 0, -1), (0.7, 0.7, 0)])
directions = st.one_of(special_dirs, st.tuples(*[st.floats(-1, 1)] * 3))


@st.composite
def extreme_gaussians(draw):
    n = draw(st.integers(1, 12))
    rows = []
    for _ in range(n):
        d = np.asarray(draw(directions), dtype=np.float64)
        if np.linalg.norm(d) < 1e-12:
            d = np.array([0.0, 0.0, 1.0])
        rng_ = draw(st.sampled_from([0.0, 1e-6, 1e-4, 1e-2, 0.5, 3.0, 1e3, 1e6]))
        mean = d / np.linalg.norm(d) * rng_
        scales = [draw(st.sampled_from([0.0, 1e-8, 1e-3, 0.1, 2.0, 1e4])) for _ in range(3)]
        q = np.asarray(draw(st.tuples(*[st.floats(-1, 1)] * 4)))
        rows.append((mean, scales, q, draw(st.sampled_from([0.0, 1 / 255, 0.5, 0.999, 1.0])),
                     draw(st.floats(0, 1))))
    means, scales, quats, op, col = map(np.array, zip(*rows))
    return Gaussians(means, scales, quats, op, rgb_to_sh_dc(np.repeat(col[:, None], 3, 1))[:, None, :])


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(g=extreme_gaussians(), cam=st.sampled_from(CAMERAS), seed=st.integers(0, 2**16))
def test_extreme_gaussians_render_finite(g, cam, seed):
    rng = np.random.default_rng(seed)
    c2w = np.eye(4)
    if seed % 2:
        q = rng.normal(size=4)
        from rasterizer.gaussians import quat_to_rotmat
        c2w[:3, :3] = quat_to_rotmat(q[None] / np.linalg.norm(q))[0]
    check(render(g, c2w, **cam))


@settings(max_examples=10, deadline=None)
@given(count=st.integers(500, 3000), spread=st.sampled_from([0.0, 1e-6, 0.01]), cam=st.sampled_from(CAMERAS))
def test_many_overlapping_splats(count, spread, cam):
    rng = np.random.default_rng(count)
    means = np.array([0.0, 0.0, 2.0]) + rng.normal(size=(count, 3)) * spread
    g = Gaussians(means, np.full((count, 3), 0.3), np.tile([1.0, 0, 0, 0], (count, 1)),
                  rng.uniform(0, 1, count), rng.normal(size=(count, 1, 3)))
    out = render(g, geo.yang_pose(np.eye(4)) if cam["projection"] == "yang" else np.eye(4), **cam)
    check(out)
    assert out.alpha.max() > 0.99  # hundreds of layers saturate the centre


@pytest.mark.parametrize("field", ["means", "scales", "quats", "opacities", "sh"])
@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_nan_and_inf_are_rejected_naming_the_field(field, bad):
    g = Gaussians(np.array([[0.0, 0, 2]]), np.full((1, 3), 0.1), np.array([[1.0, 0, 0, 0]]),
                  np.array([0.5]), np.zeros((1, 1, 3)))
    arr = getattr(g, field).copy()
    arr.flat[0] = bad
    with pytest.raises(ValueError, match=field) as err:
        render(g.with_(**{field: arr}), np.eye(4), projection="erp", width=32)
    assert isinstance(err.value, GaussiansError)


def test_bad_pose_and_sizes_are_rejected():
    g = Gaussians.empty()
    with pytest.raises(ValueError, match="NaN"):
        render(g, np.full((4, 4), np.nan), projection="erp", width=32)
    with pytest.raises(ValueError, match="width"):
        render(g, np.eye(4), projection="erp", width=0)
    with pytest.raises(ValueError, match="fov"):
        render(g, np.eye(4), projection="perspective", width=16, fov_deg=180)
    out = render(g, np.eye(4), projection="erp", width=32)
    assert out.colour.shape == (16, 32, 3) and out.alpha.max() == 0


def _disc(means, scale=0.004):
    n = len(means)
    return Gaussians(means=np.asarray(means, np.float32), scales=np.full((n, 3), scale, np.float32),
                     quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)), opacities=np.ones(n, np.float32),
                     sh=rgb_to_sh_dc(np.full((n, 3), 0.5, np.float32))[:, None, :])


def test_grazing_gaussians_beside_a_pinhole_add_no_haze_and_are_not_refused():
    """Centimetre Gaussians 2 m away but 89.7 deg off axis (z = 1 cm) cannot reach the image.

    Before the 3-D frustum cull their linearised (EWA) ellipses covered the
    image many times over: a hazy veil and RenderLimitError for inside views.
    """
    rng = np.random.default_rng(0)
    ang = rng.uniform(0, 2 * np.pi, 400)
    means = np.stack([2 * np.cos(ang), 2 * np.sin(ang), rng.uniform(0.0101, 0.012, 400)], axis=1)
    out = render(_disc(means), np.eye(4), projection="perspective", width=1024, height=768, fov_deg=90,
                 threads=1)
    assert out.alpha.max() == 0.0
    # one just inside the widened border still draws (the cull is conservative)
    inside = _disc([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0]], 0.05)
    out = render(inside, np.eye(4), projection="perspective", width=64, height=48, fov_deg=90)
    assert out.alpha[24, 32] > 0.9 and out.alpha[:, -1].max() > 0.1


@pytest.mark.parametrize("cam", [dict(projection="perspective", width=1024, height=768, fov_deg=90),
                                 dict(projection="erp", width=1024, method="direct"),
                                 dict(projection="erp", width=1024), dict(projection="yin", width=768)])
def test_camera_one_centimetre_from_a_wall_renders(cam):
    """A dense wall of pixel-sized Gaussians seen from 1 cm renders without RenderLimitError."""
    u = np.linspace(-1.5, 1.5, 301)
    xx, yy = np.meshgrid(u, u)
    means = np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, 0.0105)], axis=1)
    out = render(_disc(means, 0.004), np.eye(4), threads=1, **cam)
    check(out)
    assert out.alpha.max() > 0.9


@settings(max_examples=12, deadline=None)
@given(k=st.sampled_from([4, 9, 16]), value=st.sampled_from([3e38, -3e38, 1e38, 2e37]),
       cam=st.sampled_from(CAMERAS + [dict(projection="perspective", width=32, height=24, resolution="scene")]))
def test_sh_coefficients_near_float32s_limit_give_finite_clamped_colours(k, value, cam):
    """Finite SH coefficients whose sum overflows float32 (3.4e38) made Inf colours, and NaN pixels (Inf times a
    zero weight) in the Yin-Yang merge, shown black: each colour is now clamped to COLOUR_MAX, which saturates.
    Seen along +z (x = y = 0) every basis function of the coefficients' sign adds, so the sum is +-(0.28 + 0.49
    + 0.63 + 0.75) x value."""
    means = np.array([[0.0, 0.0, 2.0], [0.0, -0.3, 2.0]])
    g = Gaussians(means, np.full((2, 3), 0.3), np.tile([1.0, 0, 0, 0], (2, 1)), np.full(2, 0.9),
                  np.full((2, k, 3), value))
    out = render(g, geo.yang_pose(np.eye(4)) if cam["projection"] == "yang" else np.eye(4), threads=1, **cam)
    check(out)
    covered = out.alpha > 0.5
    assert covered.any()
    assert np.all(to_uint8(out.colour)[covered] == (255 if value > 0 else 0))


def test_colour_max_saturates_the_faintest_contribution():
    assert COLOUR_MAX * ALPHA_MIN * T_MIN * 255.0 + 0.5 >= 255.0
    colours = sh_to_rgb(np.full((2, 16, 3), 3e38, np.float32), np.array([[0.0, 0, 2], [0.0, 0, -2]]), np.zeros(3))
    assert colours.dtype == np.float32 and np.allclose(colours, [[COLOUR_MAX] * 3, [0.0] * 3])


@pytest.mark.parametrize("axis", [(0, -1, 0), (0, 1, 0), (1, 0, 0), (-1, 0, 0)])
def test_a_wide_gaussian_on_a_grids_pole_axis_renders_as_one_beside_it(axis):
    """A centre exactly on the Yin grid's pole axis (straight up or down) or the Yang grid's (camera +-x) had a
    Jacobian of zero (its offsets from the axis were 0 and the floor applied to their squares only): the grid
    drew it as a sub-pixel dot outside its domain, dropping the wide footprint's part in it (about 30% of this
    one's coverage), while a centre 1e-6 m beside the axis drew it whole."""
    def alpha(mean):
        g = Gaussians(np.array([mean]), np.full((1, 3), 3.0), np.array([[1.0, 0, 0, 0]]), np.array([0.5]),
                      np.zeros((1, 1, 3)))
        return render(g, np.eye(4), projection="erp", width=64, threads=1).alpha

    on = alpha(3.0 * np.asarray(axis, float))
    beside = alpha(3.0 * np.asarray(axis, float) + [0.0, 0.0, 1e-6])
    assert np.isfinite(on).all() and on.sum() > 0
    assert np.abs(on - beside).max() < 1e-3
