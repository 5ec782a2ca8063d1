"""The `omnisplat render` command line: its query checked as the API checks it, PLY files that hold no Gaussian,
NaN rows or a short header, the render budget, and pose files read as the API reads JSON."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

from rasterizer.ply import write_ply
from service import cli
from tests.service._support import IDENTITY, ply_with_nan, render_argv


def test_render_argument_errors(tmp_path, capsys):
    assert cli.main(["render", "x.ply"]) == 2
    assert "exactly one of" in capsys.readouterr().err
    assert cli.main(["render", "x.ply", "--c2w", "1,2,3"]) == 2
    assert "16" in capsys.readouterr().err


@pytest.mark.parametrize("extra, says", [
    (["--width", "0"], "--width"),  # was a ValueError traceback
    (["--width", "99999999"], "--width"),  # was a MemoryError traceback
    (["--width", "63"], "even width"),  # was a 63 x 31 'ERP'
    (["--projection", "perspective", "--fov-deg", "180"], "--fov-deg"),  # was a traceback
    (["--projection", "perspective", "--width", "1", "--height", "640", "--fov-deg", "120"], "vertically"),  # black rows
    (["--height", "32"], "only a perspective"),  # was ignored
    (["--fov-deg", "30"], "only a perspective"),  # was ignored
    (["-o", "view.gif"], ".png, .jpg or .jpeg"),  # PNG bytes were written to view.gif
])
def test_render_checks_its_query_as_the_api_does_before_reading_the_ply(tmp_path, capsys, extra, says):
    argv = ["render", str(tmp_path / "missing.ply"), "--c2w", IDENTITY, "-o", str(tmp_path / "view.png")]
    if extra[0] == "-o":
        argv[-1] = str(tmp_path / extra[1])
        extra = []
    assert cli.main(argv + extra) == 2
    err = capsys.readouterr().err
    assert says in err and "Traceback" not in err


def test_render_refuses_a_ply_without_gaussians(tmp_path, capsys):
    """A 0-Gaussian PLY rendered an all-black PNG with exit status 0."""
    from rasterizer.gaussians import Gaussians

    write_ply(tmp_path / "empty.ply", Gaussians.empty(1))
    assert cli.main(render_argv(tmp_path, "empty.ply")) == 2
    err = capsys.readouterr().err
    assert "empty.ply: the PLY holds no Gaussians" in err and "Traceback" not in err
    assert not (tmp_path / "view.png").exists()
    ply_with_nan(tmp_path / "nan.ply", 4, range(4))
    assert cli.main(render_argv(tmp_path, "nan.ply")) == 2
    err = capsys.readouterr().err
    assert "holds no Gaussians with finite values" in err and "row 0" in err and not (tmp_path / "view.png").exists()


def test_render_drops_the_rows_holding_nan_as_the_service_does_and_says_so(tmp_path, capsys):
    """One NaN row was a GaussiansError traceback; the service's pipeline and PLY writer drop such rows."""
    ply_with_nan(tmp_path / "nan.ply", 50, [7, 20])
    assert cli.main(render_argv(tmp_path, "nan.ply")) == 0
    err = capsys.readouterr().err
    assert "dropped 2 of 50 Gaussians holding NaN or Inf" in err and "row 7, x, y, z" in err
    assert "rendering 48 Gaussians" in err and "Traceback" not in err
    from PIL import Image

    assert np.asarray(Image.open(tmp_path / "view.png")).max() > 0


@pytest.mark.parametrize("header", [
    b"ply\nformat\nend_header\n",
    b"ply\nformat binary_little_endian 1.0\nelement vertex\nend_header\n",
    b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float\nend_header\n",
])
def test_render_of_a_ply_with_a_short_header_line_is_a_one_line_error(tmp_path, capsys, header):
    (tmp_path / "bad.ply").write_bytes(header)  # each was an IndexError traceback
    assert cli.main(render_argv(tmp_path, "bad.ply")) == 2
    err = capsys.readouterr().err
    assert "cannot read" in err and "malformed PLY header" in err and "Traceback" not in err


def test_render_too_large_for_the_renderer_names_width(tmp_path, capsys, monkeypatch):
    """The rasterizer's RenderLimitError (the API's 413 render_too_large) is a one-line error naming --width."""
    import importlib

    from rasterizer.splat import RenderLimitError

    def too_large(*a, **k):
        raise RenderLimitError("image 64x32 with 50 Gaussians exceeds the 64-bit sort key")

    ply_with_nan(tmp_path / "g.ply", 50, [])
    monkeypatch.setattr(importlib.import_module("rasterizer.render"), "render", too_large)  # the module, not the function
    assert cli.main(render_argv(tmp_path, "g.ply")) == 2
    err = capsys.readouterr().err
    assert "--width 64:" in err and "smaller --width" in err and "Traceback" not in err


def test_render_beyond_the_render_budget_is_a_one_line_error(tmp_path, capsys, monkeypatch):
    """The CLI rendered whatever it was asked, where the API answers 413 render_too_large."""
    ply_with_nan(tmp_path / "g.ply", 50, [])
    monkeypatch.setenv("OMNISPLAT_MAX_RENDER_COST", "1e8")  # a 64x32 view of 50 Gaussians costs about 3.1e8
    assert cli.main(render_argv(tmp_path, "g.ply")) == 2
    err = capsys.readouterr().err
    assert "--width: a 64x32 render of this scene's 50 Gaussians exceeds the render budget" in err
    assert "Traceback" not in err and not (tmp_path / "view.png").exists()
    monkeypatch.setenv("OMNISPLAT_MAX_RENDER_COST", "1e9")
    assert cli.main(render_argv(tmp_path, "g.ply")) == 0


