"""PLY writing edge cases and the streamed PLY (rasterizer.ply)."""

from __future__ import annotations

import numpy as np
import pytest

from rasterizer.gaussians import Gaussians
from rasterizer.ply import ply_bytes, property_names, read_ply


@pytest.mark.parametrize("sh_degree", [0, 1, 2])
def test_empty_scene_ply_has_a_header_and_no_rows(sh_degree):
    data = ply_bytes(Gaussians.empty(sh_degree))
    assert data.endswith(b"end_header\n")
    assert b"element vertex 0\n" in data
    assert data.count(b"property float") == len(property_names((sh_degree + 1) ** 2))
    assert len(read_ply(data)) == 0
