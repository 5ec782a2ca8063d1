"""The loaded model: the onnxruntime encoder, its metadata, and readiness (load + warm-up)."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger("omnisplat.service")


@dataclass
class ModelRuntime:
    """State of the model on ``app.state.runtime``; ``ready`` turns true after the warm-up."""

    model_path: Path
    threads: int = 2
    encoder: Any = None
    metadata: dict = field(default_factory=dict)
    ready: bool = False
    error: str | None = None
    load_seconds: float | None = None
    warmup_seconds: float | None = None

    def load(self, warmup: bool = True) -> None:
        """Create the onnxruntime session (explicit CPU settings inside OnnxEncoder), unless ``encoder`` is one
        already, and warm it up."""
        try:
            start = time.perf_counter()
            from .encoder import OnnxEncoder

            if self.encoder is None:
                self.encoder = OnnxEncoder(self.model_path, threads=self.threads)
            meta = dict(self.encoder.metadata)
            meta.setdefault("name", self.model_path.stem)
            meta.setdefault("version", "unknown")
            meta["path"] = str(self.model_path)
            self.metadata = meta
            self.load_seconds = time.perf_counter() - start
            if warmup:
                start = time.perf_counter()
                self._warmup()
                self.warmup_seconds = time.perf_counter() - start
            self.ready = True
            log.info("model %s loaded in %.2f s, warm-up %.2f s", self.model_path, self.load_seconds,
                     self.warmup_seconds or 0.0)
        except Exception as exc:  # noqa: BLE001 - reported by /readyz, logged here
            self.error = f"{type(exc).__name__}: {exc}"
            log.exception("model failed to load")

    def _warmup(self) -> None:
        """Build a scene of two synthetic panoramas and render it as the API renders a default ERP request:
        onnxruntime's first run, the numpy stages' cached tables and the Yin-Yang merge's taps of the surfels'
        grid are made before the first request. That one still builds the taps of its shell's grid, whose size
        follows the view's scale. Comparing the two panoramas (:func:`service.images.same_picture`, which every POST
        runs) imports and starts OpenCV: 0.07-0.17 s (warm / cold file cache) that the first POST would otherwise pay."""
        from rasterizer.render import render

        from .images import same_picture
        from .inputs import DEFAULT_FOV_DEG, DEFAULT_RENDER_WIDTH, RenderQuery
        from .pipeline import PipelineOptions, build_scene

        img = np.random.default_rng(0).random((self.encoder.height, self.encoder.width, 3), dtype=np.float32)
        c2w_b = np.eye(4)
        c2w_b[2, 3] = 1.0
        scene = build_scene(self.encoder, img, img, np.eye(4), c2w_b, PipelineOptions.from_dict({}))
        query = RenderQuery(np.eye(4), "erp", DEFAULT_RENDER_WIDTH, None, DEFAULT_FOV_DEG, "png", "plain", False)
        render(scene.gaussians, query.c2w, **query.render_kwargs(normalize=False), backdrop=scene.info["shell"])
        same_picture(img, img[::-1])

    @property
    def version(self) -> str:
        return str(self.metadata.get("version", "unknown"))

    @property
    def sha256(self) -> str:
        return str(self.metadata.get("sha256", ""))
