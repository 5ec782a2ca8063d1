"""`omnisplat bench quality --short` end to end on one dev scene (the command must not rot)."""

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


def test_quality_rejects_non_scene_folder(tmp_path):
    with pytest.raises(SystemExit):
        bench_quality.main(["--data", str(tmp_path), "--short", "--out", str(tmp_path / "o")])
