"""``omnisplat refine`` (service.cli) on a tiny synthetic scene."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from rasterizer.ply import read_ply, write_ply
from rasterizer.render import render
from service.cli import main as cli_main
from tests.rasterizer._support import toy_scene


def main(argv):
    return cli_main(["refine", *argv])


def test_refine_cli_writes_refined_ply(tmp_path, capsys):
    truth = toy_scene(4, n=300)
    c2ws = [np.eye(4), np.eye(4)]
    c2ws[1][0, 3] = 0.3
    for name, c2w in zip("ab", c2ws):
        img = render(truth, c2w, projection="erp", width=64).colour
        Image.fromarray((np.clip(img, 0, 1) * 255).astype(np.uint8)).save(tmp_path / f"{name}.png")
    (tmp_path / "poses.json").write_text(json.dumps({"convention": "opencv", "c2w": [m.tolist() for m in c2ws]}))
    rng = np.random.default_rng(0)
    start = truth.__class__(truth.means, truth.scales, truth.quats, truth.opacities,
                            truth.sh + rng.normal(0, 0.5, truth.sh.shape).astype(np.float32))
    write_ply(tmp_path / "in.ply", start)
    rc = main([str(tmp_path / "in.ply"), str(tmp_path / "a.png"), str(tmp_path / "b.png"),
               "--poses", str(tmp_path / "poses.json"), "--out", str(tmp_path / "out.ply"),
               "--height", "16", "--iterations", "10"])
    assert rc == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["held_loss_best"] < summary["held_loss_start"]
    assert summary["cross_check"]["accepted"] and summary["cross_check"]["mse_best"] < summary["cross_check"]["mse_start"]
    out = read_ply(tmp_path / "out.ply")
    assert len(out) == len(start)
    np.testing.assert_allclose(out.means, start.means, atol=1e-6)


def test_refine_cli_bad_arguments(tmp_path):
    assert main([str(tmp_path / "missing.ply"), str(tmp_path), "--out", str(tmp_path / "o.ply")]) == 2
    assert main([str(tmp_path / "missing.ply"), str(tmp_path), "--out", str(tmp_path / "o.ply"),
                 "--no-cross-check"]) == 2
    for flag in (["--loss", "huber"], ["--optimise-opacity"], ["--opacity-lr", "0.1"]):  # experiment switches
        with pytest.raises(SystemExit):
            main([str(tmp_path / "missing.ply"), str(tmp_path), "--out", str(tmp_path / "o.ply"), *flag])


@pytest.mark.parametrize("flag, value", [("--height", "100000"), ("--colour-reg", "nan"), ("--holdout", "0.9"),
                                         ("--patience", "-3"), ("--iterations", "5000")])
def test_refine_cli_takes_the_api_bounds_before_any_work(tmp_path, capsys, flag, value):
    """--height 100000 was a MemoryError traceback and --colour-reg nan ran; the API's bounds apply."""
    assert main([str(tmp_path / "missing.ply"), str(tmp_path), "--out", str(tmp_path / "o.ply"), flag, value]) == 2
    err = capsys.readouterr().err
    assert f"{flag}:" in err and "Traceback" not in err


def test_refine_cli_patience_without_a_holdout_is_refused_and_a_holdout_of_zero_alone_is_not(tmp_path, capsys):
    """The CLI hands the API's check only the flags given, so --holdout 0 alone passes it (and fails later, on the
    missing PLY), while --patience beside it is refused naming --patience."""
    base = [str(tmp_path / "missing.ply"), str(tmp_path), "--out", str(tmp_path / "o.ply"), "--holdout", "0"]
    assert main([*base, "--patience", "5"]) == 2
    assert "--patience:" in capsys.readouterr().err
    assert main(base) == 2
    err = capsys.readouterr().err
    assert "missing.ply" in err and "early stop" not in err, err


def test_refine_cli_needs_poses_and_a_writable_output(tmp_path, capsys):
    write_ply(tmp_path / "in.ply", toy_scene(4, n=50))
    img = np.zeros((32, 64, 3), np.uint8)
    for name in ("a.png", "b.png"):
        Image.fromarray(img).save(tmp_path / name)
    images = [str(tmp_path / "a.png"), str(tmp_path / "b.png")]
    assert main([str(tmp_path / "in.ply"), *images, "--out", str(tmp_path / "o.ply")]) == 2  # was a PoseError traceback
    assert "--poses" in capsys.readouterr().err
    (tmp_path / "poses.json").write_text(json.dumps({"c2w": [np.eye(4).tolist(), (np.eye(4) + np.eye(4, k=3)).tolist()]}))
    argv = [str(tmp_path / "in.ply"), *images, "--poses", str(tmp_path / "poses.json"), "--iterations", "1", "--height", "16"]
    assert main([*argv, "--out", str(tmp_path / "in.ply" / "o.ply")]) == 2  # was a traceback, then a refusal after the run
    assert "is a file, not a folder" in capsys.readouterr().err
    assert main([*argv, "--out", str(tmp_path / "new" / "sub" / "o.ply")]) == 0  # its folders are made, as reconstruct's
    assert (tmp_path / "new" / "sub" / "o.ply").is_file()


