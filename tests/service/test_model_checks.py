"""The runtime refuses ONNX files it cannot feed, with a message that says why, when the model loads."""

import onnx
import pytest
from onnx import TensorProto, helper

from rasterizer.sweep import INPUT_NAMES, WARP_GRIDS_RANK
from service.encoder import OnnxEncoder


def _model(path, names, warp_rank):
    """A tiny graph with the given input names (warp_grids of ``warp_rank`` dims) and one output."""
    inputs = [helper.make_tensor_value_info(n, TensorProto.FLOAT, [2] * (warp_rank if n == "warp_grids" else 2))
              for n in names]
    out = helper.make_tensor_value_info("means", TensorProto.FLOAT, [2, 2])
    graph = helper.make_graph([helper.make_node("Identity", [names[0]], ["means"])], "g", inputs, [out])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.save(model, str(path))
    return path


def test_a_model_with_the_old_warp_layout_is_refused(tmp_path):
    path = _model(tmp_path / "old.onnx", INPUT_NAMES, WARP_GRIDS_RANK + 1)
    with pytest.raises(ValueError, match=r"older exporter .* rebuild it with `omnisplat export`"):
        OnnxEncoder(path)


def test_a_model_with_other_inputs_is_refused(tmp_path):
    path = _model(tmp_path / "other.onnx", ("image",), 2)
    with pytest.raises(ValueError, match="not an omnisplat encoder"):
        OnnxEncoder(path)


def test_a_model_with_other_depth_candidates_is_refused(tmp_path):
    """A graph that reads its candidates in another spacing would place every depth wrongly, without a word."""
    path = _model(tmp_path / "parallax.onnx", INPUT_NAMES, WARP_GRIDS_RANK)
    model = onnx.load(str(path))
    onnx.helper.set_model_props(model, {"candidate_spacing": "parallax"})
    onnx.save(model, str(path))
    with pytest.raises(ValueError, match=r"spaced by 'parallax'.* rebuild it with `omnisplat export`"):
        OnnxEncoder(path)
