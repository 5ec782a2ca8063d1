"""The FastAPI application: :func:`create_app` wires settings, store, model, limits and routes.

    from service.app import create_app
    from service.config import Settings
    app = create_app(Settings(model_path="model.onnx", store_dir="scenes"))

Everything stateful (store, work gates, job registry, model) is created in the lifespan;
running refinement jobs are cancelled at shutdown. The onnxruntime session is created in a
worker thread, so ``/healthz`` answers at once, and kept on ``app.state.runtime``; ``/readyz`` turns true after it has
loaded and warmed up (one synthetic scene built and rendered). Nothing heavy happens at import time.
"""

from __future__ import annotations

import logging
from contextlib import asynccontextmanager

import anyio
import anyio.to_thread
from fastapi import FastAPI
from fastapi.middleware.cors import CORSMiddleware

from . import __version__
from .access import AccessGuard, Admission, declare_auth
from .config import Settings, get_settings
from .errors import install_error_handlers
from .http_cache import HEAD_SCOPE_KEY
from .job_state import JobFiles, identity
from .jobs import REFINE_QUEUE, JobRegistry
from .limits import BodySizeLimit, WorkGate
from .metrics import RequestMetrics, ServiceMetrics
from .model_files import ModelUnavailable
from .routes import docs, edits, health, jobs, scenes, viewer
from .runtime import ModelRuntime
from .store import SceneStore

log = logging.getLogger("omnisplat.service")

DESCRIPTION = """Two 360-degree ERP panoramas + their poses in, 3D Gaussians out (one ONNX forward pass on
the CPU); novel views rendered by a numpy rasterizer. Poses are camera-to-world, OpenCV axes
(x right, y down, z forward) unless `convention` says `opengl`. Errors are JSON
`{"error": {"code", "message"}}`."""


class HeadAsGet:
    """ASGI middleware: a ``HEAD`` request runs as the ``GET`` of its path and the body is dropped (RFC 9110
    section 9.3.2: the same status and headers as the GET, ``Content-Length`` included). FastAPI registers GET
    routes without HEAD; here every GET route, the probes included, answers HEAD. The GET's scope carries
    :data:`~service.http_cache.HEAD_SCOPE_KEY`, so that a route whose body is costly to make can skip it."""

    def __init__(self, app) -> None:
        self.app = app

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http" or scope.get("method") != "HEAD":
            await self.app(scope, receive, send)
            return

        async def no_body(message):
            if message["type"] == "http.response.body":
                message = {**message, "body": b""}
            await send(message)

        inner = {**scope, "method": "GET", HEAD_SCOPE_KEY: True}
        try:
            await self.app(inner, receive, no_body)
        finally:  # the matched route, for the metrics outside (they count the HEAD under its path)
            if "route" in inner:
                scope["route"] = inner["route"]


def create_app(settings: Settings | None = None, *, encoder=None) -> FastAPI:
    """Build the app; the model is loaded when the app starts (lifespan), not here. ``encoder``: the settings'
    model already loaded (``omnisplat serve --model`` loads it to check it), which the first start takes instead
    of loading the file again."""
    settings = settings or get_settings()
    metrics = ServiceMetrics()
    preloaded = [encoder] if encoder is not None else []

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        model_path = settings.resolved_model_path
        if not model_path.is_file():
            raise ModelUnavailable(f"model file {model_path} does not exist (run `omnisplat export` or "
                                   "`omnisplat serve`, which builds it)")
        state = app.state
        state.store = SceneStore.from_settings(settings)
        state.inference_gate = WorkGate("inference", settings.inference_concurrency, settings.inference_queue,
                                        settings.retry_after_s, metrics.rejected.labels(kind="inference").inc)
        state.render_gate = WorkGate("render", settings.render_concurrency, settings.render_queue,
                                     settings.retry_after_s, metrics.rejected.labels(kind="render").inc)
        # refinements wait in their own queue but share the inference capacity (the same cores)
        state.refine_gate = WorkGate("refine", settings.inference_concurrency, REFINE_QUEUE, settings.retry_after_s,
                                     metrics.rejected.labels(kind="refine").inc,
                                     limiter=state.inference_gate.limiter)
        state.heavy_render_gate = WorkGate("render_heavy", settings.inference_concurrency, settings.render_queue,
                                           settings.retry_after_s, metrics.rejected.labels(kind="render_heavy").inc,
                                           limiter=state.inference_gate.limiter)
        # job records beside the scenes: every replica sharing the store answers them
        state.jobs = JobRegistry(files=JobFiles(state.store.root / "jobs", identity(settings.replica_id)))
        runtime = ModelRuntime(model_path, threads=settings.ort_threads, encoder=preloaded.pop() if preloaded else None)
        state.runtime = runtime

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
                state.jobs.cancel_all()  # running refinements stop at their next progress report
                tg.cancel_scope.cancel()
        state.runtime.encoder = None

    # /docs with its files served locally (routes/docs.py); no ReDoc, whose page loads from CDNs
    app = FastAPI(title="omnisplat", version=__version__, description=DESCRIPTION, lifespan=lifespan,
                  docs_url=None, redoc_url=None)
    app.state.settings = settings
    app.state.metrics = metrics
    app.state.admission = Admission(settings.max_requests, settings.max_body_readers)  # read by /readyz
    install_error_handlers(app)
    app.include_router(health.router)
    app.include_router(scenes.router)
    app.include_router(jobs.router)
    app.include_router(viewer.router)
    app.include_router(edits.router)
    app.include_router(docs.router)
    make_schema = app.openapi

    def openapi() -> dict:  # FastAPI's schema, once, with the API key's 401 on the paths that check it
        return app.openapi_schema or declare_auth(make_schema())

    app.openapi = openapi
    # Last added = outermost: metrics see every request, including refusals by the guard and body limit.
    if settings.cors_origins:
        app.add_middleware(CORSMiddleware, allow_origins=settings.cors_origins, allow_methods=["GET", "POST", "DELETE"],
                           allow_headers=["Authorization", "X-API-Key", "Content-Type"])
    app.add_middleware(HeadAsGet)  # inside the guard and the metrics, which see the HEAD
    app.add_middleware(BodySizeLimit, max_bytes=settings.max_upload_bytes, on_reject=metrics.body_rejected.inc,
                       timeout_s=settings.body_timeout_s, min_rate=settings.body_min_rate,
                       rate_window_s=settings.body_rate_window_s)
    app.add_middleware(AccessGuard, settings=settings, state=app.state)
    app.add_middleware(RequestMetrics, metrics=metrics)
    return app