def references(tmp_path):
    """Two black 64x32 references and their poses file: the arguments after the PLY."""
    img = np.zeros((32, 64, 3), np.uint8)
    for name in ("a.png", "b.png"):
        Image.fromarray(img).save(tmp_path / name)
    moved = np.eye(4)
    moved[0, 3] = 0.3
    (tmp_path / "poses.json").write_text(json.dumps({"c2w": [np.eye(4).tolist(), moved.tolist()]}))
    return [str(tmp_path / "a.png"), str(tmp_path / "b.png"), "--poses", str(tmp_path / "poses.json")]


def test_refine_cli_refuses_a_ply_without_gaussians(tmp_path, capsys):
    """A 0-Gaussian PLY was 'refined' into another with exit status 0."""
    from rasterizer.gaussians import Gaussians

    write_ply(tmp_path / "empty.ply", Gaussians.empty(0))
    assert main([str(tmp_path / "empty.ply"), *references(tmp_path), "--out", str(tmp_path / "o.ply"),
                 "--iterations", "1", "--height", "16"]) == 2
    err = capsys.readouterr().err
    assert "the PLY holds no Gaussians" in err and "Traceback" not in err and not (tmp_path / "o.ply").exists()


def test_refine_cli_output_that_is_not_a_ply_is_refused_before_any_work(tmp_path, capsys):
    """--out r.png wrote a PLY under that name."""
    assert main([str(tmp_path / "missing.ply"), *references(tmp_path), "--out", str(tmp_path / "r.png")]) == 2
    err = capsys.readouterr().err
    assert "--out" in err and "r.png" in err and ".ply" in err and "missing.ply" not in err


def test_refine_cli_height_too_large_for_the_scene_names_height(tmp_path, capsys):
    """--height 1024 (within the API's bounds) ended in a RenderLimitError traceback; the API's job fails
    with render_too_large. Room-sized Gaussians around the cameras fill every pixel of the Yin/Yang grids."""
    g = toy_scene(4, n=400)
    write_ply(tmp_path / "big.ply", g.with_(scales=np.full_like(g.scales, 5.0)))
    assert main([str(tmp_path / "big.ply"), *references(tmp_path), "--out", str(tmp_path / "o.ply"),
                 "--iterations", "1", "--height", "1024", "--no-cross-check"]) == 2
    err = capsys.readouterr().err
    assert "--height 1024:" in err and "max_contributions=" in err and "smaller --height" in err
    assert "Traceback" not in err and not (tmp_path / "o.ply").exists()


def test_refine_cli_drops_rows_holding_nan_and_says_so(tmp_path, capsys):
    from rasterizer.ply import ply_bytes, ply_header, property_names

    g = toy_scene(4, n=60)
    data = bytearray(ply_bytes(g))
    body = np.frombuffer(data, dtype="<f4", offset=len(ply_header(len(g), g.sh.shape[1])))
    body.reshape(len(g), len(property_names(g.sh.shape[1])))[3, 10] = np.inf  # scale_0
    (tmp_path / "in.ply").write_bytes(bytes(data))
    assert main([str(tmp_path / "in.ply"), *references(tmp_path), "--out", str(tmp_path / "o.ply"),
                 "--iterations", "1", "--height", "16"]) == 0  # was a GaussiansError traceback
    captured = capsys.readouterr()
    assert "dropped 1 of 60 Gaussians holding NaN or Inf" in captured.err and "row 3, scale_0..2" in captured.err
    assert json.loads(captured.out)["num_gaussians"] == 59 == len(read_ply(tmp_path / "o.ply"))


def test_refine_cli_refuses_to_write_over_its_input(tmp_path, capsys):
    """--out naming the PLY being refined replaced it, where reconstruct and render refuse an output that is
    one of their inputs."""
    from tests.service._support import ply_with_nan

    ply_with_nan(tmp_path / "in.ply", 10, [])
    before = (tmp_path / "in.ply").read_bytes()
    room = str(Path(__file__).resolve().parents[2] / "samples" / "room")
    assert main([str(tmp_path / "in.ply"), room, "--out", str(tmp_path / "in.ply"), "--height", "16",
                 "--iterations", "1"]) == 2
    err = capsys.readouterr().err
    assert f"--out {tmp_path / 'in.ply'} is one of the command's inputs" in err and "Traceback" not in err, err
    assert (tmp_path / "in.ply").read_bytes() == before
