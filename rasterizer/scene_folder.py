"""Read scene folders (conventions section 2): images, optional depth, poses, splits."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image

from .geometry import as_c2w


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
    """Parse ``root/scene.json``; poses are converted to OpenCV c2w and validated."""
    root = Path(root)
    meta = json.loads((root / "scene.json").read_text(encoding="utf-8-sig"))  # a byte order mark is no error
    convention = pose_convention(meta)
    frames = {}
    for f in meta["frames"]:
        if f["name"] in frames:  # the second would replace the first without a word
            raise ValueError(f"{root}: the frame name {f['name']!r} appears twice")
        depth = f.get("depth")
        frames[f["name"]] = Frame(
            name=f["name"],
            image_path=root / f["image"],
            c2w=as_c2w(f["c2w"], convention),
            depth_path=(root / depth) if depth else None,
        )
    splits = []
    for s in meta.get("splits", []):
        refs = tuple(s["references"])
        if len(refs) != 2:
            raise ValueError(f"{root}: a split needs exactly two references, got {refs}")
        missing = [n for n in refs + tuple(s["targets"]) if n not in frames]
        if missing:
            raise ValueError(f"{root}: split names unknown frames {missing}")
        splits.append(Split(refs, tuple(s["targets"])))
    return SceneFolder(root, meta.get("name", root.name), frames, tuple(splits), meta)
