"""The references.npz artifact: np.savez_compressed's layout, read back exactly by np.load."""

import io
import zipfile

import numpy as np

from rasterizer.render import to_uint8
from service.references import references_bytes


def test_references_round_trip_exactly_as_deflated_npy_members():
    rng = np.random.default_rng(3)
    a = rng.integers(0, 256, (8, 16, 3), dtype=np.uint8)
    b = rng.random((8, 16, 3)).astype(np.float32)  # float input is stored as uint8
    data = references_bytes(a, b)
    with zipfile.ZipFile(io.BytesIO(data)) as z:
        assert sorted(z.namelist()) == ["image_a.npy", "image_b.npy"]
        assert all(i.compress_type == zipfile.ZIP_DEFLATED for i in z.infolist())
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        assert z["image_a"].dtype == np.uint8 and np.array_equal(z["image_a"], a)
        assert z["image_b"].dtype == np.uint8 and np.array_equal(z["image_b"], to_uint8(b))
