"""Reference-copy baseline: the nearest reference turned to the target's orientation."""

from __future__ import annotations

import numpy as np

from rasterizer.camera import sample_erp
from rasterizer.geometry import grid_directions, project_to_grid


def rotate_erp(image: np.ndarray, c2w_src: np.ndarray, c2w_dst: np.ndarray, height: int, width: int) -> np.ndarray:
    """The source ERP seen from the destination camera's orientation, depth at infinity."""
    dirs = grid_directions("erp", height, width)  # (H, W, 3) destination camera frame
    rel = c2w_src[:3, :3].T @ c2w_dst[:3, :3]  # destination camera -> source camera
    src_dirs = dirs @ rel.T
    col, row = project_to_grid("erp", src_dirs, image.shape[0], image.shape[1])
    return sample_erp(np.asarray(image, dtype=np.float32), col, row)


def copy_nearest(refs: list[tuple[np.ndarray, np.ndarray]], c2w_target: np.ndarray, height: int, width: int) -> np.ndarray:
    """Prediction of the "copy nearest reference" row: ``refs`` is [(image, c2w), ...]."""
    centre = np.asarray(c2w_target)[:3, 3]
    dists = [np.linalg.norm(np.asarray(c2w)[:3, 3] - centre) for _, c2w in refs]
    image, c2w = refs[int(np.argmin(dists))]
    return rotate_erp(image, np.asarray(c2w), np.asarray(c2w_target), height, width)
