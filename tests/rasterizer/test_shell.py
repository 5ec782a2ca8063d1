"""Environment shell: layout, geometry, coverage behind translucent surfels, and compaction's pass-through."""

import numpy as np
import pytest

from rasterizer import geometry as geo
from rasterizer.compaction import CompactionError, CompactionOptions, Provenance, compact_result
from rasterizer.depth_gaussians import gaussians_from_depth
from rasterizer.gaussians import Gaussians, rgb_to_sh_dc, sh_dc_to_rgb
from rasterizer.render import render
from rasterizer.shell import SHELL_OPACITY, SHELL_RADIUS_FACTOR, environment_shell, shell_block, shell_layout, shell_radius
from tests.rasterizer._support import box_range, pose_at

H, W = 16, 48  # one Yin/Yang grid


def _scene(opacity):
    """Two references in a box room: pixel-aligned surfels of the given opacity, ranges (2, 2, H, W), poses."""
    poses = np.stack([pose_at([0.0, 0.0, -0.3]), pose_at([0.0, 0.0, 0.3])])
    ranges = np.stack([[box_range(k, c, size=(H, W)) for k in ("yin", "yang")] for c in poses])
    parts = []
    for v, c in enumerate(poses):
        for gi, k in enumerate(("yin", "yang")):
            p = c[:3, 3] + (geo.grid_directions(k, H, W) @ c[:3, :3].T) * ranges[v, gi][..., None]
            colour = (0.5 + 0.4 * np.sin(3 * p)).astype(np.float32)
            parts.append(gaussians_from_depth(colour, ranges[v, gi], c, k, surfels=True, opacity=opacity))
    return Gaussians.concatenate(parts), ranges, poses


