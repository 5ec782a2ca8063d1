"""The split's image-only work runs beside the encoder: the scene is the one the split makes after it, to the bit."""

import io

import numpy as np
from PIL import Image

from service.encoder import OnnxEncoder
from service.pipeline import PipelineOptions, build_scene

from ._support import panorama


class _GridsHidden:
    """The encoder without its grid geometry: build_scene cannot prepare the split beside it."""

    def __init__(self, encoder: OnnxEncoder) -> None:
        self._encoder = encoder

    def reconstruct(self, *args, **kwargs):
        return self._encoder.reconstruct(*args, **kwargs)


def test_split_prepared_beside_the_encoder_gives_the_same_scene(model_path):
    enc = OnnxEncoder(model_path)
    uploads = [np.asarray(Image.open(io.BytesIO(panorama(height=2 * enc.height, seed=s, shift=8 * s)))) for s in (5, 6)]
    erp_a, erp_b = uploads  # the encoder resamples them to its input size
    c2w_b = np.eye(4)
    c2w_b[0, 3] = 0.5
    opts = PipelineOptions.from_dict({})
    beside = build_scene(enc, erp_a, erp_b, np.eye(4), c2w_b, opts, uploads=tuple(uploads))
    after = build_scene(_GridsHidden(enc), erp_a, erp_b, np.eye(4), c2w_b, opts, uploads=tuple(uploads))
    rec = enc.reconstruct(erp_a, erp_b, np.eye(4), c2w_b)
    assert tuple(rec.range_maps.shape[2:]) == enc.grid_size  # the geometry the split is prepared for
    assert beside.info["compaction"]["split_textured"]["split"] > 0
    assert "split_detail" in beside.timings and "split_detail" not in after.timings  # the two paths were taken
    for key in ("split", "added"):
        assert beside.info["compaction"]["split_textured"][key] == after.info["compaction"]["split_textured"][key]
    for name in ("means", "scales", "quats", "opacities", "sh"):
        np.testing.assert_array_equal(getattr(beside.gaussians, name), getattr(after.gaussians, name))
