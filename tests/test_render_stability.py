"""Property-based stability of the renderer over extreme Gaussians and cameras."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from rasterizer import geometry as geo
from rasterizer.gaussians import Gaussians, GaussiansError, rgb_to_sh_dc
from rasterizer.render import render

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
