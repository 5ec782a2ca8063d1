"""Bench framework pieces that need no encoder or renderer: settings, aggregation, reports,
the copy baseline, the synthetic scenes, machine info."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bench.baselines import copy_nearest, rotate_erp
from bench.machine import machine_info, machine_line
from bench.quality import is_extrapolation, resize_erp_box
from bench.report import aggregate, markdown, plot, write_json
from bench.settings import Setting, full_grid, parse_setting, short_grid
from bench.synthetic import SyntheticScene, camera, random_rotation, similarity
from rasterizer.geometry import grid_directions, project_to_grid
from rasterizer.scene_folder import load_scene

# -- settings ------------------------------------------------------------------

def test_full_grid_covers_resolutions_planes_ablation_oracle_copy():
    grid = full_grid()
    models = [s for s in grid if s.kind == "model"]
    assert {(s.height, s.planes) for s in models if not s.erp_encoder and s.rasterizer == "yinyang"
            and s.downscale is None} == {(h, p) for h in (256, 512) for p in (32, 64, 128)}
    ablation = {(s.erp_encoder, s.rasterizer) for s in models if (s.height, s.planes) == (256, 64)}
    assert ablation == {(False, "yinyang"), (False, "direct"), (True, "yinyang"), (True, "direct")}
    assert [s.kind for s in grid[-2:]] == ["oracle", "copy"]
    assert len({s.slug for s in grid}) == len(grid)
    assert len({s.model_key for s in models}) == 8  # 6 YY models, the quality preset, the ERP-encoder one


@pytest.mark.parametrize("setting", full_grid() + short_grid())
def test_parse_setting_round_trips(setting):
    if setting.kind == "model":
        text = f"{setting.height}x{setting.width}:{setting.planes}:{'erp' if setting.erp_encoder else 'yy'}:{setting.rasterizer}"
        if setting.downscale is not None:
            text += f":d{setting.downscale}"
    else:
        text = setting.kind if setting.kind == "copy" else f"oracle:{setting.rasterizer}"
    assert parse_setting(text) == setting


def test_parse_setting_rig_layer():
    s = parse_setting("512x1024:64:yy:yinyang:rig")
    assert s.rig and s == Setting("model", 512, 1024, 64, rig=True)
    assert parse_setting("256x512:64:yy:direct:d2:rig") == Setting("model", 256, 512, 64, False, "direct", 2, True)
    assert s.slug.endswith("_rig") and s.name.endswith("capture rig layer")
    assert s.model_key == parse_setting("512x1024:64").model_key  # the same ONNX model
    assert not parse_setting("512x1024:64").rig


@pytest.mark.parametrize("bad", ["256x500:64", "256x512", "256x512:64:foo", "256x512:64:yy:raytrace", "oracle:foo",
                                 "256x512:64:yy:yinyang:x", "256x512:64:yy:yinyang:rig:rig"])
def test_parse_setting_rejects_bad_text(bad):
    with pytest.raises(ValueError):
        parse_setting(bad)


# -- aggregation and reports ------------------------------------------------------

def _rec(setting, group, psnr, extra=False, total=1.0):
    return {"setting": setting, "setting_name": setting, "group": group, "extrapolation": extra,
            "psnr": psnr, "ssim": psnr / 100, "ws_psnr": psnr - 1,
            "seconds": {"decode": 0.1 * total, "encoder": 0.5 * total, "gaussian_head": 0.1 * total, "render": 0.3 * total}}


def test_aggregate_is_mean_over_targets_then_unweighted_over_scenes():
    recs = [_rec("s", "a", 10.0), _rec("s", "a", 20.0), _rec("s", "a", 30.0), _rec("s", "b", 40.0),
            _rec("s", "b (extrapolation)", 0.0, extra=True)]
    (summary,) = aggregate(recs)
    assert summary["per_group"]["a"]["psnr"] == pytest.approx(20.0)
    assert summary["mean"]["psnr"] == pytest.approx(30.0)  # (20 + 40) / 2, not (10+20+30+40)/4 = 25
    assert summary["mean"]["groups"] == 2
    assert summary["extrapolation"]["psnr"] == pytest.approx(0.0)
    assert summary["mean"]["seconds"]["total"] == pytest.approx(1.0)
    assert summary["mean"]["seconds"]["encoder"] == pytest.approx(0.5)


def test_report_writers(tmp_path):
    recs = [_rec("fast", "a", 20.0, total=0.5), _rec("slow", "a", 24.0, total=5.0), _rec("copy", "a", 14.0, total=0.1)]
    summary = aggregate(recs)
    md = markdown(summary, "test machine", ["note one"])
    rows = [line for line in md.splitlines() if line.startswith("| fast") or line.startswith("| slow")]
    assert len(rows) == 4  # main table + per-group table
    assert "20.00" in rows[0] and "test machine" in md and "note one" in md
    png = plot(summary, tmp_path / "p.png", "test machine")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    path = write_json(tmp_path / "q.json", {"summary": summary, "bad": float("nan"), "arr": [np.float32(1.5)]})
    data = json.loads(path.read_text())
    assert data["bad"] is None and data["arr"] == [1.5]


def test_machine_info_names_cpu_cores_and_versions():
    info = machine_info()
    assert info["logical_cores"] >= 1 and info["cpu_model"]
    for key in ("python", "numpy", "onnxruntime"):
        assert info[key] and info[key] != "absent"
    assert info["numpy"] in machine_line(info)


# -- copy baseline -------------------------------------------------------------------

def test_rotate_erp_identity_and_quarter_turn():
    rng = np.random.default_rng(0)
    img = rng.random((16, 32, 3)).astype(np.float32)
    same = rotate_erp(img, np.eye(4), np.eye(4), 16, 32)
    np.testing.assert_allclose(same, img, atol=1e-5)
    # Destination turned +90 deg about the camera y axis (down): its forward is the source's +x or -x.
    rot = np.eye(4)
    c, s = np.cos(np.pi / 2), np.sin(np.pi / 2)
    rot[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    turned = rotate_erp(img, np.eye(4), rot, 16, 32)
    shift = [np.abs(turned - np.roll(img, k, axis=1)).max() for k in (8, -8)]
    assert min(shift) < 1e-5


def test_copy_nearest_picks_the_closer_reference():
    a = np.zeros((8, 16, 3), np.float32)
    b = np.ones((8, 16, 3), np.float32)
    pred = copy_nearest([(a, camera([0, 0, 0])), (b, camera([1, 0, 0]))], camera([0.9, 0, 0]), 8, 16)
    assert np.all(pred == 1.0)


def test_resize_erp_box_keeps_mean():
    img = np.random.default_rng(1).random((32, 64, 3)).astype(np.float32)
    small = resize_erp_box(img, 16)
    assert small.shape == (8, 16, 3)
    assert abs(small.mean() - img.mean()) < 0.01


# -- extrapolation split detection on the dev data ------------------------------------

def test_zind_second_split_is_extrapolation(zind_dir, m3d_dir):
    zind = load_scene(zind_dir)
    assert [is_extrapolation(zind, s, i) for i, s in enumerate(zind.splits)] == [False, True]
    m3d = load_scene(m3d_dir)
    assert not is_extrapolation(m3d, m3d.splits[0], 0)


# -- synthetic scenes ------------------------------------------------------------------

def test_synthetic_views_are_consistent():
    """A point seen by camera A at its range has the same colour when camera B looks at it."""
    scene = SyntheticScene()
    c2w_a, c2w_b = camera([-0.25, 0, 0]), camera([0.25, 0.1, 0.0], random_rotation(np.random.default_rng(5)))
    h, w = 32, 64
    rgb_a, rng_a = scene.render(c2w_a, h, w, supersample=1)
    pts = grid_directions("erp", h, w) * rng_a[..., None] + c2w_a[:3, 3]
    cam_b = (pts - c2w_b[:3, 3]) @ c2w_b[:3, :3]
    dist_b = np.linalg.norm(cam_b, axis=-1)
    col, row = project_to_grid("erp", cam_b, h, w)
    # Re-cast the exact rays from B to those points: same range (not occluded) -> same colour.
    dirs_b = (cam_b / dist_b[..., None]).reshape(-1, 3) @ c2w_b[:3, :3].T
    t, hit, prim = scene.cast(c2w_b[:3, 3], dirs_b)
    visible = np.abs(t - dist_b.reshape(-1)) < 1e-6
    assert visible.mean() > 0.5
    colour_b = scene.shade(hit, prim)
    np.testing.assert_allclose(colour_b[visible], rgb_a.reshape(-1, 3)[visible], atol=1e-5)
    assert np.all(np.isfinite(col)) and np.all(np.isfinite(row))


def test_synthetic_range_and_texture_modes():
    scene = SyntheticScene()
    rgb, rng = scene.render(camera([0, 0, 0]), 32, 64)
    assert rgb.shape == (32, 64, 3) and rng.shape == (32, 64)
    assert np.all(rng > 0.1) and np.all(rng < 6.0) and 0.0 <= rgb.min() and rgb.max() <= 1.0
    assert rgb.std() > 0.1
    flat, _ = scene.with_(texture="flat").render(camera([0, 0, 0]), 32, 64)
    assert np.allclose(flat, 0.5)
    poles, _ = scene.with_(texture="poles").render(camera([0, 0, 0]), 32, 64)
    assert poles[12:20].std() < 1e-6 and poles[:3].std() > 0.05  # textured only near the poles
    seam, _ = scene.with_(texture="seam").render(camera([0, 0, 0]), 32, 64)
    assert seam[:, 24:40].std() < 1e-6 and seam[12:20, :3].std() > 0.05  # textured only across the seam
    with pytest.raises(ValueError, match="outside the room"):
        scene.render(camera([10, 0, 0]), 8, 16)


def test_similarity_moves_poses_rigidly():
    rot = random_rotation(np.random.default_rng(2))
    assert np.allclose(rot @ rot.T, np.eye(3)) and np.linalg.det(rot) == pytest.approx(1.0)
    a, b = camera([1, 2, 3]), camera([-1, 0, 2])
    a2, b2 = similarity(a, rot, 10.0), similarity(b, rot, 10.0)
    assert np.linalg.norm(a2[:3, 3] - b2[:3, 3]) == pytest.approx(10 * np.linalg.norm(a[:3, 3] - b[:3, 3]))
    rel = np.linalg.inv(a) @ b
    rel2 = np.linalg.inv(a2) @ b2
    np.testing.assert_allclose(rel2[:3, :3], rel[:3, :3], atol=1e-12)


# -- stability checks themselves -------------------------------------------------------------

def test_stability_checks_catch_nan_and_bad_alpha():
    from types import SimpleNamespace

    from bench.stability import constant_psnr, reconstruction_problems, render_problems
    from rasterizer.gaussians import Gaussians

    n = 4
    good = Gaussians(np.zeros((n, 3)), np.full((n, 3), 0.1), np.tile([1.0, 0, 0, 0], (n, 1)), np.full(n, 0.5),
                     np.zeros((n, 1, 3)))
    ok = SimpleNamespace(gaussians=good, range_maps=np.ones((2, 1, 2, 2)), confidence=np.ones((2, 1, 2, 2)))
    assert reconstruction_problems(ok) == []
    means = good.means.copy()
    means[1, 2] = np.nan
    bad = SimpleNamespace(gaussians=good.with_(means=means), range_maps=np.full((2, 1, 2, 2), np.inf),
                          confidence=np.ones((2, 1, 2, 2)))
    assert reconstruction_problems(bad) == ["gaussians.means not finite", "range_maps not finite"]
    img = np.full((4, 8, 3), 0.5, np.float32)
    assert render_problems(SimpleNamespace(colour=img, alpha=np.ones((4, 8)), range=np.ones((4, 8)))) == []
    alpha = np.ones((4, 8))
    alpha[0, 0] = 1.5
    assert render_problems(SimpleNamespace(colour=img, alpha=alpha, range=np.ones((4, 8)))) == [
        "render alpha outside [0, 1]"]
    two = np.concatenate([np.zeros((2, 8, 3)), np.ones((2, 8, 3))]).astype(np.float32)
    assert constant_psnr(two) == pytest.approx(-10 * np.log10(0.25))  # best constant 0.5, MSE 0.25


def test_alpha_normalised_divides_covered_pixels_only():
    from bench.quality import alpha_normalised

    colour = np.array([[[0.25, 0.5, 0.0], [0.001, 0.001, 0.001]]], np.float32)
    alpha = np.array([[0.5, 0.001]], np.float32)
    out = alpha_normalised(colour, alpha)
    np.testing.assert_allclose(out[0, 0], [0.5, 1.0, 0.0])
    assert np.all(out[0, 1] == 0.0)  # alpha below 1/255: empty, not amplified noise


def test_readme_block_replaces_only_the_marked_section(tmp_path):
    from bench.report import README_END, README_START, readme_block, update_readme

    report = ("# Quality\n\nMachine: m\n\n## Mean over scenes (extrapolation splits excluded)\n\n"
              "| setting | PSNR |\n|---|---|\n| a | 20.00 |\n\n## Per scene group\n\n| x |\n")
    block = readme_block(report, "m", "docs/bench/q.png", "docs/bench/q.md")
    assert "| a | 20.00 |" in block and "Per scene group" not in block and "docs/bench/q.png" in block
    readme = tmp_path / "README.md"
    readme.write_text(f"# top\n\n{README_START}\nold table\n{README_END}\n\n## after\n")
    assert update_readme(readme, block)
    text = readme.read_text()
    assert "old table" not in text and "| a | 20.00 |" in text
    assert text.startswith("# top") and text.rstrip().endswith("## after") and text.count(README_END) == 1
    plain = tmp_path / "PLAIN.md"
    plain.write_text("no markers\n")
    assert not update_readme(plain, block) and plain.read_text() == "no markers\n"


def test_compaction_readme_block_keeps_the_quality_block(tmp_path):
    from bench.compaction import readme_block
    from bench.report import README_START, readme_markers, update_readme

    def variant(count, psnr, render_s, contrib):
        t = {"count": count, "ply_bytes": count * 68, "render_s": render_s, "psnr": psnr, "contributions": contrib}
        return {"targets": {"t0": t}, "compact_s": 0.1}

    results = {"model": "m", "num_planes": 64, "render": "ERP 1024x512 via Yin-Yang", "load_avg_start": (1.0,),
               "load_avg_end": (1.5,), "splits": [{"scene": "s", "references": ["a", "b"], "sources": {"encoder": {
                   "variants": {"none": variant(1000, 20.0, 2.0, 100), "smooth": variant(800, 19.9, 1.6, 80),
                                "all": variant(500, 19.85, 1.0, 60), "cap60": variant(600, 15.0, 1.0, 50)}}}}]}
    block = readme_block(results, "docs/bench/compaction.md")
    start, end = readme_markers("compaction")
    assert block.startswith(start) and block.endswith(end)
    assert "| s a+b | encoder | default (smooth merge) | 500 | 50.0 | 40.0 | 1.0 | 50.0 | -0.150 (-0.150) | 0.1 |" in block
    assert "cap60" not in block
    readme = tmp_path / "README.md"
    readme.write_text(f"{README_START}\nquality\n<!-- bench:quality:end -->\n\n{start}\nold\n{end}\n")
    assert update_readme(readme, block, "compaction")
    text = readme.read_text()
    assert "quality\n" in text and "old" not in text and text.count(end) == 1


# -- the omnisplat-bench entry point ----------------------------------------------

def test_bench_entry_point_dispatches_to_the_module_main(monkeypatch):
    import sys

    from bench.__main__ import main

    seen = {}

    class Fake:
        @staticmethod
        def main(argv):
            seen["argv"] = argv
            return 3

    monkeypatch.setitem(sys.modules, "bench.render", Fake)
    assert main(["render", "--json", "--x", "1"]) == 3
    assert seen["argv"] == ["--json", "--x", "1"]


@pytest.mark.parametrize("argv, code", [(["nonsense"], 2), ([], 2), (["--help"], 0)])
def test_bench_entry_point_usage(argv, code, capsys):
    from bench.__main__ import main

    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == code
    captured = capsys.readouterr()
    assert "omnisplat-bench" in captured.out + captured.err


def test_every_bench_command_is_a_module_with_main():
    import ast
    from pathlib import Path

    from bench.__main__ import COMMANDS

    root = Path(__file__).resolve().parents[2]
    for name, (module, help_text) in COMMANDS.items():
        path = root / Path(*module.split(".")).with_suffix(".py")
        tree = ast.parse(path.read_text())
        assert any(isinstance(n, ast.FunctionDef) and n.name == "main" for n in tree.body), module
        assert help_text
    with_main = {p.stem for p in (root / "bench").glob("*.py") if p.stem != "__main__" and
                 any(isinstance(n, ast.FunctionDef) and n.name == "main" for n in ast.parse(p.read_text()).body)}
    assert with_main == set(COMMANDS)  # every benchmark is listed once
