"""Layout prior (export/layout.py): plane fit on a synthetic room, upright gate, agreement gating,
nothing below the floor."""

import numpy as np
import pytest
import torch

from export.aggregation import pyramid_levels
from export.layout import CLAMP_MIN_SIN, clamp_below_floor, fit_planes, plane_prior, with_plane_prior
from rasterizer.geometry import grid_directions

H, W = 32, 96  # one Yin/Yang feature grid
FLOOR, CEILING = 1.4, 0.9  # metres below / above the cameras
HALF = (2.5, 3.0)  # box half-extents (x, z), metres


def _rays() -> torch.Tensor:
    return torch.from_numpy(np.stack([grid_directions(k, H, W) for k in ("yin", "yang")]).astype(np.float32))


def _box_range(rays_world: np.ndarray, centre: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Range to the walls, floor and ceiling of an axis-aligned box room (world frame ``up`` = -gravity)."""
    down = -rup(up)
    s = rays_world @ down
    horiz = rays_world - s[..., None] * down
    # walls: |x| = HALF[0], |z| = HALF[1] in the horizontal plane spanned by e1, e2
    e1 = np.cross(down, [0.0, 0.0, 1.0]) if abs(down[2]) < 0.9 else np.cross(down, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(down, e1)
    c1, c2 = centre @ e1, centre @ e2
    t = np.full(s.shape, np.inf)
    for axis, half, c in ((e1, HALF[0], c1), (e2, HALF[1], c2)):
        v = horiz @ axis
        with np.errstate(divide="ignore"):
            t = np.minimum(t, np.where(v > 1e-9, (half - c) / v, np.where(v < -1e-9, (-half - c) / v, np.inf)))
    with np.errstate(divide="ignore"):
        t = np.minimum(t, np.where(s > 1e-9, FLOOR / s, np.where(s < -1e-9, CEILING / -s, np.inf)))
    return t


def rup(up):
    up = np.asarray(up, dtype=np.float64)
    return up / np.linalg.norm(up)


def _pose(yaw_deg: float, centre, up=(0.0, -1.0, 0.0)) -> np.ndarray:
    """Upright camera: OpenCV y (down) along -up, yawed about it."""
    down = -rup(up)
    a = np.cross(down, [0.0, 0.0, 1.0]) if abs(down[2]) < 0.9 else np.cross(down, [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(a, down)
    yaw = np.radians(yaw_deg)
    x = np.cos(yaw) * a + np.sin(yaw) * b
    z = np.cross(x, down)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([x, down, z], axis=1)
    c2w[:3, 3] = centre
    return c2w


def _room(up=(0.0, -1.0, 0.0)):
    rays = _rays()
    side = np.cross(rup(up), [1.0, 0.0, 0.0]) if abs(rup(up)[0]) < 0.9 else np.cross(rup(up), [0.0, 0.0, 1.0])
    poses = [_pose(10.0, np.zeros(3), up), _pose(-35.0, 0.8 * side / np.linalg.norm(side), up)]
    inv = []
    for c2w in poses:
        world = rays.numpy().astype(np.float64) @ c2w[:3, :3].T
        inv.append(1.0 / _box_range(world, c2w[:3, 3], up))
    inv = torch.from_numpy(np.stack(inv).reshape(4, 1, H, W).astype(np.float32))
    return rays, inv, torch.from_numpy(np.stack(poses).astype(np.float32))


@pytest.mark.parametrize("up", [(0.0, -1.0, 0.0), (0.0, 0.0, 1.0), (0.3, 0.2, 0.9)], ids=["y-up", "z-up", "tilted-world"])
def test_fit_planes_recovers_floor_and_ceiling(up):
    rays, inv, c2w = _room(up)
    gravity, floor, ceiling, upright = fit_planes(rays, inv, torch.ones_like(inv), c2w)
    assert float(upright) == 1.0
    np.testing.assert_allclose(gravity.numpy(), -rup(up), atol=1e-5)
    np.testing.assert_allclose(floor.numpy(), [FLOOR, FLOOR], rtol=0.02)
    np.testing.assert_allclose(ceiling.numpy(), [CEILING, CEILING], rtol=0.02)
    # the prior then reproduces the box's floor and ceiling pixels exactly where they are steep
    plane_inv, ramp = plane_prior((gravity, floor, ceiling, upright), rays, c2w, (0.2, 0.5))
    steep = ramp >= 1.0
    assert steep.float().mean() > 0.2
    # the box's walls are nearer than the planes at some steep pixels: compare only true plane pixels
    on = steep & ((plane_inv - inv).abs() <= 0.02 * inv)
    assert on.float().sum() >= 0.6 * steep.float().sum()


TABLE = 0.6  # metres below the cameras


@pytest.mark.parametrize(("table_weight", "expect"), [(1.5, FLOOR), (1.9, FLOOR), (3.0, TABLE)])
def test_floor_is_the_farthest_heavy_level_not_a_heavier_table_top(table_weight, expect):
    """A table top under both cameras outweighs the floor in the histogram (its mode is the table).
    The fit returns the floor while the floor holds at least FLOOR_PEAK_SHARE of the table's
    weight (here 0.84 and 0.66), and the table below that (0.42); the ceiling either way."""
    rays, inv, c2w = _room()
    sin_el = torch.stack([(rays.reshape(-1, 3) @ c2w[v, :3, :3].T)[:, 1] for v in range(2)]).reshape(inv.shape)
    top = (sin_el > 0.7) & (TABLE / sin_el.clamp(min=1e-6) < 1.0 / inv)
    inv = torch.where(top, sin_el / TABLE, inv)
    weight = torch.where(top, torch.full_like(inv, table_weight), torch.ones_like(inv))
    on_floor = (sin_el > 0.25) & ~top & ((inv * FLOOR - sin_el).abs() < 0.01)
    assert float(weight[top].sum()) > float(weight[on_floor].sum()) > 0  # the mode would pick the table
    _, floor, ceiling, _ = fit_planes(rays, inv, weight, c2w)
    np.testing.assert_allclose(floor.numpy(), [expect, expect], rtol=0.02)
    np.testing.assert_allclose(ceiling.numpy(), [CEILING, CEILING], rtol=0.02)


@pytest.mark.parametrize("nadir_deg", [5.0, 15.0, 40.0])
def test_no_floor_prior_straight_under_the_cameras(nadir_deg):
    """Within nadir_deg of straight down the ramp is 0 (each camera's rig or what it stands over); elsewhere,
    ceiling included, it is the ramp without the cut."""
    rays, inv, c2w = _room()
    planes = fit_planes(rays, inv, torch.ones_like(inv), c2w)
    _, full = plane_prior(planes, rays, c2w, (0.2, 0.5))
    _, cut = plane_prior(planes, rays, c2w, (0.2, 0.5), nadir_deg)
    gravity = planes[0].double()
    down = torch.stack([rays.double() @ c2w[v, :3, :3].double().T @ gravity for v in range(2)])  # (view, grid, h, w)
    down = down.reshape(cut.shape)  # cos of each ray's angle to gravity, in plane_prior's [view][grid] order
    under = down > np.cos(np.radians(nadir_deg))
    assert under.any() and (~under & (full > 0)).any()
    assert float(cut[under].abs().max()) == 0.0
    assert torch.equal(cut[~under], full[~under])


def test_tilted_cameras_get_no_prior():
    rays, inv, c2w = _room()
    tilt = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.866, -0.5], [0.0, 0.5, 0.866]])  # 30 deg about x
    c2w[1, :3, :3] = tilt @ c2w[1, :3, :3]
    planes = fit_planes(rays, inv, torch.ones_like(inv), c2w)
    assert float(planes[3]) == 0.0
    _, ramp = plane_prior(planes, rays, c2w, (0.2, 0.5))
    assert float(ramp.abs().max()) == 0.0


def test_no_confident_pixels_adds_nothing():
    """Textureless input: no weight anywhere -> the prior adds no weight (no invented planes)."""
    rays, inv, c2w = _room()
    zero = torch.zeros_like(inv)
    planes = fit_planes(rays, inv, zero, c2w)
    assert all(torch.isfinite(t).all() for t in planes)
    plane_inv, ramp = plane_prior(planes, rays, c2w, (0.2, 0.5))
    value, weight = with_plane_prior(inv, zero, plane_inv, ramp, pyramid_levels(H, W), 3.0, 0.08)
    assert torch.isfinite(value).all() and float(weight.abs().max()) == 0.0


def test_agreement_gates_the_prior():
    """A floor patch whose confident pixels lie on the plane takes it; one whose confident pixels
    lie 30% nearer (a table top) keeps its own data: the prior's weight there stays near zero."""
    levels = pyramid_levels(H, W)
    plane_inv = torch.full((1, 1, H, W), 0.5)
    ramp = torch.ones_like(plane_inv)
    weight = torch.zeros_like(plane_inv)
    weight[..., ::4, ::4] = 1.0  # sparse confident pixels
    for data, expect_prior in ((0.5, True), (0.5 / 0.7, False)):
        inv = torch.full_like(plane_inv, data)
        inv[weight == 0] = 0.1  # unconfident pixels' raw picks: wrong
        value, w = with_plane_prior(inv, weight, plane_inv, ramp, levels, 3.0, 0.08)
        gap = weight == 0
        added = (w - weight)[gap]
        if expect_prior:
            assert float(added.min()) > 2.0
            torch.testing.assert_close(value[gap], plane_inv[gap])
        else:
            assert float(added.max()) < 1e-3


@pytest.mark.parametrize("bad", [-1.0, 90.0, 120.0])
def test_config_refuses_a_nadir_cut_outside_0_to_90(bad):
    from export.config import make_config

    with pytest.raises(ValueError, match="layout_nadir_deg"):
        make_config("quality", layout_nadir_deg=bad)


def _sin_below(rays, c2w, gravity):
    """(2, G, h, w) sine of each camera-frame ray's (G, h, w, 3) elevation below the horizon, per view."""
    return torch.stack([rays @ c2w[v, :3, :3].T @ gravity for v in range(2)])


@pytest.mark.parametrize("tol", [0.0, 0.1, 0.3])
def test_nothing_below_the_floor(tol):
    """Points sunk below the floor (the fill's smear) come up to (1 + tol) x the floor's range; points
    above it (furniture, walls), rays near or above the horizon and the true room stay as they are."""
    rays, inv, c2w = _room()
    planes = fit_planes(rays, inv, torch.ones_like(inv), c2w)
    floor = planes[1].reshape(2, 1, 1, 1).repeat_interleave(2, 0)  # per map
    sin_el = _sin_below(rays, c2w, planes[0]).reshape(inv.shape)  # the maps' [view][grid] order
    # the room itself: untouched, up to the fit's error in the floor height (< 1%) at tol 0
    torch.testing.assert_close(clamp_below_floor(planes, inv, rays, c2w, tol), inv, rtol=0.01, atol=0.0)
    sunk = inv * 0.5  # every point twice as far
    out = clamp_below_floor(planes, sunk, rays, c2w, tol)
    below = (sin_el > CLAMP_MIN_SIN) & (sunk < sin_el / (floor * (1 + tol)))
    assert below.float().mean() > 0.2
    torch.testing.assert_close(out[below], (sin_el / (floor * (1 + tol)))[below])
    assert torch.equal(out[~below], sunk[~below])
    assert bool((out[sin_el <= CLAMP_MIN_SIN] == sunk[sin_el <= CLAMP_MIN_SIN]).all())


def test_no_floor_clamp_for_tilted_cameras_or_a_floor_above_them():
    rays, inv, c2w = _room()
    sunk = inv * 0.5
    planes = fit_planes(rays, inv, torch.ones_like(inv), c2w)
    gravity, floor, ceiling, _ = planes
    assert torch.equal(clamp_below_floor((gravity, floor, ceiling, torch.zeros(())), sunk, rays, c2w, 0.1), sunk)
    assert torch.equal(clamp_below_floor((gravity, -floor, ceiling, planes[3]), sunk, rays, c2w, 0.1), sunk)


@pytest.mark.parametrize("bad", [-0.1, float("nan")])
def test_config_refuses_a_negative_floor_tolerance(bad):
    from export.config import make_config

    with pytest.raises(ValueError, match="floor_clamp_tol"):
        make_config("quality", floor_clamp_tol=bad)


@pytest.mark.parametrize("clamp", [True, False], ids=["floor_clamp", "no_clamp"])
def test_encoder_keeps_every_point_above_the_floor(zind_dir, monkeypatch, clamp):
    """The whole graph on zind_room09's widest pair (4.25 m, where the fill sinks the carpet): with the
    rule, no final range lies beyond (1 + floor_clamp_tol) x the fitted floor's range along its ray;
    without it, some do (so this test sees the rule's wiring, not only the function)."""
    import export.model as model_module
    from export.config import make_config
    from export.model import OmniSplatEncoder
    from rasterizer.scene_folder import load_scene
    from rasterizer.sweep import INPUT_NAMES, OUTPUT_NAMES, default_near_far, sweep_inputs
    from rasterizer.yin_yang import resize_erp

    fits = []
    monkeypatch.setattr(model_module, "fit_planes", lambda *a: fits.append(fit_planes(*a)) or fits[-1])
    cfg = make_config("quality", height=128, width=256, num_planes=16, floor_clamp=clamp)
    scene = load_scene(zind_dir)
    fa, fb = scene.frames["pano_2"], scene.frames["pano_6"]
    near, far = default_near_far(fa.c2w, fb.c2w)
    si = sweep_inputs(fa.c2w, fb.c2w, near=near, far=far, num_planes=cfg.num_planes, feature_size=cfg.feature_size)
    img = lambda f: np.ascontiguousarray(resize_erp(f.image(), cfg.height, cfg.width).transpose(2, 0, 1)[None])
    feeds = {"erp_a": img(fa), "erp_b": img(fb), **{k: np.array(si[k]) for k in INPUT_NAMES[2:]}}
    with torch.no_grad():
        out = OmniSplatEncoder(cfg).eval()(*[torch.from_numpy(feeds[k]) for k in INPUT_NAMES])
    rng = dict(zip(OUTPUT_NAMES, out))["range_maps"].double()  # (2, G, H, W)
    (gravity, floor, _, upright), = fits
    assert float(upright) == 1.0 and bool((floor > 0.5).all())  # an upright capture with a floor below
    rays = torch.from_numpy(np.stack([grid_directions(k, *rng.shape[-2:]) for k in cfg.grids]))
    sin_el = _sin_below(rays, torch.from_numpy(np.stack([fa.c2w, fb.c2w])), gravity.double())  # (2, G, H, W)
    below = sin_el > CLAMP_MIN_SIN
    depth = (rng * sin_el)[below]  # metres below the camera along gravity
    limit = (floor.double().reshape(2, 1, 1, 1).expand_as(rng) * (1 + cfg.floor_clamp_tol))[below]
    sunk = float((depth > limit * (1 + 1e-4)).double().mean())
    if clamp:
        assert sunk == 0.0
    else:
        assert sunk > 0.01, sunk