def test_block_and_layout():
    assert shell_block(16, 48) == 4 and shell_block(6, 18) == 2 and shell_block(5, 15) == 1
    index, block = shell_layout(2, 2, H, W)
    assert index.size == 2 * 2 * (H // 4) * (W // 4) and np.all(block == 4)
    # [view][grid][block row][block col]: the top-left pixel of each block
    assert index[0] == 0 and index[1] == 4 and index[W // 4] == 4 * W
    assert index[(H // 4) * (W // 4)] == H * W  # view 0, Yang grid starts after the Yin grid


def test_geometry_and_colour():
    g, ranges, poses = _scene(opacity=0.3)
    shell = environment_shell(g, ranges, poses, ("yin", "yang"))
    assert len(shell) == 2 * 2 * (H // 4) * (W // 4)
    shell.check_finite()
    assert np.all(shell.opacities == np.float32(SHELL_OPACITY))
    # view A's Yin blocks: on the sphere of shell_radius around camera A, along each block centre's ray
    n = (H // 4) * (W // 4)
    radius = shell_radius(ranges)
    assert radius == pytest.approx(SHELL_RADIUS_FACTOR * np.percentile(ranges, 99))
    assert radius > 2 * ranges.max()  # beyond every surface of the box
    np.testing.assert_allclose(np.linalg.norm(shell.means[:n] - poses[0, :3, 3], axis=1), radius, rtol=1e-5)
    centre_rays = geo.grid_directions("yin", H // 4, W // 4).reshape(-1, 3)
    np.testing.assert_allclose((shell.means[:n] - poses[0, :3, 3]) / radius, centre_rays, atol=1e-5)
    # colour: the block mean of the pixel-aligned colours
    rgb = sh_dc_to_rgb(g.sh[: H * W, 0]).reshape(H // 4, 4, W // 4, 4, 3).mean(axis=(1, 3)).reshape(-1, 3)
    np.testing.assert_allclose(sh_dc_to_rgb(shell.sh[:n, 0]), np.clip(rgb, 0, 1), atol=1e-5)
    # exactly numpy's block mean, in every view and grid
    blocks = sh_dc_to_rgb(g.sh[:, 0]).reshape(2, 2, H // 4, 4, W // 4, 4, 3).mean(axis=(3, 5)).reshape(-1, 3)
    np.testing.assert_array_equal(shell.sh[:, 0], rgb_to_sh_dc(np.clip(blocks, 0, 1)))


def test_radius_ignores_invalid_ranges():
    r = np.array([1.0, 2.0, np.nan, np.inf, -1.0, 0.0])
    assert shell_radius(r) == pytest.approx(SHELL_RADIUS_FACTOR * np.percentile([1.0, 2.0], 99))
    assert shell_radius(np.full(4, np.nan)) == SHELL_RADIUS_FACTOR


def test_shell_never_hides_a_surface_only_the_other_view_sees():
    """A near object in front of view A: A's backdrop of it must stay behind the wall that B sees."""
    g, ranges, poses = _scene(opacity=0.99)
    near = ranges.copy()
    near[0] *= 0.25  # view A's ranges (a near object all round A); B keeps the box
    shell = environment_shell(g, near, poses, ("yin", "yang"))
    n = len(shell) // 2
    d_a = np.linalg.norm(shell.means[:n] - poses[0, :3, 3], axis=1)
    assert d_a.min() > ranges[1].max() + np.linalg.norm(poses[1, :3, 3] - poses[0, :3, 3])


def test_shell_covers_behind_translucent_surfels():
    g, ranges, poses = _scene(opacity=0.3)
    shell = environment_shell(g, ranges, poses, ("yin", "yang"))
    target = pose_at([0.4, 0.2, 0.0])  # off the baseline
    alone = render(g, target, projection="erp", width=96, method="direct").alpha
    both = render(Gaussians.concatenate([g, shell]), target, projection="erp", width=96, method="direct").alpha
    assert (alone >= 0.99).mean() < 0.5  # translucent surfels alone leave the view half see-through
    assert (both >= 0.99).mean() >= 0.98
    # at a reference the shell shows that reference's own colours: the render matches the surfels' own
    ref = render(Gaussians.concatenate([g, shell]), poses[0], projection="erp", width=96, method="direct")
    opaque = render(g.with_(opacities=np.full(len(g), 0.99, np.float32)), poses[0], projection="erp", width=96,
                    method="direct")
    assert np.abs(ref.colour - opaque.colour).mean() < 0.05


@pytest.mark.parametrize("projection", ["erp", "perspective"])
def test_the_two_shells_alone_cover_every_pixel(projection):
    """Both references' shells, without any surfel, leave no pixel see-through from a pose off the baseline."""
    g, ranges, poses = _scene(opacity=0.3)
    shell = environment_shell(g, ranges, poses, ("yin", "yang"))
    target = pose_at([0.4, 0.2, 0.0])
    size = {"erp": dict(width=96), "perspective": dict(width=160, height=120, fov_deg=100.0)}[projection]
    alpha = render(shell, target, projection=projection, **size).alpha
    assert alpha.min() >= 0.98


def test_compaction_passes_the_shell_through():
    g, ranges, poses = _scene(opacity=0.9)
    shell = environment_shell(g, ranges, poses, ("yin", "yang"))
    both = Gaussians.concatenate([g, shell])
    prov = Provenance(("yin", "yang"), H, W, poses, shell=len(shell))
    res = compact_result(both, prov, CompactionOptions())
    assert res.stats["input"] == len(both) and res.stats["output"] == len(res.gaussians)
    assert res.stats["shell"] == len(shell) and len(res.gaussians) < len(both)  # the surfels were compacted
    tail = res.gaussians.subset(np.arange(len(res.gaussians) - len(shell), len(res.gaussians)))
    np.testing.assert_array_equal(tail.means, shell.means)
    index, block = shell_layout(2, 2, H, W)
    np.testing.assert_array_equal(res.provenance.index[-len(shell):], index)
    np.testing.assert_array_equal(res.block[-len(shell):], block)
    with pytest.raises(CompactionError, match="shell of"):
        compact_result(both, Provenance(("yin", "yang"), H, W, poses, shell=len(shell) + 4), CompactionOptions())


def test_the_shell_comes_after_the_compacted_surfels_as_they_are():
    """The output is the surfels' own compaction, then the shell (its missing SH bands zero), field by field."""
    g, ranges, poses = _scene(opacity=0.9)
    sh = np.random.default_rng(2).normal(0.0, 0.3, (len(g), 4, 3))  # view-dependent colour
    sh[:, 0] = g.sh[:, 0]
    g = g.with_(sh=sh)
    shell = environment_shell(g, ranges, poses, ("yin", "yang"))
    assert shell.sh.shape[1] == 1
    res = compact_result(Gaussians.concatenate([g, shell]), Provenance(("yin", "yang"), H, W, poses, shell=len(shell)),
                         CompactionOptions())
    front = compact_result(g, Provenance(("yin", "yang"), H, W, poses), CompactionOptions())
    assert front.stats["merge_smooth"]["added"] > 0  # merged blocks interleaved with the kept surfels
    want = Gaussians.concatenate([front.gaussians, shell])
    for f in ("means", "scales", "quats", "opacities", "sh"):
        np.testing.assert_array_equal(getattr(res.gaussians, f), getattr(want, f), err_msg=f)
    np.testing.assert_array_equal(res.block[:len(front.block)], front.block)
    assert res.stats["output"] == len(res.gaussians) == len(front.gaussians) + len(shell)


@pytest.mark.parametrize("cap", [100, 10, 0])
def test_cap_and_opacity_cut_count_the_shell(cap):
    g, ranges, poses = _scene(opacity=0.9)
    shell = environment_shell(g, ranges, poses, ("yin", "yang"))
    both = Gaussians.concatenate([g, shell])
    prov = Provenance(("yin", "yang"), H, W, poses, shell=len(shell))
    res = compact_result(both, prov, CompactionOptions(max_count=cap))
    assert len(res.gaussians) == res.stats["output"] == cap
    assert sum(res.stats["removed"].values()) == len(both) - cap
    assert res.block.shape == res.provenance.index.shape == (cap,)
    # an opacity cut above the shell's opacity drops it like any other Gaussian
    cut = compact_result(both, prov, CompactionOptions(min_opacity=0.995))
    assert len(cut.gaussians) == 0 and cut.stats["removed"]["min_opacity"] == len(both)
