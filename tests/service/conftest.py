"""Fixtures of tests/service: the small ONNX model, exported once per session."""

from pathlib import Path

import pytest

from ._support import small_model


@pytest.fixture(scope="session")
def model_path(tmp_path_factory) -> Path:
    """The small test model (128x256 input, 8 planes)."""
    return small_model(tmp_path_factory)


@pytest.fixture(scope="module")
def client(live):
    """An HTTP client of the module's ``live`` server (each module that asks for it defines ``live``)."""
    with live.client() as c:
        yield c
