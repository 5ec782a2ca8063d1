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


def _query_names(dependant) -> list[str]:
    """The query parameters a route declares (its own and its dependencies'), in declaration order."""
    names = [param.alias for param in dependant.query_params]
    for sub in dependant.dependencies:
        names += [name for name in _query_names(sub) if name not in names]
    return names


def known_query_parameters(request: Request) -> None:
    """422 ``unknown_query_parameter`` when the query names a parameter the route does not take.

    A misspelt parameter (``fov=30`` for ``fov_deg``, ``fromat``, ``Width``) would otherwise be dropped
    without a word and the answer made with the default. The accepted names are the route's declared
    query parameters (its signature: one source of truth, the OpenAPI document lists the same).
    """
    route = request.scope.get("route")
    accepted = _query_names(route.dependant) if route is not None else []
    unknown = [name for name in request.query_params.keys() if name not in accepted]
    if unknown:
        takes = (f"this request takes {', '.join(accepted)}" if accepted
                 else "this request takes no query parameters")
        raise BadInput(f"unknown query parameter {unknown[0][:40]!r}; {takes}", code="unknown_query_parameter")


def _is_json(content_type: str) -> bool:
    media = content_type.split(";", 1)[0].strip().lower()
    return media == "application/json" or (media.startswith("application/") and media.endswith("+json"))


async def unique_body_keys(request: Request) -> None:
    """415 when a body is not sent as JSON (the route would answer that the body is not an object: its
    ``Content-Type`` makes it unread); 422 when the JSON body names a key twice: the body's model would
    silently keep the last value."""
    body = await request.body()  # Starlette caches it for the route's own body parameter
    if body:
        content_type = request.headers.get("content-type", "")
        if not _is_json(content_type):
            got = f"Content-Type {content_type[:60]!r}" if content_type else "no Content-Type"
            raise BadInput(f"request body: must be a JSON object sent with Content-Type: application/json "
                           f"(got {got})", code="unsupported_media_type", status=415)
        check_unique_keys(body)


#: media types a form arrives in (files need multipart; a urlencoded one is answered field by field)
FORM_MEDIA_TYPES = ("multipart/form-data", "application/x-www-form-urlencoded")


async def form_body(request: Request) -> None:
    """415 when a form route's body is not a form (a JSON object, a bare image): its fields would be read as absent,
    and the answer would only list them as missing."""
    content_type = request.headers.get("content-type", "")
    if content_type.split(";", 1)[0].strip().lower() not in FORM_MEDIA_TYPES:
        got = f"Content-Type {content_type[:60]!r}" if content_type else "no Content-Type"
        raise BadInput(f"request body: must be a multipart/form-data form with the files image_a and image_b "
                       f"(got {got})", code="unsupported_media_type", status=415)


SettingsDep = Annotated[Settings, Depends(_settings)]
StoreDep = Annotated[SceneStore, Depends(_store)]
MetricsDep = Annotated[ServiceMetrics, Depends(_metrics)]
RuntimeDep = Annotated[ModelRuntime, Depends(_runtime)]
ReadyRuntimeDep = Annotated[ModelRuntime, Depends(_ready_runtime)]
InferenceGateDep = Annotated[WorkGate, Depends(_inference_gate)]
RenderGateDep = Annotated[WorkGate, Depends(_render_gate)]
HeavyRenderGateDep = Annotated[WorkGate, Depends(_heavy_render_gate)]
#: router-level dependencies of the routes that read query parameters (and of those that take none)
SingleQueryValues = Depends(single_query_values)
KnownQueryParameters = Depends(known_query_parameters)
#: route dependency of the routes that take a JSON body
UniqueBodyKeys = Depends(unique_body_keys)
#: route dependency of the routes that take a form (POST /v1/scenes)
FormBody = Depends(form_body)
SceneId = Annotated[str, Path(pattern=SCENE_ID_PATTERN, description="32 lower-case hex digits",
                              examples=["0123456789abcdef0123456789abcdef"])]
