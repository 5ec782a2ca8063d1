"""The FastAPI application: :func:`create_app` wires settings, store, model, limits and routes.

    from service.app import create_app
    from service.config import Settings
    app = create_app(Settings(model_path="model.onnx", store_dir="scenes"))

The onnxruntime session is created in the lifespan (in a worker thread, so ``/healthz``
answers at once) and kept on ``app.state.runtime``; ``/readyz`` turns true after it has
loaded and run one warm-up inference. Nothing heavy happens at import time.
"""

from __future__ import annotations

import logging
from contextlib import asynccontextmanager

import anyio
import anyio.to_thread
from fastapi import FastAPI

from . import __version__
from .config import Settings, get_settings
from .errors import install_error_handlers
from .limits import BodySizeLimit, WorkGate
from .metrics import RequestMetrics, ServiceMetrics
from .model_files import ModelUnavailable
from .routes import health, jobs, scenes
from .runtime import ModelRuntime
from .store import SceneStore

log = logging.getLogger("omnisplat.service")

DESCRIPTION = """Two 360-degree ERP panoramas + their poses in, 3D Gaussians out (one ONNX forward pass on
the CPU); novel views rendered by a numpy rasterizer. Poses are camera-to-world, OpenCV axes
(x right, y down, z forward) unless `convention` says `opengl`. Errors are JSON
`{"error": {"code", "message"}}`."""


def create_app(settings: Settings | None = None) -> FastAPI:
    """Build the app; the model is loaded when the app starts (lifespan), not here."""
    settings = settings or get_settings()
    metrics = ServiceMetrics()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        model_path = settings.resolved_model_path
        if not model_path.is_file():
            raise ModelUnavailable(f"model file {model_path} does not exist (run `omnisplat export` or "
                                   "`omnisplat serve`, which builds it)")
        app.state.store = SceneStore(settings.store_dir, cache_scenes=settings.cache_scenes,
                                     cache_bytes=settings.cache_bytes, max_scenes=settings.max_scenes,
                                     tmp_grace_s=settings.store_tmp_grace_s)
        runtime = ModelRuntime(model_path, threads=settings.ort_threads)
        app.state.runtime = runtime

        async def load() -> None:
            # Through the inference limiter: no request inference overlaps the warm-up.
            await anyio.to_thread.run_sync(runtime.load, settings.warmup, abandon_on_cancel=True,
                                           limiter=app.state.inference_gate.limiter)
            metrics.ready.set(1 if runtime.ready else 0)
            if runtime.ready:
                m = runtime.metadata
                metrics.build.labels(model_name=str(m.get("name")), model_version=str(m.get("version")),
                                     model_sha256=str(m.get("sha256"))).set(1)

        async with anyio.create_task_group() as tg:
            tg.start_soon(load)
            try:
                yield
            finally:
                tg.cancel_scope.cancel()
        app.state.runtime.encoder = None

    app = FastAPI(title="omnisplat", version=__version__, description=DESCRIPTION, lifespan=lifespan)
    app.state.settings = settings
    app.state.metrics = metrics
    app.state.inference_gate = WorkGate("inference", settings.inference_concurrency, settings.inference_queue,
                                        settings.retry_after_s, metrics.rejected.labels(kind="inference").inc)
    app.state.render_gate = WorkGate("render", settings.render_concurrency, settings.render_queue,
                                     settings.retry_after_s, metrics.rejected.labels(kind="render").inc)
    install_error_handlers(app)
    app.include_router(health.router)
    app.include_router(scenes.router)
    app.include_router(jobs.router)
    # Last added = outermost: metrics see every request, including 413s from the body limit.
    app.add_middleware(BodySizeLimit, max_bytes=settings.max_upload_bytes, on_reject=metrics.body_rejected.inc)
    app.add_middleware(RequestMetrics, metrics=metrics)
    return app
