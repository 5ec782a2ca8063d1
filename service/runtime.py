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
        """Create the onnxruntime session (explicit CPU settings inside OnnxEncoder) and warm it up."""
        try:
            start = time.perf_counter()
            from .encoder import OnnxEncoder

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
        if hasattr(self.encoder, "warmup"):
            self.encoder.warmup()
            return
        h = int(self.metadata.get("height") or self.metadata.get("input_height") or 64)
        h = max(16, min(h, 1024))
        yy, xx = np.mgrid[0:h, 0 : 2 * h]
        img = np.stack([(xx * 7 % 255), (yy * 5 % 255), ((xx + yy) * 3 % 255)], -1).astype(np.uint8)
        a = np.eye(4)
        b = np.eye(4)
        b[0, 3] = 0.25
        self.encoder.reconstruct(img, np.roll(img, 3, axis=1), a, b)

    @property
    def version(self) -> str:
        return str(self.metadata.get("version", "unknown"))

    @property
    def sha256(self) -> str:
        return str(self.metadata.get("sha256", ""))
