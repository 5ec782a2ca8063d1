"""service.encoder.OnnxEncoder: metadata, reconstruction on dev data, input errors, no torch."""

import subprocess
import sys

import numpy as np
import pytest

from export.onnx_export import export_model
from rasterizer.colour_fit import COLOUR_FIT_STRENGTH
from rasterizer.geometry import grid_directions, project_to_grid
from rasterizer.rig import rig_mask
from rasterizer.scene_folder import load_scene
from rasterizer.sh import sh_to_rgb
from rasterizer.shell import shell_radius
from service.encoder import EncoderInputError, OnnxEncoder


@pytest.fixture(scope="module")
def encoder(tmp_path_factory):
    path = export_model(tmp_path_factory.mktemp("enc") / "small.onnx", height=128, width=256, num_planes=16)
    return OnnxEncoder(path, threads=2)


@pytest.fixture(scope="module")
def m3d(m3d_dir):
    scene = load_scene(m3d_dir)
    return scene.frames["00"], scene.frames["02"]


def test_metadata(encoder):
    meta = encoder.metadata
    assert len(meta["sha256"]) == 64
    assert meta["input_height"] == "128" and meta["num_planes"] == "16"
    assert meta["settings"]["num_planes"] == 16
    assert encoder.feature_size == (16, 48)


