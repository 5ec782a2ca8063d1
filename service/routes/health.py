"""Liveness, readiness, Prometheus metrics and service/model info."""

from __future__ import annotations

import anyio.to_thread
from fastapi import APIRouter, Request, Response
from fastapi.responses import JSONResponse

from .. import __version__
from ..deps import MetricsDep, RuntimeDep, SettingsDep, StoreDep
from ..schemas import Health, Info, Ready
from ..store import json_safe

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health, summary="Liveness: the process answers")
@router.get("/v2/health/live", response_model=Health, include_in_schema=False)
async def healthz() -> Health:
    return Health(status="ok")


@router.get("/readyz", response_model=Ready, summary="Readiness: model loaded and warmed up, work can be taken",
            responses={503: {"model": Ready, "description": "not ready: the model is loading (or failed to load), "
                                                            "the store cannot take a scene, or every request or "
                                                            "upload slot is in use; `error` says which"}})
@router.get("/v2/health/ready", response_model=Ready, include_in_schema=False)
async def readyz(request: Request, runtime: RuntimeDep, settings: SettingsDep, store: StoreDep) -> Response:
    problem = None
    if runtime.ready:  # and the request slots are not all taken, and the store can take a new scene
        problem = request.app.state.admission.problem()
        if problem is None:
            problem = await anyio.to_thread.run_sync(store.write_problem, settings.min_free_store_bytes)
    loading = None if runtime.ready or runtime.error else "the model is loading and warming up"
    body = Ready(ready=runtime.ready and problem is None, error=runtime.error or problem or loading)
    if body.ready:
        return JSONResponse(body.model_dump())
    return JSONResponse(body.model_dump(), status_code=503, headers={"Retry-After": str(settings.retry_after_s)})


@router.get("/metrics", summary="Prometheus metrics (text exposition format)",
            response_class=Response, responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}}}})
async def metrics(request: Request, metrics: MetricsDep, store: StoreDep) -> Response:
    state = request.app.state
    gates = [state.inference_gate, state.render_gate, state.heavy_render_gate, state.refine_gate]
    data, content_type = metrics.render(store, gates)
    return Response(data, media_type=content_type)


@router.get("/v1/info", response_model=Info, summary="Model name, version, sha256 and the service settings")
async def info(runtime: RuntimeDep, settings: SettingsDep) -> Info:
    model = {k: v for k, v in json_safe(runtime.metadata).items() if k != "path"}  # no server paths
    model["load_seconds"] = runtime.load_seconds
    model["warmup_seconds"] = runtime.warmup_seconds
    return Info(service="omnisplat", service_version=__version__, model=model, ready=runtime.ready,
                settings=settings.public())
