"""PLY writing edge cases and the streamed PLY (rasterizer.ply)."""

from __future__ import annotations

import numpy as np
import pytest

from rasterizer.gaussians import Gaussians
from rasterizer.ply import ply_bytes, ply_stream, property_names, read_ply


@pytest.mark.parametrize("sh_degree", [0, 1, 2])
def test_empty_scene_ply_has_a_header_and_no_rows(sh_degree):
    data = ply_bytes(Gaussians.empty(sh_degree))
    assert data.endswith(b"end_header\n")
    assert b"element vertex 0\n" in data
    assert data.count(b"property float") == len(property_names((sh_degree + 1) ** 2))
    assert len(read_ply(data)) == 0


@pytest.mark.parametrize("sh_degree, rows", [(0, 7), (1, 1000), (1, 3)])
def test_streamed_ply_is_the_same_bytes_in_chunks(sh_degree, rows):
    rng = np.random.default_rng(sh_degree)
    n, k = 50, (sh_degree + 1) ** 2
    q = rng.normal(size=(n, 4))
    g = Gaussians(rng.normal(size=(n, 3)), rng.uniform(1e-6, 0.1, (n, 3)), q / np.linalg.norm(q, axis=1, keepdims=True),
                  rng.uniform(0, 1, n), rng.normal(size=(n, k, 3)))
    g.means[3, 1] = np.nan  # dropped by both
    size, chunks = ply_stream(g, rows=rows)
    blocks = list(chunks)
    assert b"".join(blocks) == ply_bytes(g) and size == len(ply_bytes(g))
    assert len(blocks) == 1 + -(-(n - 1) // rows)


def test_compaction_byte_cap_counts_the_header_of_an_sh_degree_1_ply():
    from rasterizer.compaction import ply_bytes_for_count, ply_count_for_bytes

    per = 4 * len(property_names(4))
    header = len(ply_bytes(Gaussians.empty(1)))
    assert ply_count_for_bytes(header + 12 + 10 * per, 4) == 10
    for coeffs in (1, 4):  # the inverse: the fewest bytes that hold a count
        for count in (1, 10):
            need = ply_bytes_for_count(count, coeffs)
            assert ply_count_for_bytes(need, coeffs) == count > ply_count_for_bytes(need - 1, coeffs)