def test_reconstruct_m3d_depth_is_metric(encoder, m3d):
    fa, fb = m3d
    rec = encoder.reconstruct(fa.image(), fb.image(), fa.c2w, fb.c2w)
    g = rec.gaussians
    shell_block = 4  # rasterizer.shell: one shell disc per 4x4 pixels of each grid
    assert rec.shell == rec.info["num_gaussians_shell"] == 2 * 2 * (64 // shell_block) * (192 // shell_block)
    assert len(g) == 2 * 2 * 64 * 192 + rec.shell
    g.check_finite()
    assert set(rec.timings) >= {"resample", "sweep_inputs", "onnx", "gaussians", "total"}
    assert rec.info["baseline"] == pytest.approx(1.0)
    assert rec.range_maps.shape == rec.confidence.shape == (2, 2, 64, 192)
    assert 0.0 <= rec.confidence.min() and rec.confidence.max() <= 1.0
    # Yin range map of view A against GT at the same directions (nearest ERP pixel)
    gt = fa.depth()
    col, row = project_to_grid("erp", grid_directions("yin", 64, 192), *gt.shape)
    gt_yin = gt[np.clip(np.round(row).astype(int), 0, gt.shape[0] - 1), np.round(col).astype(int) % gt.shape[1]]
    ok = gt_yin > 0
    rel = np.abs(rec.range_maps[0, 0][ok] - gt_yin[ok]) / gt_yin[ok]
    assert np.median(rel) < 0.2
    # means are range x ray from the camera centre
    d = np.linalg.norm(g.means[: 64 * 192] - fa.c2w[:3, 3], axis=1)
    np.testing.assert_allclose(d, rec.range_maps[0, 0].ravel(), rtol=1e-4)
    # the shell: opaque, on a sphere around its camera beyond the estimated ranges (view A's Yin blocks first)
    shell = g.subset(np.arange(len(g) - rec.shell, len(g)))
    assert shell.opacities.min() >= 0.99
    d_shell = np.linalg.norm(shell.means[: 16 * 48] - fa.c2w[:3, 3], axis=1)
    np.testing.assert_allclose(d_shell, rec.info["shell_radius"], rtol=1e-4)
    assert rec.info["shell_radius"] == shell_radius(rec.range_maps)
    assert shell_radius(rec.range_maps) > np.percentile(rec.range_maps, 99)
    # view-dependent colour (default sh_degree 1): each reference sees its own pixel colours
    assert g.sh.shape == (len(g), 4, 3) and np.all(shell.sh[:, 1:] == 0) and rec.info["sh_degree"] == 1
    one = encoder.reconstruct(fa.image(), fb.image(), fa.c2w, fb.c2w, sh_degree=0).gaussians
    assert one.sh.shape == (len(g), 1, 3)
    n = 2 * 64 * 192
    for v, c2w in enumerate((fa.c2w, fb.c2w)):
        own = slice(v * n, (v + 1) * n)
        np.testing.assert_allclose(sh_to_rgb(g.sh[own], g.means[own], c2w[:3, 3]),
                                   sh_to_rgb(one.sh[own], one.means[own], c2w[:3, 3]), atol=1e-4)
    # the colour-fit step (rasterizer.colour_fit) moves colours only: geometry, opacity and count stay
    plain = encoder.reconstruct(fa.image(), fb.image(), fa.c2w, fb.c2w, sh_degree=0, colour_fit=0).gaussians
    assert rec.info["colour_fit"] == COLOUR_FIT_STRENGTH > 0
    np.testing.assert_array_equal(plain.means, one.means)
    np.testing.assert_array_equal(plain.opacities, one.opacities)
    assert np.abs(plain.sh[:2 * n] - one.sh[:2 * n]).max() > 0.05
    with pytest.raises(EncoderInputError, match="colour_fit"):
        encoder.reconstruct(fa.image(), fb.image(), fa.c2w, fb.c2w, colour_fit=-1)
    # the rig cap re-colours only pixels near each camera's nadir; geometry and count stay
    capped = encoder.reconstruct(fa.image(), fb.image(), fa.c2w, fb.c2w, sh_degree=0, rig_cap_deg=20.0,
                                 colour_fit=0)
    assert capped.info["rig_cap_deg"] == 20.0 and rec.info["rig_cap_deg"] == 0.0
    c = capped.gaussians
    np.testing.assert_array_equal(c.means, plain.means)
    changed = np.any(c.sh[:2 * n] != plain.sh[:2 * n], axis=(1, 2))  # both views, shell excluded
    near_nadir = np.tile(rig_mask(("yin", "yang"), 64, 192, 20.0).ravel(), 2)
    assert changed.any() and not changed[~near_nadir].any()


def test_any_2to1_size_and_dtype(encoder, m3d):
    fa, fb = m3d
    a8 = (fa.image() * 255).round().astype(np.uint8)
    small_b = fb.image()[::2, ::2]  # 256 x 512
    r1 = encoder.reconstruct(a8, small_b, fa.c2w, fb.c2w)
    r2 = encoder.reconstruct(a8.astype(np.float32) / 255, small_b, fa.c2w, fb.c2w)
    # uint8 is scaled after the resample, float before it: inputs equal to ~1e-7, which the small
    # model's untrained weights amplify to ~1e-4 in its ranges
    np.testing.assert_allclose(r1.range_maps, r2.range_maps, rtol=1e-3)


def test_near_far_override_and_pruning(encoder, m3d):
    fa, fb = m3d
    cut = 0.5  # opacities are 0.3 + 0.69 confidence^2 (export/config.py): drops the unconfident ones
    rec = encoder.reconstruct(fa.image(), fb.image(), fa.c2w, fb.c2w, near=1.0, far=5.0, min_opacity=cut)
    assert rec.info["near"] == 1.0 and rec.info["far"] == 5.0
    assert rec.range_maps.min() >= 1.0 - 1e-4 and rec.range_maps.max() <= 5.0 + 1e-3
    assert len(rec.gaussians) - rec.shell < rec.info["num_gaussians_raw"]
    assert rec.gaussians.opacities.min() >= cut  # the shell (0.99) is kept whole


@pytest.mark.parametrize("bad, match", [
    (dict(erp_a=np.zeros((100, 300, 3), np.float32)), "width = 2 x height"),
    (dict(erp_a=np.full((64, 128, 3), np.nan, np.float32)), "NaN"),
    (dict(erp_a=np.zeros((64, 128), np.float32)), "RGB"),
    (dict(erp_a=np.full((64, 128, 3), 7.0, np.float32)), r"\[0, 1\]"),
    (dict(c2w_b=np.eye(4)), "coincide"),
    (dict(c2w_b=np.diag([1.0, 1.0, -1.0, 1.0])), "mirror"),
    (dict(near=5.0, far=1.0), "near < far"),
    (dict(colour_mode="x"), "unknown encoder option"),
    (dict(sh_degree=2), "sh_degree"),
    (dict(sh_degree=True), "sh_degree"),
    (dict(rig_cap_deg=-1.0), "rig_cap_deg"),
    (dict(rig_cap_deg=60.0), "rig_cap_deg"),
    (dict(rig_cap_deg=float("nan")), "rig_cap_deg"),
])
def test_bad_inputs_raise_clear_errors(encoder, bad, match):
    args = dict(erp_a=np.zeros((64, 128, 3), np.float32), erp_b=np.zeros((64, 128, 3), np.float32),
                c2w_a=np.eye(4), c2w_b=np.diag([1.0, 1.0, 1.0, 1.0]))
    args["c2w_b"][2, 3] = 1.0
    args.update(bad)
    with pytest.raises(EncoderInputError, match=match):
        encoder.reconstruct(args.pop("erp_a"), args.pop("erp_b"), args.pop("c2w_a"), args.pop("c2w_b"), **args)
    assert issubclass(EncoderInputError, ValueError)


def test_runtime_never_imports_torch():
    code = "import sys, service.encoder, rasterizer.sweep; assert 'torch' not in sys.modules; assert 'export' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True, cwd=str(__import__("pathlib").Path(__file__).parents[2]))
