"""The `omnisplat` command line: help, argument errors, dispatch to other modules."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rasterizer.ply import read_ply, write_ply
from service import cli
from service.cli import export as cli_export
from service.cli.reconstruct import pipeline_options
from service.model_files import default_model_name
from tests.service._support import panorama, ply_with_nan, render_argv

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(autouse=True)
def _any_port(monkeypatch):
    """`serve` checks its port before anything else: these tests of its other checks must not depend on what else
    listens on the default port 8000 of the machine (port 0: any free one, not checked)."""
    monkeypatch.setenv("OMNISPLAT_PORT", "0")


def test_help_lists_every_command(capsys):
    with pytest.raises(SystemExit) as info:
        cli.main(["--help"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    for command in ("serve", "reconstruct", "render", "export", "refine", "select", "edit"):
        assert command in out
    assert "bench" not in out  # benchmarks have their own entry point (omnisplat-bench)
    assert "OpenCV" in out


@pytest.mark.parametrize("command", ["serve", "reconstruct", "render", "export", "refine", "select", "edit"])
def test_subcommand_help(command, capsys):
    with pytest.raises(SystemExit) as info:
        cli.main([command, "--help"])
    assert info.value.code == 0
    assert "usage: omnisplat" in capsys.readouterr().out


def test_help_does_not_import_heavy_modules():
    code = ("import sys; from service import cli; "
            "import contextlib, io\n"
            "with contextlib.redirect_stdout(io.StringIO()):\n"
            "    try: cli.main(['--help'])\n"
            "    except SystemExit: pass\n"
            "bad = [m for m in ('torch', 'onnxruntime', 'fastapi', 'uvicorn') if m in sys.modules]\n"
            "print(bad); sys.exit(1 if bad else 0)")
    run = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stdout + run.stderr


def test_service_imports_no_torch():
    code = ("import sys, service.app, service.cli, service.store, service.scenes; "
            "sys.exit(1 if 'torch' in sys.modules else 0)")
    run = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr


def test_missing_command_is_an_error(capsys):
    with pytest.raises(SystemExit) as info:
        cli.main([])
    assert info.value.code == 2


def test_bench_is_not_a_service_command(capsys):
    with pytest.raises(SystemExit) as info:
        cli.main(["bench", "render"])
    assert info.value.code == 2
    assert "invalid choice" in capsys.readouterr().err


def test_export_without_torch_is_a_clear_error(monkeypatch, tmp_path, capsys):
    def load():
        raise ModuleNotFoundError("No module named 'torch'", name="torch")

    monkeypatch.setattr(cli_export, "load_export_model", load)
    assert cli.main(["export", str(tmp_path / "m.onnx")]) == 2
    err = capsys.readouterr().err
    assert "not available" in err and "'torch'" in err and "export extra" in err
    assert not (tmp_path / "m.onnx").exists()


@pytest.mark.parametrize("failure, status", [(KeyboardInterrupt, 130), (ValueError("bad size"), 2)])
def test_export_that_stops_half_way_leaves_no_partial_model(monkeypatch, tmp_path, capsys, failure, status):
    """The exporter writes its output as it goes (torch's graph, then the weights inlined): a build that
    failed or was interrupted left that half-written file at the path, over an earlier model."""
    def half_then_fail(path, **kw):
        Path(path).write_bytes(b"half a model")
        raise failure

    monkeypatch.setattr(cli_export, "load_export_model", lambda: half_then_fail)
    (tmp_path / "m.onnx").write_bytes(b"the earlier model")
    assert cli.main(["export", str(tmp_path / "m.onnx"), "--height", "64"]) == status
    assert "Traceback" not in capsys.readouterr().err
    assert [p.name for p in tmp_path.iterdir()] == ["m.onnx"]
    assert (tmp_path / "m.onnx").read_bytes() == b"the earlier model"


def test_export_renames_the_built_model_to_its_path(monkeypatch, tmp_path, capsys):
    import json

    import onnx
    from onnx import TensorProto, helper

    def build(path, **kw):
        x = helper.make_tensor_value_info("x", TensorProto.FLOAT, [1])
        model = helper.make_model(helper.make_graph([helper.make_node("Identity", ["x"], ["y"])], "g", [x],
                                                    [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1])]))
        for key in ("name", "num_planes", "grids", "num_gaussians"):
            model.metadata_props.add(key=key, value=key)
        onnx.save(model, str(path))
        return Path(path)

    monkeypatch.setattr(cli_export, "load_export_model", lambda: build)
    assert cli.main(["export", str(tmp_path / "sub" / "m.onnx")]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["path"] == str(tmp_path / "sub" / "m.onnx") and summary["name"] == "name"
    assert [p.name for p in (tmp_path / "sub").iterdir()] == ["m.onnx"]


@pytest.mark.parametrize("flag", ["--erp-encoder", "--readout"])
def test_export_offers_no_experiment_switches(flag, capsys):
    with pytest.raises(SystemExit) as info:
        cli.main(["export", "m.onnx", flag])
    assert info.value.code == 2
    assert "unrecognized arguments" in capsys.readouterr().err


def test_reconstruct_argument_errors(tmp_path, capsys):
    # input errors are reported before any model is loaded or built
    missing = tmp_path / "none.onnx"
    assert cli.main(["reconstruct", str(tmp_path), "--model", str(missing)]) == 2
    assert "not a scene folder" in capsys.readouterr().err
    assert cli.main(["reconstruct", "a.png", "b.png", "--model", str(missing)]) == 2  # no poses: estimated, but
    assert "cannot read image" in capsys.readouterr().err                              # the images are missing
    assert cli.main(["reconstruct", "a.png", "b.png", "c.png", "--model", str(missing)]) == 2
    capsys.readouterr()
    (tmp_path / "poses.json").write_text('{"c2w": [[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]], '
                                         '[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]]}')
    assert cli.main(["reconstruct", "a.png", "b.png", "--poses", str(tmp_path / "poses.json")]) == 2
    assert "identical" in capsys.readouterr().err
    for name, seed in (("a.png", 0), ("b.png", 1)):  # two pictures of detail: one sent twice, or a flat one, is refused
        (tmp_path / name).write_bytes(panorama(32, seed=seed))  # first
    (tmp_path / "poses.json").write_text('{"c2w": [[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]], '
                                         '[[1,0,0,1],[0,1,0,0],[0,0,1,0],[0,0,0,1]]]}')
    argv = ["reconstruct", str(tmp_path / "a.png"), str(tmp_path / "b.png"), "--poses", str(tmp_path / "poses.json"),
            "--model", str(missing), "--no-build"]
    assert cli.main(argv) == 2
    assert "does not exist" in capsys.readouterr().err


def test_reconstruct_reads_images_as_the_api_does(tmp_path, capsys):
    """A 16-bit greyscale PNG is scaled by its range (Pillow's RGB conversion made it white) and a PNG
    holding fewer rows than its header says is refused (Pillow left the missing rows black)."""
    import argparse
    import io

    from PIL import Image

    from service.cli.reconstruct import load_pair
    from service.images import decode_rgb
    from tests.service._support import POSES, panorama

    grey = np.asarray(Image.open(io.BytesIO(panorama(seed=5))).convert("L")).astype(np.uint16) * 257
    Image.fromarray(grey).save(tmp_path / "a.png")
    (tmp_path / "b.png").write_bytes(panorama(seed=6))
    (tmp_path / "poses.json").write_text(POSES)
    args = argparse.Namespace(inputs=[str(tmp_path / "a.png"), str(tmp_path / "b.png")], poses=str(tmp_path / "poses.json"))
    a, _, _, _, _ = load_pair(args)
    api, _ = decode_rgb((tmp_path / "a.png").read_bytes(), "image_a", max_pixels=1 << 25, min_height=32)
    assert a.dtype == np.float32 and np.array_equal(np.round(a * 255).astype(np.uint8), api)
    assert abs(float(a.mean()) - grey.mean() / 65535) < 0.01  # not white
    whole = (tmp_path / "b.png").read_bytes()
    (tmp_path / "b.png").write_bytes(whole[: len(whole) // 3] + whole[-12:])  # IEND kept: Pillow reads no error
    assert cli.main(["reconstruct", str(tmp_path / "a.png"), str(tmp_path / "b.png"), "--poses",
                     str(tmp_path / "poses.json"), "--no-build", "--model", str(tmp_path / "none.onnx")]) == 2
    err = capsys.readouterr().err
    assert "b.png" in err and "truncated" in err


def test_reconstruct_reads_a_scene_folder_as_the_api_reads_uploads(tmp_path):
    """A scene folder's images go through the API's decoder too: a 16-bit PNG scaled by its range, not white."""
    import argparse
    import io
    import json

    from PIL import Image

    from service.cli.reconstruct import load_pair
    from service.images import decode_rgb
    from tests.service._support import panorama

    grey = np.asarray(Image.open(io.BytesIO(panorama(seed=5))).convert("L")).astype(np.uint16) * 257
    Image.fromarray(grey).save(tmp_path / "a.png")
    (tmp_path / "b.png").write_bytes(panorama(seed=6))
    eye = np.eye(4)
    moved = eye.copy()
    moved[0, 3] = 1.0
    frames = [{"name": "a", "image": "a.png", "c2w": eye.tolist()}, {"name": "b", "image": "b.png", "c2w": moved.tolist()}]
    (tmp_path / "scene.json").write_text(json.dumps({"convention": "opencv", "frames": frames}))
    a, b, c2w_a, c2w_b, _ = load_pair(argparse.Namespace(inputs=[str(tmp_path)], refs=None, split=0))
    api, _ = decode_rgb((tmp_path / "a.png").read_bytes(), "image_a", max_pixels=1 << 25, min_height=32)
    assert a.dtype == np.float32 and np.array_equal(np.round(a * 255).astype(np.uint8), api)
    assert abs(float(a.mean()) - grey.mean() / 65535) < 0.01  # not white
    assert np.allclose(c2w_b[:3, 3], [1.0, 0.0, 0.0])


def test_reconstruct_scale_flags_with_given_poses_are_refused(tmp_path, capsys):
    """--baseline / --camera-height scale estimated poses only; with --poses they were ignored without a word."""
    from tests.service._support import POSES, panorama

    for name, seed in (("a.png", 7), ("b.png", 8)):
        (tmp_path / name).write_bytes(panorama(seed=seed))
    (tmp_path / "poses.json").write_text(POSES)
    for flag in ("--baseline", "--camera-height"):
        assert cli.main(["reconstruct", str(tmp_path / "a.png"), str(tmp_path / "b.png"), "--poses",
                         str(tmp_path / "poses.json"), flag, "2", "--no-build", "--model", str(tmp_path / "none.onnx")]) == 2
        err = capsys.readouterr().err
        assert flag in err and "given" in err
    # and --refine-poses refines given poses only: without --poses it was ignored the same way
    assert cli.main(["reconstruct", str(tmp_path / "a.png"), str(tmp_path / "b.png"), "--refine-poses", "--no-build",
                     "--model", str(tmp_path / "none.onnx")]) == 2
    err = capsys.readouterr().err
    assert "--refine-poses" in err and "without poses" in err


@pytest.mark.parametrize("flag", ["-o", "--json"])
def test_reconstruct_output_that_is_a_folder_is_refused_before_any_work(tmp_path, capsys, flag):
    (tmp_path / "out").mkdir()
    argv = ["reconstruct", str(tmp_path / "a.png"), str(tmp_path / "b.png"), flag, str(tmp_path / "out"),
            "--no-build", "--model", str(tmp_path / "none.onnx")]
    assert cli.main(argv) == 2  # was an IsADirectoryError traceback after the reconstruction
    err = capsys.readouterr().err
    assert "is a folder" in err and "Traceback" not in err


def test_reconstruct_compaction_flags_map_to_options():
    parser = cli.build_parser()

    def opts(*flags):
        return pipeline_options(parser.parse_args(["reconstruct", "scene", *flags])).compaction

    default = opts()
    assert default.merge_smooth is True and default.smooth_levels == 1
    assert opts("--no-merge-smooth").merge_smooth is False
    assert opts("--no-compaction").merge_smooth is False
    with pytest.raises(cli.CliError, match="--min-opacity, --no-merge-smooth would do nothing"):  # not dropped
        opts("--no-compaction", "--min-opacity", "0.5", "--no-merge-smooth")
    with pytest.raises(SystemExit):  # an experiment's switch, not a CLI option
        opts("--smooth-levels", "2")
    full = pipeline_options(parser.parse_args(["reconstruct", "scene"]))
    assert full.sh_degree == 1
    assert pipeline_options(parser.parse_args(["reconstruct", "scene", "--sh-degree", "0"])).sh_degree == 0
    with pytest.raises(cli.CliError, match="--sh-degree"):
        pipeline_options(parser.parse_args(["reconstruct", "scene", "--sh-degree", "2"]))
    assert full.rig_cap_deg is None  # automatic (rasterizer.rig.resolve_rig_cap)
    assert pipeline_options(parser.parse_args(["reconstruct", "scene", "--rig-cap-deg", "20"])).rig_cap_deg == 20.0
    with pytest.raises(cli.CliError, match="--rig-cap-deg"):
        pipeline_options(parser.parse_args(["reconstruct", "scene", "--rig-cap-deg", "50"]))


@pytest.mark.parametrize("flags, says", [
    (["--max-gaussians", "0"], "--max-gaussians: "),  # was "options.compaction.max_count: ..."
    (["--max-bytes", "-5"], "--max-bytes: "),
    (["--min-opacity", "1"], "--min-opacity: "),
    (["--near", "-1"], "--near: "),
    (["--sh-degree", "2"], "--sh-degree: "),
])
def test_reconstruct_option_errors_name_the_flags(flags, says):
    with pytest.raises(cli.CliError) as info:
        pipeline_options(cli.build_parser().parse_args(["reconstruct", "scene", *flags]))
    assert str(info.value).startswith(says) and "options." not in str(info.value)


def test_reconstruct_output_that_is_not_a_ply_is_refused_before_any_work(tmp_path, capsys):
    argv = ["reconstruct", str(tmp_path / "a.png"), str(tmp_path / "b.png"), "-o", str(tmp_path / "s.txt"),
            "--no-build", "--model", str(tmp_path / "none.onnx")]
    assert cli.main(argv) == 2  # a PLY was written under the name s.txt
    err = capsys.readouterr().err
    assert "s.txt" in err and ".ply" in err and "Traceback" not in err
    assert not (tmp_path / "s.txt").exists()


def test_reconstruct_checks_near_far_against_the_cameras_before_the_model(tmp_path, capsys):
    """The API's 422 (check_sweep_range); the CLI's message names --far, not 'options: far='."""
    from tests.service._support import POSES, panorama

    for name, seed in (("a.png", 7), ("b.png", 8)):
        (tmp_path / name).write_bytes(panorama(seed=seed))
    (tmp_path / "poses.json").write_text(POSES)
    assert cli.main(["reconstruct", str(tmp_path / "a.png"), str(tmp_path / "b.png"), "--poses", str(tmp_path / "poses.json"),
                     "--far", "1e9", "--model", str(tmp_path / "none.onnx"), "--no-build"]) == 2
    err = capsys.readouterr().err
    assert "--far 1e+09 is beyond" in err and "options" not in err and "does not exist" not in err


def test_reconstruct_with_a_model_file_that_is_no_onnx_model_is_a_one_line_error(tmp_path, capsys):
    from tests.service._support import POSES, panorama

    for name, seed in (("a.png", 7), ("b.png", 8)):
        (tmp_path / name).write_bytes(panorama(seed=seed))
    (tmp_path / "poses.json").write_text(POSES)
    (tmp_path / "m.onnx").write_bytes(b"not a model")  # was an onnxruntime InvalidProtobuf traceback
    assert cli.main(["reconstruct", str(tmp_path / "a.png"), str(tmp_path / "b.png"), "--poses", str(tmp_path / "poses.json"),
                     "--model", str(tmp_path / "m.onnx"), "--no-build", "-o", str(tmp_path / "s.ply")]) == 2
    err = capsys.readouterr().err
    assert "--model" in err and "not a loadable ONNX model" in err and "Traceback" not in err


def test_reconstruct_that_leaves_no_gaussian_is_refused_as_the_api_refuses_it(tmp_path, capsys, model_path):
    """--min-opacity 0.999999 wrote a 0-Gaussian PLY with exit status 0; the API answers 422 empty_scene."""
    from tests.service._support import POSES, panorama

    for name, seed in (("a.png", 61), ("b.png", 62)):
        (tmp_path / name).write_bytes(panorama(seed=seed))
    (tmp_path / "poses.json").write_text(POSES)
    argv = ["reconstruct", str(tmp_path / "a.png"), str(tmp_path / "b.png"), "--poses", str(tmp_path / "poses.json"),
            "--model", str(model_path), "--no-build", "-o", str(tmp_path / "s.ply"), "--json", str(tmp_path / "s.json")]
    assert cli.main([*argv, "--min-opacity", "0.999999"]) == 2
    err = capsys.readouterr().err
    assert "reconstruction is empty" in err and "--min-opacity removed" in err and "Traceback" not in err
    assert not (tmp_path / "s.ply").exists() and not (tmp_path / "s.json").exists()
    assert cli.main(argv) == 0  # the same inputs with the default compaction
    assert len(read_ply(tmp_path / "s.ply")) > 0


@pytest.mark.parametrize("text, says", [
    ("[]", "wrong type"),  # each was a TypeError / AttributeError / KeyError traceback or a bare "'image'"
    ('{"frames": 5}', "wrong type"),
    ('{"frames": [{"name": "a"}]}', "lacks the key 'image'"),
    ('{"frames": [{"name": "a", "image": 5, "c2w": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}', "wrong type"),
])
def test_malformed_scene_json_is_a_one_line_error(tmp_path, capsys, text, says):
    (tmp_path / "scene.json").write_text(text)
    for argv in (["reconstruct", str(tmp_path), "--no-build", "--model", str(tmp_path / "none.onnx")],
                 ["refine", str(tmp_path / "in.ply"), str(tmp_path), "--out", str(tmp_path / "o.ply")]):
        if argv[0] == "refine":
            ply_with_nan(tmp_path / "in.ply", 10, [])
        assert cli.main(argv) == 2
        err = capsys.readouterr().err
        assert "scene.json" in err and says in err and "Traceback" not in err


def test_select_and_edit_with_a_store_that_is_a_file_is_a_one_line_error(tmp_path, capsys):
    (tmp_path / "store").write_text("not a folder")  # was a NotADirectoryError traceback
    for argv in (["select", "0" * 32, "--view", "a", "--point", "0.5,0.5"],
                 ["edit", "0" * 32, "--selection", "0" * 32, "--op", "remove"]):
        assert cli.main([argv[0], "--store", str(tmp_path / "store"), *argv[1:]]) == 2
        err = capsys.readouterr().err
        assert "--store" in err and "scene store" in err and "Traceback" not in err


def test_select_and_edit_in_a_folder_that_holds_no_store_make_none(tmp_path, capsys):
    """A mistyped --store is refused, not made into an empty store (scenes/, tmp/, trash/) that has no such scene."""
    (tmp_path / "elsewhere").mkdir()
    for store in (tmp_path / "typo", tmp_path / "elsewhere"):
        for argv in (["select", "0" * 32, "--view", "a", "--point", "0.5,0.5"],
                     ["edit", "0" * 32, "--selection", "0" * 32, "--op", "remove"]):
            assert cli.main([argv[0], "--store", str(store), *argv[1:]]) == 2
            err = capsys.readouterr().err
            assert f"--store {store}: no scene store there" in err and "Traceback" not in err, err
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["elsewhere"]


@pytest.mark.parametrize("argv, says", [
    (["select", "../../etc", "--view", "a", "--point", "0.5,0.5"], "invalid_scene_id"),  # was a traceback
    (["select", "0" * 32, "--view", "a", "--point", "0.5,0.5", "--negative", "1.5,0.5"],
     "--negative: negative[0] = [1.5, 0.5]"),
    (["select", "0" * 32, "--point", "0.5,0.5"], "--view: give the reference"),  # took view a; the API's 422
    (["select", "0" * 32, "--view", "b", "--segment", "3"], "--segment: give either"),  # --view was ignored
    (["select", "0" * 32, "--view", "a", *["--point", "0.5,0.5"] * 65], "--point: List should have at most 64"),
    (["select", "0" * 32, "--segment", "-1"], "--segment: Input should be greater"),  # was "select.segment: ..."
    (["edit", "../x", "--selection", "0" * 32, "--op", "keep"], "invalid_scene_id"),
    (["edit", "0" * 32, "--selection", "0" * 32, "--op", "remove", "--color", "1,0,0"],
     "--color: only for the recolor op, not remove"),  # was ignored, then named the API's body keys
    (["edit", "0" * 32, "--selection", "0" * 32, "--op", "recolor", "--color", "2,0,0"], "--color: the recolor op needs r, g, b"),
    (["edit", "0" * 32, "--selection", "0" * 32, "--op", "keep", "--offset", "1,0,0"], "--offset: only for the translate op"),
    (["edit", "0" * 32, "--selection", "0" * 32, "--op", "translate", "--offset", "1e7,0,0"],
     "--offset: the translate op needs dx, dy, dz, each within +-1e+06"),
])
def test_select_and_edit_errors_are_one_line_as_the_api_words_them(tmp_path, capsys, argv, says):
    (tmp_path / "store" / "scenes").mkdir(parents=True)  # an empty store
    assert cli.main([argv[0], "--store", str(tmp_path / "store"), *argv[1:]]) == 2
    err = capsys.readouterr().err
    assert says in err and "Traceback" not in err


def test_serve_without_model_and_no_build(tmp_path, capsys):
    assert cli.main(["serve", "--model", str(tmp_path / "missing.onnx"), "--no-build"]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_console_script_is_declared():
    text = (ROOT / "pyproject.toml").read_text()
    assert 'omnisplat = "service.cli:main"' in text
    assert 'omnisplat-bench = "bench.__main__:main"' in text


def _importable(name: str) -> bool:
    import importlib.util

    try:
        return importlib.util.find_spec(name) is not None
    except ModuleNotFoundError:
        return False


@pytest.mark.parametrize("build", [True, False])
def test_a_model_path_that_is_a_folder_is_said_to_be_one(tmp_path, build):
    """A folder given as the model file is said to be a folder (not "does not exist"), and nothing is built there."""
    from service.model_files import ModelUnavailable, ensure_model

    with pytest.raises(ModelUnavailable, match="is a folder; give the path of an .onnx file"):
        ensure_model(tmp_path, build_if_missing=build)
    assert list(tmp_path.iterdir()) == []


def test_ensure_model_builds_once_atomically(tmp_path):
    from service.model_files import ensure_model

    target = tmp_path / "models" / "m.onnx"
    messages = []
    path = ensure_model(target, progress=messages.append, height=64, width=128, num_planes=4)
    assert path == target and target.stat().st_size > 0
    assert [p.name for p in target.parent.iterdir()] == ["m.onnx"]  # no temporary left behind
    assert any("building" in m for m in messages)
    mtime = target.stat().st_mtime_ns
    assert ensure_model(target, progress=messages.append) == target and target.stat().st_mtime_ns == mtime


def test_settings_from_environment(monkeypatch, tmp_path):
    from pydantic import ValidationError

    from service.config import Settings

    monkeypatch.setenv("OMNISPLAT_STORE_DIR", str(tmp_path / "s"))
    monkeypatch.setenv("OMNISPLAT_MAX_UPLOAD_BYTES", "5000")
    monkeypatch.setenv("OMNISPLAT_INFERENCE_QUEUE", "0")
    s = Settings()
    assert s.store_dir == tmp_path / "s" and s.max_upload_bytes == 5000 and s.inference_queue == 0
    assert s.resolved_model_path.name == default_model_name()
    assert re.fullmatch(r"omnisplat-default-[0-9a-f]{10}\.onnx", default_model_name())
    assert Settings(port=9000).port == 9000  # explicit values (CLI flags) win over the environment
    monkeypatch.setenv("OMNISPLAT_PORT", "not a port")
    with pytest.raises(ValidationError):
        Settings()


def test_reconstruct_without_poses_refuses_identical_images(tmp_path, capsys):
    from PIL import Image

    noise = np.random.default_rng(0).integers(0, 255, (256, 512, 3), dtype=np.uint8)
    for name in ("a.png", "b.png"):
        Image.fromarray(noise).save(tmp_path / name)
    argv = ["reconstruct", str(tmp_path / "a.png"), str(tmp_path / "b.png"), "--model", str(tmp_path / "none.onnx"),
            "--no-build"]
    assert cli.main(argv) == 2
    assert "same picture" in capsys.readouterr().err
    assert cli.main([*argv, "--baseline", "1", "--camera-height", "1.5"]) == 2
    assert "not both" in capsys.readouterr().err


# -- outputs checked before any work, scene folders read strictly ----------------------------------------

SAMPLE = ROOT / "samples" / "room"


def _sample_copy(tmp_path: Path) -> Path:
    import shutil

    return Path(shutil.copytree(SAMPLE, tmp_path / "room"))


def _no_model(tmp_path: Path) -> list[str]:
    return ["--no-build", "--model", str(tmp_path / "none.onnx")]


@pytest.mark.parametrize("extra, says", [
    (["--split", "5"], "--split 5: "),  # the last split was taken without a word
    (["--json", "{room}/images/00.png"], "--json"),  # an input photo was overwritten by the summary
    (["--json", "{room}/scene.json"], "is one of the command's inputs"),
    (["--json", "{tmp}/x.ply"], "must end in .json"),
    (["-o", "{room}/scene.json/x.ply"], "is a file, not a folder"),  # refused only after the reconstruction
    (["-o", ""], "-o: give a file name"),
    (["-o", "{tmp}/n/x.json/s.ply", "--json", "{tmp}/n/x.json"], "give the outputs separate names"),  # before any work:
    (["-o", "{tmp}/n/s.ply", "--json", "{tmp}/n/s.ply/x.json"], "give the outputs separate names"),  # no PLY left behind
    (["--threads", "100000"], "--threads: Input should be less than or equal to 256"),  # 16 GB of thread stacks
    (["--threads", "-1"], "--threads: Input should be greater than or equal to 1"),
])
def test_reconstruct_refuses_bad_outputs_and_splits_before_any_work(tmp_path, capsys, extra, says):
    room = _sample_copy(tmp_path)
    before = {p: p.read_bytes() for p in room.rglob("*") if p.is_file()}
    extra = [e.format(room=room, tmp=tmp_path) for e in extra]
    assert cli.main(["reconstruct", str(room), *_no_model(tmp_path), *extra]) == 2
    err = capsys.readouterr().err
    assert says in err and "does not exist" not in err and "Traceback" not in err, err  # before the model check
    assert {p: p.read_bytes() for p in room.rglob("*") if p.is_file()} == before


@pytest.mark.parametrize("command", ["reconstruct", "refine"])
@pytest.mark.parametrize("inputs, extra, says", [
    (["room"], ["--poses", "{tmp}/missing.json"], "--poses: {room} is a scene folder"),  # dropped without a word
    (["a", "b"], ["--refs", "00,02"], "--refs: chooses the references of a scene folder"),
    (["a", "b"], ["--split", "0"], "--split: chooses the references of a scene folder"),
    (["a", "b"], ["--poses", "{tmp}/empty.json"], "the file is empty; leave --poses out"),  # not "estimate them"
])
def test_flags_the_inputs_do_not_use_are_refused(tmp_path, capsys, command, inputs, extra, says):
    (tmp_path / "empty.json").write_bytes(b" \n")
    paths = {"room": str(SAMPLE), "a": str(SAMPLE / "images" / "00.png"), "b": str(SAMPLE / "images" / "02.png")}
    if command == "reconstruct":
        argv = ["reconstruct", *(paths[i] for i in inputs), *_no_model(tmp_path), "-o", str(tmp_path / "s.ply")]
    else:
        ply_with_nan(tmp_path / "in.ply", 10, [])
        argv = ["refine", str(tmp_path / "in.ply"), *(paths[i] for i in inputs), "--out", str(tmp_path / "s.ply"),
                "--iterations", "1", "--height", "16"]
    assert cli.main([*argv, *(e.format(tmp=tmp_path) for e in extra)]) == 2
    err = capsys.readouterr().err
    assert says.format(room=SAMPLE) in err and "Traceback" not in err, err
    assert not (tmp_path / "s.ply").exists()


def test_scene_folder_errors_name_its_scene_json_once(tmp_path, capsys):
    """Each error names scene.json once (not "ROOM: ROOM: ..."), and a bad pose names its frame."""
    room = _sample_copy(tmp_path)
    scene = json.loads((room / "scene.json").read_text())
    scene["splits"][0]["targets"] = ["zz"]
    (room / "scene.json").write_text(json.dumps(scene))
    assert cli.main(["reconstruct", str(room), *_no_model(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert f"error: {room / 'scene.json'}: split names unknown frames ['zz']" in err and err.count(str(room)) == 1, err
    scene["splits"][0]["targets"], scene["frames"][2]["c2w"][0][0] = ["01"], float("nan")
    (room / "scene.json").write_text(json.dumps(scene))
    assert cli.main(["reconstruct", str(room), *_no_model(tmp_path)]) == 2
    assert f"error: {room / 'scene.json'}: frame '02': pose contains NaN" in capsys.readouterr().err


def test_reconstruct_split_message_names_the_folders_splits(tmp_path, capsys):
    room = _sample_copy(tmp_path)
    assert cli.main(["reconstruct", str(room), *_no_model(tmp_path), "--split", "5"]) == 2
    assert f"--split 5: {room} has splits 0-0" in capsys.readouterr().err


@pytest.mark.parametrize("edit, says", [
    (lambda text: "\ufeff" + text, "does not exist"),  # a BOM: Python's "Unexpected UTF-8 BOM"; now read as the API reads JSON
    (lambda text: text.replace('"name": "01"', '"name": "00"'), "the frame name '00' appears twice"),
])
def test_scene_json_with_a_bom_is_read_and_duplicate_frames_refused(tmp_path, capsys, edit, says):
    room = _sample_copy(tmp_path)
    scene_json = room / "scene.json"
    scene_json.write_text(edit(scene_json.read_text()), encoding="utf-8")
    assert cli.main(["reconstruct", str(room), *_no_model(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert says in err and "Traceback" not in err, err  # "does not exist": the folder passed, the missing model stops it


def test_serve_with_a_named_missing_model_does_not_build_one(tmp_path, capsys, monkeypatch):
    """`serve --model typo.onnx` exported the default model at the typo's path and served it."""
    import service.model_files as model_files

    def no_export(*a, **k):
        raise AssertionError("built a model")

    monkeypatch.setattr(model_files, "_say", lambda msg: None)
    monkeypatch.setitem(sys.modules, "export.onnx_export", type(sys)("stub"))
    sys.modules["export.onnx_export"].export_model = no_export
    assert cli.main(["serve", "--model", str(tmp_path / "typo.onnx"), "--store", str(tmp_path / "store")]) == 2
    err = capsys.readouterr().err
    assert "typo.onnx does not exist" in err and "only the default model" in err
    assert not (tmp_path / "typo.onnx").exists()


def test_serve_on_a_port_in_use_is_a_one_line_error_before_any_model(tmp_path, capsys):
    """A port another server listens on is said at once, in one line, before a model is looked for or built."""
    import socket

    with socket.socket() as other:
        other.bind(("127.0.0.1", 0))
        other.listen(1)
        port = other.getsockname()[1]
        code = cli.main(["serve", "--port", str(port), "--store", str(tmp_path / "store"), "--no-build",
                         "--model", str(tmp_path / "missing.onnx")])
    err = capsys.readouterr().err
    assert code == 2 and f"--port {port}: cannot listen on 127.0.0.1:{port}" in err and "Traceback" not in err
    assert "does not exist" not in err  # the model was not looked at


def test_serve_with_a_store_that_is_a_file_is_a_one_line_error(tmp_path, capsys):
    (tmp_path / "store").write_text("not a folder")
    assert cli.main(["serve", "--store", str(tmp_path / "store"), "--no-build", "--model", str(tmp_path / "m.onnx")]) == 2
    err = capsys.readouterr().err
    assert "--store" in err and "cannot keep scenes there" in err and "Traceback" not in err


@pytest.mark.parametrize("argv, says", [
    (["{tmp}/m.onnx", "--downscale", "0"], "--downscale: must be 1 or more, got 0"),  # a ZeroDivisionError traceback
    (["{tmp}"], "is a folder"),  # IsADirectoryError after the build
    (["{tmp}/m.txt"], "must end in .onnx"),
])
def test_export_checks_its_arguments_before_building(tmp_path, capsys, monkeypatch, argv, says):
    monkeypatch.setattr(cli_export, "load_export_model", lambda: pytest.fail("built before checking"))
    assert cli.main(["export", *(a.format(tmp=tmp_path) for a in argv)]) == 2
    err = capsys.readouterr().err
    assert says in err and "Traceback" not in err, err


def test_serve_setting_errors_name_the_flags_and_variables(tmp_path, capsys, monkeypatch):
    """They named Settings' fields (port, ort_threads, max_upload_bytes) with links to the library's docs."""
    assert cli.main(["serve", "--port", "99999", "--threads", "0", "--max-upload-mb", "-1", "--no-build"]) == 2
    err = capsys.readouterr().err
    assert "--port: " in err and "(got 99999)" in err and "--threads: " in err and "--max-upload-mb: " in err
    assert "ort_threads" not in err and "pydantic" not in err
    monkeypatch.setenv("OMNISPLAT_MAX_REQUESTS", "many")
    assert cli.main(["serve", "--no-build"]) == 2
    assert "OMNISPLAT_MAX_REQUESTS: " in capsys.readouterr().err


@pytest.mark.parametrize("value", ["nan", "inf"])
def test_serve_max_upload_that_is_no_number_of_mib_is_a_one_line_error(tmp_path, capsys, value):
    """The MiB flag is turned into bytes before the settings check it: NaN and Inf must reach that check."""
    argv = ["serve", f"--max-upload-mb={value}", "--store", str(tmp_path / "s"), "--no-build"]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert f"--max-upload-mb: Input should be a finite number (got {value} MiB)" in err and "Traceback" not in err, err


def test_select_and_edit_on_a_server_store_keep_its_writes_and_take_its_settings(tmp_path, capsys, monkeypatch):
    """The CLI borrows the server's store: it never clears what the server is writing (tmp/, trash/, artifact
    .tmp files) and keeps the store settings of the environment (budget, max scenes); --store moves the folder."""
    import os

    from rasterizer.gaussians import Gaussians
    from service import edits
    from service.store import SceneStore, content_id

    root = tmp_path / "store"
    sid = content_id("cli-store")
    one = np.ones((5, 3), np.float32)
    SceneStore(root).put(sid, Gaussians(one, one * 0.1, np.tile([1.0, 0, 0, 0], (5, 1)), np.ones(5), one[:, None]), {})
    staging, trash = root / "tmp" / f"{sid}-0123", root / "trash" / f"{sid}-4567"
    staging.mkdir()
    trash.mkdir()
    artifact = root / "scenes" / sid / ".gaussians.ply.89ab.tmp"
    artifact.write_bytes(b"half")
    for path in (staging, trash, artifact):
        os.utime(path, (0, 0))  # even old ones: the CLI is no server and clears nothing
    monkeypatch.setenv("OMNISPLAT_MAX_SCENES", "1")
    monkeypatch.setenv("OMNISPLAT_STORE_BUDGET_BYTES", "40000000")
    monkeypatch.setenv("OMNISPLAT_STORE_DIR", str(tmp_path / "elsewhere"))
    seen = []
    monkeypatch.setattr(edits, "create_selection", lambda store, scene, request: seen.append(store) or {"ok": 1})
    assert cli.main(["select", sid, "--store", str(root), "--view", "a", "--point", "0.5,0.5"]) == 0
    assert cli.main(["select", "0" * 32, "--store", str(root), "--segment", "2"]) == 0
    capsys.readouterr()
    assert staging.is_dir() and trash.is_dir() and artifact.is_file()
    assert [(s.root, s.max_scenes, s.budget_bytes) for s in seen] == [(root, 1, 40_000_000)] * 2


@pytest.mark.parametrize("env, command", [
    ({"OMNISPLAT_CORS_ORIGINS": "x"}, "serve"),  # pydantic-settings' own error: a 41-line traceback
    ({"OMNISPLAT_CORS_ORIGINS": "x"}, "render"),
    ({"OMNISPLAT_MAX_SCENES": "-1"}, "select"),
])
def test_bad_environment_settings_are_one_line_errors(tmp_path, capsys, monkeypatch, env, command):
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    ply_with_nan(tmp_path / "g.ply", 10, [])
    argv = {"serve": ["serve", "--no-build"], "render": render_argv(tmp_path, "g.ply"),
            "select": ["select", "0" * 32, "--store", str(tmp_path / "s"), "--view", "a", "--point", "0.5,0.5"]}[command]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "OMNISPLAT_" in err and "Traceback" not in err, err


@pytest.mark.parametrize("name, value, says", [
    ("OMNISPLAT_API_KEY", "s3cret\n", "must not be blank nor begin or end with white space"),  # every /v1 request 401
    ("OMNISPLAT_API_KEY", "   ", "must not be blank"),
    ("OMNISPLAT_ALLOWED_HOSTS", "[]", "OMNISPLAT_ALLOWED_HOSTS) is empty"),  # every request 400, /healthz included
    ("OMNISPLAT_MIN_IMAGE_HEIGHT", "5000", "over max_image_pixels 33554432: every upload would be refused"),
    ("OMNISPLAT_MAX_IMAGE_PIXELS", "1024", "min_image_height 32 needs panoramas of at least 2048 pixels"),
])
def test_settings_that_refuse_every_request_are_one_line_errors(tmp_path, capsys, monkeypatch, name, value, says):
    """Settings under which a server would refuse every request (or every upload) are start-up errors."""
    monkeypatch.setenv(name, value)
    assert cli.main(["serve", "--no-build", "--model", str(tmp_path / "m.onnx")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and says in err and "does not exist" not in err and "Traceback" not in err, err


def test_serve_refuses_a_misspelt_setting_variable_and_says_which_others_it_ignores(tmp_path, capsys, monkeypatch):
    """OMNISPLAT_ORT_THREAD=8 left ort_threads at 2 without a word (pydantic-settings ignores unknown names)."""
    argv = ["serve", "--no-build", "--model", str(tmp_path / "m.onnx")]
    monkeypatch.setenv("OMNISPLAT_ORT_THREAD", "8")
    monkeypatch.setenv("OMNISPLAT_NODE_MODULES", str(tmp_path))  # read by the viewer, not a setting: fine
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "OMNISPLAT_ORT_THREAD is no setting; did you mean OMNISPLAT_ORT_THREADS?" in err
    monkeypatch.delenv("OMNISPLAT_ORT_THREAD")
    monkeypatch.setenv("OMNISPLAT_SERVICE_HOST", "10.0.0.1")  # close to no setting: said, then the start goes on
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert "ignoring OMNISPLAT_SERVICE_HOST: no omnisplat setting" in err and "m.onnx does not exist" in err, err
    assert "NODE_MODULES" not in err


def test_serve_with_a_models_dir_that_is_a_file_is_a_one_line_error(tmp_path, capsys, monkeypatch):
    """Building the missing default model under a file printed a FileExistsError traceback."""
    (tmp_path / "models").write_text("not a folder")
    monkeypatch.setenv("OMNISPLAT_MODELS_DIR", str(tmp_path / "models"))
    assert cli.main(["serve", "--store", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cannot be built there" in err and "Traceback" not in err, err


def test_commands_that_do_not_serve_ignore_the_servers_host_rule(tmp_path, capsys, monkeypatch):
    """A shell set up for `serve --host 0.0.0.0` (no key) made select refuse and render print a traceback."""
    monkeypatch.setenv("OMNISPLAT_HOST", "0.0.0.0")
    ply_with_nan(tmp_path / "g.ply", 10, [])
    assert cli.main(render_argv(tmp_path, "g.ply")) == 0
    (tmp_path / "s" / "scenes").mkdir(parents=True)  # an empty store
    assert cli.main(["select", "0" * 32, "--store", str(tmp_path / "s"), "--view", "a", "--point", "0.5,0.5"]) == 2
    assert "scene_not_found" in capsys.readouterr().err  # the store opened; only the scene is missing
    assert cli.main(["serve", "--no-build", "--model", str(tmp_path / "m.onnx")]) == 2
    err = capsys.readouterr().err
    assert "OMNISPLAT_* settings: host '0.0.0.0' is not a loopback address" in err and "{" not in err


def test_serve_with_a_model_file_that_is_no_model_is_a_one_line_error(tmp_path, capsys):
    (tmp_path / "m.onnx").write_bytes(b"\x89PNG not a model")
    assert cli.main(["serve", "--model", str(tmp_path / "m.onnx"), "--store", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err
    assert "--model" in err and "not a loadable ONNX model" in err and "Traceback" not in err


@pytest.mark.parametrize("source", ["default", "variable"])
def test_serve_with_a_damaged_model_not_named_by_flag_is_a_one_line_error_naming_its_source(tmp_path, capsys,
                                                                                           monkeypatch, source):
    """A damaged default model (in OMNISPLAT_MODELS_DIR) is loaded before serving and refused in one line (a server
    would answer /readyz 503 for good: an existing file is never built again); one named by OMNISPLAT_MODEL_PATH is
    reported under that name, not as --model, a flag the user never gave."""
    if source == "default":
        path = tmp_path / "models" / default_model_name()
        monkeypatch.setenv("OMNISPLAT_MODELS_DIR", str(tmp_path / "models"))
    else:
        path = tmp_path / "m.onnx"
        monkeypatch.setenv("OMNISPLAT_MODEL_PATH", str(path))
    path.parent.mkdir(exist_ok=True)
    path.write_bytes(b"\x89PNG not a model")
    import uvicorn

    monkeypatch.setattr(uvicorn, "Server", lambda config: pytest.fail("served a model that cannot load"))
    assert cli.main(["serve", "--store", str(tmp_path / "s"), "--no-build"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not a loadable ONNX model" in err and "--model" not in err and "Traceback" not in err
    says = f"the default model {path}" if source == "default" else f"OMNISPLAT_MODEL_PATH {path}:"
    assert says in err and ("delete it" in err) == (source == "default"), err


def test_serve_with_a_model_loads_it_once(tmp_path, monkeypatch):
    """`serve --model FILE` loaded the file to check it, dropped that session and loaded the file again as the app
    started: the checked encoder is the one the app serves, with the served thread count."""
    import time

    import uvicorn
    from fastapi.testclient import TestClient

    import service.encoder as encoder_module

    loads, served = [], {}

    class Encoder:  # an OnnxEncoder's face, without onnxruntime
        metadata = {"name": "fake", "version": "1"}
        height, width = 4, 8

        def __init__(self, path, *, threads=2):
            loads.append((Path(path), threads))

    class Server:  # starts the app and stops once its model is loaded
        def __init__(self, config):
            self.app = config.app

        def run(self):
            with TestClient(self.app):
                deadline = time.monotonic() + 60
                while not (self.app.state.runtime.ready or self.app.state.runtime.error) and time.monotonic() < deadline:
                    time.sleep(0.02)
                served["runtime"] = self.app.state.runtime

    monkeypatch.setattr(encoder_module, "OnnxEncoder", Encoder)
    monkeypatch.setattr(uvicorn, "Server", Server)
    monkeypatch.setenv("OMNISPLAT_WARMUP", "false")
    (tmp_path / "m.onnx").write_bytes(b"stands for a model")
    argv = ["serve", "--model", str(tmp_path / "m.onnx"), "--store", str(tmp_path / "s"), "--threads", "3"]
    assert cli.main(argv) == 0
    runtime = served["runtime"]
    assert runtime.ready and runtime.error is None and runtime.metadata["name"] == "fake"
    assert loads == [(tmp_path / "m.onnx", 3)]


def test_a_ply_written_to_a_symlink_goes_through_it(tmp_path):
    from tests.rasterizer._support import toy_scene

    (tmp_path / "real.ply").write_bytes(b"old")
    (tmp_path / "link.ply").symlink_to(tmp_path / "real.ply")
    write_ply(tmp_path / "link.ply", toy_scene(1, n=5))
    assert (tmp_path / "link.ply").is_symlink() and len(read_ply(tmp_path / "real.ply")) == 5


def test_reconstruct_reads_wide_jpegs_as_the_api_does(tmp_path, model_path, monkeypatch):
    """A 4096-wide JPEG is read at 2048 columns, what the API decodes for a model no wider than the pose features
    read; a wider model reads the pair again at its own width."""
    import argparse
    import io

    from PIL import Image

    from service import scenes
    from service.cli import reconstruct
    from service.images import decode_rgb
    from tests.service._support import POSES, panorama

    for name, seed in (("a.jpg", 7), ("b.jpg", 8)):
        big = Image.open(io.BytesIO(panorama(seed=seed))).convert("RGB").resize((4096, 2048), Image.Resampling.BILINEAR)
        big.save(tmp_path / name, quality=90)
    (tmp_path / "poses.json").write_text(POSES)
    args = argparse.Namespace(inputs=[str(tmp_path / "a.jpg"), str(tmp_path / "b.jpg")], poses=str(tmp_path / "poses.json"))
    a, _, _, _, _ = reconstruct.load_pair(args, 2048)
    api, _ = decode_rgb((tmp_path / "a.jpg").read_bytes(), "image_a", max_pixels=1 << 25, min_height=32, min_width=2048)
    assert api.shape == (1024, 2048, 3) and np.array_equal(np.round(a * 255).astype(np.uint8), api)

    widths = []
    load_pair = reconstruct.load_pair

    def recorded(args, min_width=None):
        widths.append(min_width)
        return load_pair(args, min_width)

    monkeypatch.setattr(reconstruct, "load_pair", recorded)
    argv = ["reconstruct", str(tmp_path / "a.jpg"), str(tmp_path / "b.jpg"), "--poses", str(tmp_path / "poses.json"),
            "--model", str(model_path), "--no-build", "-o", str(tmp_path / "scene.ply")]
    assert cli.main(argv) == 0 and widths == [2048]  # the test model reads 256 columns
    widths.clear()
    monkeypatch.setattr(scenes, "read_width", lambda model_height: 2200)  # as a model 550 rows high would read
    assert cli.main(argv) == 0 and widths == [2048, 2200]
