"""Read scene folders (conventions section 2): images, optional depth, poses, splits."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image

from .geometry import PoseError, as_c2w


@dataclass(frozen=True)
class Frame:
    name: str
    image_path: Path
    c2w: np.ndarray  # 4x4 OpenCV camera-to-world
    depth_path: Path | None = None

    def image(self) -> np.ndarray:
        """The ERP image as float32 (H, W, 3) in [0, 1]."""
        return load_image(self.image_path)

    def depth(self) -> np.ndarray | None:
        """Euclidean range (H, W) float32 in metres, 0 = unknown; None if absent."""
        if self.depth_path is None:
            return None
        return np.load(self.depth_path).astype(np.float32)


@dataclass(frozen=True)
class Split:
    references: tuple[str, str]
    targets: tuple[str, ...]


@dataclass(frozen=True)
class SceneFolder:
    root: Path
    name: str
    frames: dict[str, Frame]
    splits: tuple[Split, ...]
    meta: dict = field(default_factory=dict)

    @property
    def has_depth(self) -> bool:
        return all(f.depth_path is not None for f in self.frames.values())

    @property
    def convention(self) -> str:
        """The axis convention scene.json writes its poses in; ``frames`` hold OpenCV c2w."""
        return pose_convention(self.meta)


def pose_convention(meta: dict) -> str:
    """The axis convention ("opencv" or "opengl") of a scene.json's poses, OpenCV unless it says otherwise."""
    return meta.get("convention", "opencv")


def load_image(path: str | Path) -> np.ndarray:
    """Read an image file as float32 RGB (H, W, 3) in [0, 1]."""
    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0


def load_scene(root: str | Path) -> SceneFolder:
    """Parse ``root/scene.json``; poses are converted to OpenCV c2w and validated.

    Every error names the scene.json (and the frame, for a pose): a ValueError for a file that is no JSON, a
    frame name given twice, a split whose references are not a list of two known frames; a
    :class:`rasterizer.geometry.PoseError` for a pose. A value of another shape than the layout's (a missing
    key, a number where a list belongs) raises the KeyError or TypeError it meets.
    """
    root = Path(root)
    path = root / "scene.json"
    try:
        meta = json.loads(path.read_text(encoding="utf-8-sig"))  # a byte order mark is no error
    except ValueError as exc:  # invalid JSON or UTF-8
        raise ValueError(f"{path}: not a JSON file ({exc})") from None
    convention = pose_convention(meta)
    frames = {}
    for f in meta["frames"]:
        if f["name"] in frames:  # the second would replace the first without a word
            raise ValueError(f"{path}: the frame name {f['name']!r} appears twice")
        image, depth = root / f["image"], f.get("depth")
        try:
            c2w = as_c2w(f["c2w"], convention)
        except PoseError as exc:
            raise PoseError(f"{path}: frame {f['name']!r}: {exc}") from None
        frames[f["name"]] = Frame(name=f["name"], image_path=image, c2w=c2w,
                                  depth_path=(root / depth) if depth else None)
    splits = []
    for s in meta.get("splits", []):
        refs, targets = s["references"], s["targets"]
        if not (isinstance(refs, list) and isinstance(targets, list)):  # a string would be read letter by letter
            raise ValueError(f"{path}: a split's references and targets are lists of frame names, got {refs!r} "
                             f"and {targets!r}")
        if len(refs) != 2:
            raise ValueError(f"{path}: a split needs exactly two references, got {refs}")
        missing = [n for n in refs + targets if n not in frames]
        if missing:
            raise ValueError(f"{path}: split names unknown frames {missing}")
        splits.append(Split(tuple(refs), tuple(targets)))
    return SceneFolder(root, meta.get("name", root.name), frames, tuple(splits), meta)
