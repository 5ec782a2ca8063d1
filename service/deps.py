"""Dependencies shared by the routes, as ``Annotated`` aliases (state lives on ``app.state``)."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Path, Request

from .config import Settings
from .errors import BadInput, Busy
from .inputs import check_unique_keys
from .limits import WorkGate
from .metrics import ServiceMetrics
from .runtime import ModelRuntime
from .store import SCENE_ID_PATTERN, SceneStore


def _settings(request: Request) -> Settings:
    return request.app.state.settings


def _store(request: Request) -> SceneStore:
    return request.app.state.store


def _metrics(request: Request) -> ServiceMetrics:
    return request.app.state.metrics


def _runtime(request: Request) -> ModelRuntime:
    return request.app.state.runtime


def _ready_runtime(request: Request) -> ModelRuntime:
    runtime: ModelRuntime = request.app.state.runtime
    if not runtime.ready:
        why = f"model failed to load: {runtime.error}" if runtime.error else "the model is still loading"
        raise Busy(f"not ready: {why}", retry_after=request.app.state.settings.retry_after_s, code="not_ready")
    return runtime


def _inference_gate(request: Request) -> WorkGate:
    return request.app.state.inference_gate


def _render_gate(request: Request) -> WorkGate:
    return request.app.state.render_gate


def _heavy_render_gate(request: Request) -> WorkGate:
    return request.app.state.heavy_render_gate


def single_query_values(request: Request) -> None:
    """400 when the query names a parameter twice: the routes would silently keep the last value."""
    seen: set[str] = set()
    for name, _ in request.query_params.multi_items():
        if name in seen:
            raise BadInput(f"the query parameter {name[:40]!r} is given more than once; give it once",
                           code="duplicate_query_parameter", status=400)
        seen.add(name)


async def unique_body_keys(request: Request) -> None:
    """422 when the JSON body names a key twice: the body's model would silently keep the last value."""
    body = await request.body()  # Starlette caches it for the route's own body parameter
    if body:
        check_unique_keys(body)


SettingsDep = Annotated[Settings, Depends(_settings)]
StoreDep = Annotated[SceneStore, Depends(_store)]
MetricsDep = Annotated[ServiceMetrics, Depends(_metrics)]
RuntimeDep = Annotated[ModelRuntime, Depends(_runtime)]
ReadyRuntimeDep = Annotated[ModelRuntime, Depends(_ready_runtime)]
InferenceGateDep = Annotated[WorkGate, Depends(_inference_gate)]
RenderGateDep = Annotated[WorkGate, Depends(_render_gate)]
HeavyRenderGateDep = Annotated[WorkGate, Depends(_heavy_render_gate)]
#: router-level dependency of the routes that read query parameters
SingleQueryValues = Depends(single_query_values)
#: route dependency of the routes that take a JSON body
UniqueBodyKeys = Depends(unique_body_keys)
SceneId = Annotated[str, Path(pattern=SCENE_ID_PATTERN, description="32 lower-case hex digits",
                              examples=["0123456789abcdef0123456789abcdef"])]
