"""Reading scene folders (rasterizer.scene_folder): every malformed scene.json is an error naming the file."""

from __future__ import annotations

import json

import numpy as np
import pytest

from rasterizer.geometry import PoseError
from rasterizer.scene_folder import load_scene

EYE = np.eye(4).tolist()


def _write(root, frames=("a", "b"), **meta):
    scene = {"frames": [{"name": n, "image": f"images/{n}.png", "c2w": EYE} for n in frames], **meta}
    (root / "scene.json").write_text(json.dumps(scene))
    return root / "scene.json"


def test_a_split_whose_references_are_a_string_is_refused(tmp_path):
    """"ab" is no list of frame names: refused, not read letter by letter as frames "a" and "b"."""
    path = _write(tmp_path, splits=[{"references": "ab", "targets": []}])
    with pytest.raises(ValueError, match="lists of frame names, got 'ab'") as info:
        load_scene(tmp_path)
    assert str(info.value).startswith(f"{path}: ")
    _write(tmp_path, splits=[{"references": ["a", "b"], "targets": []}])
    assert load_scene(tmp_path).splits[0].references == ("a", "b")


def test_a_bad_pose_names_the_file_and_the_frame(tmp_path):
    path = _write(tmp_path)
    scene = json.loads(path.read_text())
    scene["frames"][1]["c2w"][0][0] = 2.0  # a scale: not a rigid pose
    path.write_text(json.dumps(scene))
    with pytest.raises(PoseError, match="frame 'b': pose rotation is not orthonormal") as info:
        load_scene(tmp_path)
    assert str(info.value).startswith(f"{path}: ")


def test_a_scene_json_that_is_no_json_names_the_file(tmp_path):
    (tmp_path / "scene.json").write_text("{frames: []}")
    with pytest.raises(ValueError, match="not a JSON file") as info:
        load_scene(tmp_path)
    assert str(info.value).startswith(f"{tmp_path / 'scene.json'}: ")