def test_render_that_shows_no_gaussian_says_so(tmp_path, capsys):
    """A camera looking away from every Gaussian wrote an all-black image without a word."""
    ply_with_nan(tmp_path / "g.ply", 50, [])
    argv = render_argv(tmp_path, "g.ply")
    assert cli.main(argv) == 0
    assert "shows none of the" not in capsys.readouterr().err
    away = ["--c2w", "1,0,0,50,0,1,0,0,0,0,1,0,0,0,0,1", "--projection", "perspective"]  # the room is to its left
    assert cli.main(argv[:2] + away + argv[4:]) == 0
    err = capsys.readouterr().err
    assert "the view shows none of the 50 Gaussians" in err and (tmp_path / "view.png").exists()


def test_render_pose_file_with_an_unknown_key_is_refused(tmp_path, capsys):
    (tmp_path / "pose.json").write_text('{"convension": "opengl", "c2w": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}')
    assert cli.main(["render", "x.ply", "--pose", str(tmp_path / "pose.json")]) == 2
    assert "convension" in capsys.readouterr().err


def test_render_pose_file_may_start_with_a_byte_order_mark(tmp_path):
    import argparse

    from service.cli.render import _pose_from_args

    m = [[1, 0, 0, 0.5], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    (tmp_path / "pose.json").write_bytes(b"\xef\xbb\xbf" + json.dumps({"convention": "opencv", "c2w": m}).encode())
    c2w = _pose_from_args(argparse.Namespace(c2w=None, pose=str(tmp_path / "pose.json")))
    np.testing.assert_array_equal(c2w, np.array(m, dtype=float))


@pytest.mark.parametrize("text, says", [
    ('{"c2w": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]], "c2w": [[1,0,0,5],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}', "c2w"),
    ("[" * 100_000 + "]" * 100_000, "not valid JSON"),
])
def test_render_pose_file_is_read_as_the_api_reads_json(tmp_path, capsys, text, says):
    """A repeated key is refused (not the last one taken), too deep a nesting is a one-line error."""
    (tmp_path / "pose.json").write_text(text)
    assert cli.main(["render", "x.ply", "--pose", str(tmp_path / "pose.json"), "-o", str(tmp_path / "o.png")]) == 2
    err = capsys.readouterr().err
    assert "--pose" in err and says in err and "Traceback" not in err


def test_render_refuses_to_overwrite_its_inputs_and_makes_its_folders(tmp_path, capsys):
    ply_with_nan(tmp_path / "g.ply", 50, [])
    from PIL import Image

    Image.new("RGB", (64, 32)).save(tmp_path / "a.png")
    argv = render_argv(tmp_path, "g.ply")[:-1]
    assert cli.main([*argv, str(tmp_path / "a.png"), "--rig", str(tmp_path / "a.png"), str(tmp_path / "a.png")]) == 2
    assert "is one of the command's inputs" in capsys.readouterr().err
    assert cli.main([*argv, str(tmp_path / "new" / "deeper" / "view.png")]) == 0  # as reconstruct makes them
    assert (tmp_path / "new" / "deeper" / "view.png").is_file()


def test_render_reads_spz_as_it_reads_the_ply(tmp_path, capsys):
    """An SPZ file (told from a PLY by its gzip magic) renders as the PLY it came from, within its quantisation."""
    from PIL import Image

    from rasterizer.gaussians import Gaussians
    from rasterizer.spz import spz_bytes

    rng = np.random.default_rng(5)
    n = 400
    d = rng.normal(size=(n, 3))
    g = Gaussians(d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(1.5, 3, (n, 1)), rng.uniform(0.05, 0.2, (n, 3)),
                  rng.normal(size=(n, 4)), rng.uniform(0.3, 1, n), rng.uniform(-0.8, 0.8, (n, 4, 3)))
    write_ply(tmp_path / "s.ply", g)
    (tmp_path / "s.spz").write_bytes(spz_bytes(g))
    images = []
    for name in ("s.ply", "s.spz"):
        assert cli.main(render_argv(tmp_path, name)) == 0, capsys.readouterr().err
        images.append(np.asarray(Image.open(tmp_path / "view.png"), dtype=np.float64) / 255)
    mse = np.mean((images[0] - images[1]) ** 2)
    assert images[0].std() > 0.01 and 10 * np.log10(1 / mse) > 35
    (tmp_path / "bad.spz").write_bytes(b"\x1f\x8b" + b"\x00" * 20)
    assert cli.main(render_argv(tmp_path, "bad.spz")) == 2
    err = capsys.readouterr().err
    assert "cannot read" in err and "bad.spz" in err and "Traceback" not in err


@pytest.mark.skipif(sys.platform == "win32", reason="needs a POSIX file size limit")
def test_render_that_cannot_finish_its_file_leaves_no_partial_one(tmp_path):
    """A write that stops half-way (here a 300-byte file size limit, as a full disk or Ctrl-C stops one) left a
    truncated PNG at -o, over the earlier image: the image is written beside it and renamed when complete."""
    import resource
    import subprocess
    from pathlib import Path

    from tests.rasterizer._support import toy_scene

    write_ply(tmp_path / "s.ply", toy_scene(2, n=200))
    (tmp_path / "view.png").write_bytes(b"the earlier image")
    argv = [sys.executable, "-m", "service.cli", *render_argv(tmp_path, "s.ply")]
    run = subprocess.run(argv, cwd=Path(__file__).resolve().parents[2], capture_output=True, text=True, timeout=120,
                         preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (300, 300)))
    assert run.returncode == 2 and "cannot write" in run.stderr and "Traceback" not in run.stderr, run.stderr
    assert (tmp_path / "view.png").read_bytes() == b"the earlier image"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.ply", "view.png"]
