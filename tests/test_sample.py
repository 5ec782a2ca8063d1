"""The shipped sample scene (samples/room): it loads, it is what its script renders, and its
geometry follows docs/conventions.md (checked here with the conventions' own formulas, not with
the script's or the rasterizer's helpers)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from rasterizer.scene_folder import load_scene

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "samples" / "room"


@pytest.fixture(scope="module")
def scene():
    return load_scene(SAMPLE)


@pytest.fixture(scope="module")
def make_sample():
    spec = importlib.util.spec_from_file_location("make_sample", ROOT / "scripts" / "make_sample.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def pixel_rays(c2w: np.ndarray, rows: np.ndarray, cols: np.ndarray, width: int) -> np.ndarray:
    """World unit directions of ERP pixel centres (conventions section 1)."""
    height = width // 2
    lon = (cols + 0.5) / width * 2 * np.pi - np.pi
    lat = np.pi / 2 - (rows + 0.5) / height * np.pi
    d = np.stack([np.cos(lat) * np.sin(lon), -np.sin(lat), np.cos(lat) * np.cos(lon)], axis=-1)
    return d @ c2w[:3, :3].T


def box_exit(origin: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Distance from a point inside an axis-aligned box to its walls along unit rays d (N, 3)."""
    with np.errstate(divide="ignore"):
        t = np.where(d > 0, (hi - origin) / d, (lo - origin) / d)
    return np.where(np.abs(d) < 1e-12, np.inf, t).min(axis=1)


def test_sample_is_a_scene_folder(scene):
    assert scene.meta["convention"] == "opencv" and scene.meta["units"] == "metres"
    assert scene.meta["pose_accuracy"] == "exact"
    assert set(scene.frames) == {"00", "01", "02"}
    assert [(s.references, s.targets) for s in scene.splits] == [(("00", "02"), ("01",))]
    for frame in scene.frames.values():
        rot = frame.c2w[:3, :3]
        np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-5)
        assert np.linalg.det(rot) == pytest.approx(1.0, abs=1e-5)
        np.testing.assert_array_equal(frame.c2w[3], [0, 0, 0, 1])
        with Image.open(frame.image_path) as im:
            assert im.size == (1024, 512) and im.mode == "RGB"
    centres = {n: f.c2w[:3, 3] for n, f in scene.frames.items()}
    baseline = np.linalg.norm(centres["02"] - centres["00"])
    assert 0.8 <= baseline <= 1.0
    # 01 lies between the references
    assert np.linalg.norm(centres["01"] - centres["00"]) < baseline
    assert np.linalg.norm(centres["01"] - centres["02"]) < baseline


def test_sample_depth(scene):
    depth = scene.frames["01"].depth()
    assert depth.shape == (512, 1024) and depth.dtype == np.float32
    assert np.isfinite(depth).all()
    assert (depth > 0).all()  # synthetic: every pixel is known
    assert scene.frames["00"].depth() is None


def test_sample_geometry_follows_the_conventions(scene, make_sample):
    """The depth of 01 is, at every pixel, the distance along the conventions' pixel ray to the room's
    walls, or less where an object stands in front; most pixels see the walls, floor or ceiling."""
    frame = scene.frames["01"]
    depth = frame.depth()
    rows, cols = np.mgrid[0:512, 0:1024]
    d = pixel_rays(frame.c2w, rows.ravel(), cols.ravel(), 1024)
    lo = np.array([make_sample.X0, make_sample.Y_CEIL, make_sample.Z0])
    hi = np.array([make_sample.X1, make_sample.Y_FLOOR, make_sample.Z1])
    room = box_exit(frame.c2w[:3, 3], d, lo, hi).reshape(512, 1024)
    assert (depth <= room + 1e-4).all()
    on_room = np.abs(depth - room) < 1e-4
    assert on_room.mean() > 0.75
    # the top row looks up at the ceiling, 1.1 m above the camera; the bottom row down at the floor
    np.testing.assert_allclose(depth[0], 1.1 / np.cos(np.pi / 1024), rtol=1e-4)
    np.testing.assert_allclose(depth[-1], 1.5 / np.cos(np.pi / 1024), rtol=1e-4)


def test_known_point_projects_to_its_pixel(scene, make_sample):
    """The picture's centre on the right wall (x = +2 m) lands where conventions section 1 puts it:
    camera 01 looks along +z, so +x is at column 3W/4; range = distance to the point."""
    frame = scene.frames["01"]
    zc = np.mean(make_sample.PICTURE["z"])
    yc = np.mean(make_sample.PICTURE["y"])
    point = np.array([make_sample.X1, yc, zc])
    p = frame.c2w[:3, :3].T @ (point - frame.c2w[:3, 3])  # camera frame
    rng = np.linalg.norm(p)
    lon = np.arctan2(p[0], p[2])
    lat = np.arcsin(-p[1] / rng)
    col = int((lon + np.pi) / (2 * np.pi) * 1024)
    row = int((np.pi / 2 - lat) / np.pi * 512)
    assert abs(col - 3 * 1024 // 4) <= 1
    assert frame.depth()[row, col] == pytest.approx(rng, rel=2e-3)
    # the picture hangs above the camera's horizon: its centre is in the upper half
    assert row < 256


def test_script_reproduces_the_shipped_files(scene, make_sample):
    """A band of rows of each shipped image (and of the depth) is what the script renders now."""
    for index, name in enumerate(["00", "01", "02"]):
        frame = scene.frames[name]
        r0, r1 = 200 + 40 * index, 204 + 40 * index
        image, depth = make_sample.render(frame.c2w, index, rows=(r0, r1))
        shipped = np.asarray(Image.open(frame.image_path).convert("RGB"))[r0:r1]
        assert np.abs(image.astype(int) - shipped.astype(int)).max() <= 1
        if name == "01":
            np.testing.assert_allclose(depth, frame.depth()[r0:r1], rtol=1e-6)
    assert make_sample.scene_json()["frames"][1]["c2w"] == np.round(scene.frames["01"].c2w, 6).tolist()
