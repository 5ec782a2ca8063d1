"""The model runtime's warm-up: the first request should find what later ones find."""

import importlib

import numpy as np

from service.inputs import DEFAULT_RENDER_WIDTH
from service.runtime import ModelRuntime


def test_warmup_builds_a_scene_and_renders_the_default_erp(model_path, monkeypatch):
    """The warm-up renders its scene as the API's default ERP (shell apart, at the scene's resolution), so the
    Yin-Yang merge's taps for that size are made before /readyz turns true."""
    render_module = importlib.import_module("rasterizer.render")
    real, calls, depth = render_module.render, [], []

    def spy(gaussians, c2w, **kwargs):  # the render's own passes (the shell's) call it again: keep the outermost
        depth.append(1)
        out = real(gaussians, c2w, **kwargs)
        depth.pop()
        if not depth:
            calls.append((len(gaussians), kwargs, out.colour))
        return out

    monkeypatch.setattr(render_module, "render", spy)
    runtime = ModelRuntime(model_path)
    runtime.load(warmup=True)
    assert runtime.ready and runtime.error is None and runtime.warmup_seconds > 0
    (count, kwargs, colour), = calls
    assert kwargs["projection"] == "erp" and kwargs["width"] == DEFAULT_RENDER_WIDTH and kwargs["resolution"] == "scene"
    assert 0 < kwargs["backdrop"] < count
    assert colour.shape[:2] == (DEFAULT_RENDER_WIDTH // 2, DEFAULT_RENDER_WIDTH) and np.isfinite(colour).all()
