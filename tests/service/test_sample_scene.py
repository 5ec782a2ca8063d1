"""The shipped sample (samples/room) end to end through the CLI: it needs no dev data, so it runs on a fresh clone.

The small test model (128x256, 8 planes) reconstructs 00 + 02; the render at 01, which the model never
saw, must beat the copy floor (the nearest input turned to 01's orientation) by a clear margin, and the
PLY must be a finite 3DGS scene.
"""

from pathlib import Path

import numpy as np

from bench.baselines import copy_nearest
from bench.metrics import psnr
from rasterizer.ply import read_ply
from rasterizer.render import render
from rasterizer.scene_folder import load_scene
from service.cli import main

SAMPLE = Path(__file__).resolve().parents[2] / "samples" / "room"


def test_sample_room_reconstructs_and_beats_the_copy_floor(tmp_path, model_path):
    out = tmp_path / "room.ply"
    assert main(["reconstruct", str(SAMPLE), "-o", str(out), "--model", str(model_path), "--no-build"]) == 0
    g = read_ply(out)
    assert len(g) > 1000 and np.isfinite(g.means).all()

    scene = load_scene(SAMPLE)
    target = scene.frames["01"]
    view = render(g, target.c2w, projection="erp", width=256).colour
    small = _at_256(target.image())  # the 1024x512 target at the render's size
    refs = [(scene.frames[n].image(), scene.frames[n].c2w) for n in ("00", "02")]
    copy = copy_nearest(refs, target.c2w, 512, 1024)
    assert psnr(view, small) > psnr(_at_256(copy), small) + 3.0


def _at_256(image: np.ndarray) -> np.ndarray:
    """A 1024x512 image box-averaged to 256x128, in [0, 1]."""
    img = np.asarray(image, dtype=np.float64)
    img = img / 255.0 if img.max() > 1.0 else img
    return img.reshape(128, 4, 256, 4, 3).mean(axis=(1, 3))
