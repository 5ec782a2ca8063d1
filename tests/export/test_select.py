"""export.select: torch.where as mask arithmetic, equal for finite values, eager and through onnxruntime."""

import io
import warnings

import numpy as np
import onnx
import onnxruntime as ort
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from export.onnx_export import OPSET
from export.select import select, select_many

_FINITE = st.floats(width=32, allow_nan=False, allow_infinity=False)
_SHAPE = (3, 5)


@settings(max_examples=60, deadline=None)
@given(arrays(np.float32, _SHAPE, elements=_FINITE), arrays(np.float32, _SHAPE, elements=_FINITE),
       arrays(np.bool_, _SHAPE))
def test_select_equals_where_for_finite_values(a, b, cond):
    """Largest floats, subnormals and signed zeros included: the same values as torch.where."""
    ta, tb, tc = torch.from_numpy(a), torch.from_numpy(b), torch.from_numpy(cond)
    want = torch.where(tc, ta, tb).numpy()
    np.testing.assert_array_equal(select(tc, ta, tb).numpy(), want)
    first, second = select_many(tc, (ta, tb), (tb, ta))
    np.testing.assert_array_equal(first.numpy(), want)
    np.testing.assert_array_equal(second.numpy(), torch.where(tc, tb, ta).numpy())


def test_select_takes_numbers_and_broadcasts():
    x = torch.tensor([[-1.0, 2.0, 0.5]])
    cond = torch.tensor([[True], [False]])  # (2, 1) against (1, 3)
    np.testing.assert_array_equal(select(cond, x, -2.0).numpy(), torch.where(cond, x, -2.0).numpy())
    np.testing.assert_array_equal(select(x > 0, 1.5, x).numpy(), [[-1.0, 1.5, 1.5]])


def test_exported_select_has_no_where_and_matches():
    """The point of the helper: no onnxruntime Where node, and onnxruntime gives torch.where's values."""
    class Pick(torch.nn.Module):
        def forward(self, a, b):
            return select(a > b, a, b - 1.0)

    rng = np.random.default_rng(0)
    a, b = (rng.normal(size=(4, 64)).astype(np.float32) for _ in range(2))
    buf = io.BytesIO()
    with warnings.catch_warnings():  # the TorchScript exporter's deprecation notice, as export.onnx_export
        warnings.simplefilter("ignore")
        torch.onnx.export(Pick(), (torch.from_numpy(a), torch.from_numpy(b)), buf, input_names=["a", "b"],
                          opset_version=OPSET, dynamo=False)
    model = onnx.load_from_string(buf.getvalue())
    assert "Where" not in {node.op_type for node in model.graph.node}
    got = ort.InferenceSession(buf.getvalue(), providers=["CPUExecutionProvider"]).run(None, {"a": a, "b": b})[0]
    np.testing.assert_array_equal(got, np.where(a > b, a, b - 1.0))
