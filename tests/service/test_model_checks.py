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


def _edited(model_path, path, *, meta=None, drop_meta=(), drop_outputs=()):
    """A copy of the small exported model with metadata values replaced or removed, or outputs removed."""
    model = onnx.load(str(model_path))
    props = {p.key: p.value for p in model.metadata_props if p.key not in drop_meta}
    props.update(meta or {})
    del model.metadata_props[:]
    onnx.helper.set_model_props(model, props)
    kept = [o for o in model.graph.output if o.name not in drop_outputs]
    del model.graph.output[:]
    model.graph.output.extend(kept)
    onnx.save(model, str(path))
    return path


@pytest.mark.parametrize("edit, says", [
    ({"meta": {"input_height": "256", "input_width": "512"}}, r"its erp_a has shape \[1, 3, 128, 256\]"),
    ({"meta": {"num_planes": "16"}}, r"its warp_grids has shape \[2, 2, 8,"),
    ({"meta": {"feature_height": "32"}}, "its warp_grids has shape"),
    ({"meta": {"gaussian_grid_height": "7"}}, r"its range_maps has shape \[2, 2, 64, 192\]"),
    ({"meta": {"grids": "erp"}}, "its grids is 'erp'; this runtime reads 'yin,yang'"),
    ({"meta": {"erp_encoder": "yes"}}, "its erp_encoder is 'yes'"),
    ({"meta": {"input_height": "abc"}}, "its input_height is 'abc', not a positive integer"),
    ({"meta": {"settings": "{not json"}}, "its settings is not JSON"),
    ({"meta": {"far_per_baseline": "nan"}}, "0 < near < far < inf, got near 0.3, far nan"),
    ({"drop_meta": ("gaussian_grid_height",)}, "it has no 'gaussian_grid_height'"),
    ({"drop_outputs": ("range_maps",)}, "not an omnisplat encoder .it has no output range_maps"),
])
def test_a_model_whose_metadata_disagrees_with_its_graph_is_refused_at_load(model_path, tmp_path, edit, says):
    """Such a model loaded without a word and then failed the warm-up and every reconstruction inside onnxruntime
    (or with a KeyError), so `omnisplat serve --model` started a server that could never turn ready."""
    path = _edited(model_path, tmp_path / "edited.onnx", **edit)
    with pytest.raises(ValueError, match=says):
        OnnxEncoder(path)


def test_a_model_without_matches_still_loads(model_path, tmp_path):
    """Models built before the ``matches`` output serve scenes without edit data."""
    encoder = OnnxEncoder(_edited(model_path, tmp_path / "old.onnx", drop_outputs=("matches",)))
    assert "matches" not in encoder.output_names and encoder.grid_size == (64, 192)


def test_serve_with_a_model_lacking_metadata_is_a_one_line_error(model_path, tmp_path, capsys):
    from service import cli

    path = _edited(model_path, tmp_path / "bare.onnx", drop_meta=("input_height",))
    assert cli.main(["serve", "--model", str(path), "--store", str(tmp_path / "s"), "--port", "0"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--model" in err and "has no 'input_height'" in err and "Traceback" not in err, err
    assert err.count(str(path)) == 1, err  # the file named once
