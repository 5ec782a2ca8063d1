"""`omnisplat-bench quality --short` end to end on one dev scene (the command must not rot)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bench import quality as bench_quality  # noqa: E402


@pytest.fixture(scope="session")
def bench_models_dir(tmp_path_factory):
    """Shared by the bench tests so each small model is exported once per session."""
    path = tmp_path_factory.getbasetemp() / "bench_models"
    path.mkdir(exist_ok=True)
    return path


def test_short_quality_bench_writes_json_table_plot(tmp_path, m3d_dir, bench_models_dir):
    out = tmp_path / "bench"
    rc = bench_quality.main(["--data", str(m3d_dir), "--short", "--out", str(out), "--models-dir", str(bench_models_dir)])
    assert rc == 0
    data = json.loads((out / "quality.json").read_text())
    assert data["machine"]["cpu_model"] and data["machine"]["onnxruntime"]
    recs = {r["setting"]: r for r in data["records"]}
    assert set(recs) == {"64x128_p16_d1_yyenc_yinyang", "copy"}
    model = recs["64x128_p16_d1_yyenc_yinyang"]
    assert model["finite"] and model["num_gaussians"] > 0
    # A real reconstruction of the bedroom is far better than noise (~8 dB) and near or above the copy baseline.
    assert 12.0 < model["psnr"] < 60.0 and -1.0 <= model["ssim"] <= 1.0 and np.isfinite(model["ws_psnr"])
    assert model["psnr"] > recs["copy"]["psnr"] - 2.0
    assert all(model["seconds"][k] > 0 for k in ("decode", "encoder", "render"))
    md = (out / "quality.md").read_text()
    assert "| 64x128, 16 planes, features /1, YY encoder, Yin-Yang rasterizer, plain |" in md and data["machine"]["numpy"] in md
    assert (out / "quality_psnr_vs_seconds.png").read_bytes()[:4] == b"\x89PNG"
    shares = model["opacity_shares"]
    assert len(shares) == len(bench_quality.OPACITY_BINS) - 1 and sum(shares) == pytest.approx(1.0)
    assert "| 64x128_p16_d1_yyenc_yinyang | m3d_bedroom | 00+02 |" in md


def test_opacity_shares_bins_every_opacity_once():
    shares = bench_quality.opacity_shares(np.array([0.0, 0.05, 0.35, 0.35, 0.95, 1.0]))
    assert shares == pytest.approx([2 / 6, 0, 0, 2 / 6, 0, 0, 0, 0, 0, 2 / 6])
    assert bench_quality.opacity_shares(np.array([])) == [0.0] * 10


def test_quality_rejects_non_scene_folder(tmp_path):
    with pytest.raises(SystemExit):
        bench_quality.main(["--data", str(tmp_path), "--short", "--out", str(tmp_path / "o")])


def test_oracle_is_the_service_path_on_gt_depth(m3d_dir):
    """The GT-depth oracle: one surfel per ERP pixel (holes filled), degree-1 colour, then the shell."""
    from rasterizer.depth_gaussians import gaussians_from_depth
    from rasterizer.render import render
    from rasterizer.scene_folder import load_scene
    from rasterizer.yin_yang import resize_erp

    scene = load_scene(m3d_dir)
    frames = [scene.frames[n] for n in ("00", "02")]
    refs = [(resize_erp(f.image(), 64, 128), f.c2w) for f in frames]
    depths = [resize_erp(f.depth(), 64, 128) for f in frames]
    depths[0][0, :5] = 0.0  # a hole in the scan
    g = bench_quality.oracle_gaussians(gaussians_from_depth, refs, depths)
    g.check_finite()
    n = 2 * 64 * 128
    assert len(g) == n + 2 * (64 // 4) * (128 // 4) and g.sh.shape[1:] == (4, 3)
    assert np.all(g.opacities[n:] >= 0.99) and np.all(g.sh[n:, 1:] == 0)
    shell_range = np.linalg.norm(g.means[n: n + (len(g) - n) // 2] - frames[0].c2w[:3, 3], axis=1)  # view A's
    assert shell_range.min() > max(d.max() for d in depths)
    # at a reference the oracle shows that reference's image
    out = render(g, frames[0].c2w, projection="erp", width=128, method="direct")
    err = np.abs(out.colour - refs[0][0]).mean()
    assert err < 0.05 and (out.alpha >= 0.99).mean() > 0.99


def test_sharpness_and_gmsd_follow_conventions():
    from bench import metrics

    rng = np.random.default_rng(0)
    target = rng.random((32, 64, 3))
    assert metrics.sharpness(target, target) == pytest.approx(1.0)
    assert metrics.gmsd(target, target) == pytest.approx(0.0, abs=1e-12)
    y = metrics.luma(target)
    blurred = np.repeat(metrics.box5_erp(y)[..., None], 3, axis=-1)
    assert metrics.sharpness(blurred, target) < 0.5  # a 5x5 blur keeps little of white noise's detail
    assert metrics.gmsd(blurred, target) > 0.05
    flat = np.full_like(target, 0.5)
    assert metrics.sharpness(flat, target) == pytest.approx(0.0, abs=1e-12)
    # box5 wraps in longitude: a column at the seam spreads to both edges; clamped in latitude
    impulse = np.zeros((8, 16))
    impulse[4, 0] = 25.0
    box = metrics.box5_erp(impulse)
    assert box[4, 15] == pytest.approx(1.0) and box[4, 14] == pytest.approx(1.0) and box[4, 3] == 0.0
    top = np.zeros((8, 16))
    top[0, 5] = 25.0
    assert metrics.box5_erp(top)[0, 5] == pytest.approx(3.0)  # the top row counted three times (clamped)
    # only rows above -75 deg count: a difference at the nadir leaves sharpness and GMSD unchanged
    nadir = target.copy()
    nadir[-1:] = 0.0  # rows 29-31 of 32 are cut; box5 reaches two rows
    assert metrics.sharpness(nadir, target) == pytest.approx(1.0)
    assert metrics.gmsd(nadir, target) == pytest.approx(0.0, abs=1e-12)
    scores = metrics.real_capture_scores(blurred, target)
    assert set(scores) == {"psnr_above_nadir", "psnr", "ws_psnr", "sharpness", "gmsd"}


def test_copy_floor_of_the_reference_itself_is_perfect():
    rng = np.random.default_rng(1)
    img = rng.random((16, 32, 3)).astype(np.float32)
    pose = np.eye(4)
    other = np.eye(4)
    other[0, 3] = 1.0
    floor = bench_quality.copy_floor([(img, pose), (img[::-1].copy(), other)], pose, img)
    assert floor["psnr_above_nadir"] > 60 and floor["sharpness"] == pytest.approx(1.0, abs=1e-3)
