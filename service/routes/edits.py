"""Selections, segments and edits (conventions section 3):
``POST /v1/scenes/{id}/selections``, ``GET .../selections/{sel}/mask``, ``GET .../segments``,
``POST /v1/scenes/{id}/edits``. Work is in :mod:`service.edits`; these routes parse and dispatch."""

from __future__ import annotations

from typing import Annotated, Literal

import anyio.to_thread
from fastapi import APIRouter, Body, Path, Query, Request, Response
from pydantic import BaseModel, ConfigDict, Field

from .. import edits as work
from ..deps import (
    KnownQueryParameters,
    RenderGateDep,
    SceneId,
    SettingsDep,
    SingleQueryValues,
    StoreDep,
    UniqueBodyKeys,
)
from ..edits import EditRequest, SelectionRequest
from ..errors import BadInput, NotFound
from ..inputs import DEFAULT_RENDER_WIDTH, Projection, QueryFloat, QueryInt, check_render_query
from ..scenes import links, storing
from ..schemas import SceneCreated, error_responses
from ..store import SCENE_ID_PATTERN

router = APIRouter(prefix="/v1/scenes", tags=["edit"], dependencies=[KnownQueryParameters, SingleQueryValues])


class SelectionCreated(BaseModel):
    model_config = ConfigDict(extra="allow")

    id: str
    num_gaussians: int
    coverage: dict[str, float] = Field(description="fraction of each reference's sphere in the mask")
    links: dict[str, str]


#: render-query parameters that only a ``c2w`` view takes
_VIEW_PARAMS = ("projection", "height", "fov_deg")


def _view_or_query(request: Request, settings, view, c2w, width, projection, height, fov_deg):
    if (view is None) == (c2w is None):
        raise BadInput("give either view=a|b or c2w= (+ the render query)", code="invalid_render_query")
    ignored = [name for name in _VIEW_PARAMS if name in request.query_params]
    if view is not None and ignored:  # a reference's own ERP: they would be dropped without a word
        raise BadInput(f"{ignored[0]}: only with c2w=; view={view} is reference {view}'s own ERP (width only)",
                       code="invalid_render_query")
    if view is not None:
        if not (8 <= width <= settings.max_render_width and width % 2 == 0):
            raise BadInput(f"width: an even number between 8 and {settings.max_render_width}, got {width}",
                           code="invalid_render_query")
        return None
    return check_render_query(c2w, projection, width, height, fov_deg, "png",
                              max_width=settings.max_render_width, max_pixels=settings.max_render_pixels)


def _require(store, scene_id: str) -> None:
    if not store.exists(scene_id):
        raise NotFound(f"no scene with id {scene_id!r}", code="scene_not_found")


@router.post("/{scene_id}/selections", status_code=201, response_model=SelectionCreated, dependencies=[UniqueBodyKeys],
             summary="Select an object from points (or a segment) in both references",
             responses=error_responses(400, 404, 409, 415, 422, 507))
async def create_selection(scene_id: SceneId, store: StoreDep, gate: RenderGateDep, response: Response,
                           body: Annotated[SelectionRequest, Body()]) -> SelectionCreated:
    work.check_points(body.points or [], "points")
    work.check_points(body.negative, "negative")
    _require(store, scene_id)
    out = await gate.run(storing, work.create_selection, store, scene_id, body.canonical())
    response.headers["Location"] = out["links"]["self"]
    return SelectionCreated(**out)


@router.get("/{scene_id}/selections/{sel_id}", response_model=SelectionCreated, summary="A stored selection",
            description="What the selection's 201 answered (its `Location` and `links.self` point here), less the "
                        "timings.", responses=error_responses(400, 404, 422))
async def selection(scene_id: SceneId, sel_id: Annotated[str, Path(pattern=SCENE_ID_PATTERN)],
                    store: StoreDep) -> SelectionCreated:
    return SelectionCreated(**await anyio.to_thread.run_sync(work.selection_info, store, scene_id, sel_id))


@router.get("/{scene_id}/selections/{sel_id}/mask", response_class=Response, summary="Selection mask (PNG)",
            responses={200: {"content": {"image/png": {}}}, **error_responses(400, 404, 409, 422, 507)})
async def selection_mask(request: Request, scene_id: SceneId, sel_id: Annotated[str, Path(pattern=SCENE_ID_PATTERN)],
                         store: StoreDep, settings: SettingsDep, gate: RenderGateDep,
                         view: Literal["a", "b"] | None = None, c2w: str | None = None,
                         width: Annotated[QueryInt, Query()] = DEFAULT_RENDER_WIDTH,
                         projection: Annotated[Projection, Query()] = "erp",
                         height: QueryInt | None = None, fov_deg: QueryFloat | None = None) -> Response:
    query = _view_or_query(request, settings, view, c2w, width, projection, height, fov_deg)
    _require(store, scene_id)
    data = await gate.run(storing, work.mask_png, store, scene_id, sel_id, view, width, query)
    return Response(data, media_type="image/png")


@router.get("/{scene_id}/segments", response_class=Response, summary="Automatic segments (PNG)",
            responses={200: {"content": {"image/png": {}}}, **error_responses(400, 404, 409, 422, 507)})
async def segments(request: Request, scene_id: SceneId, store: StoreDep, settings: SettingsDep, gate: RenderGateDep,
                   view: Literal["a", "b"] | None = None, c2w: str | None = None,
                   width: Annotated[QueryInt, Query()] = DEFAULT_RENDER_WIDTH,
                   projection: Annotated[Projection, Query()] = "erp",
                   height: QueryInt | None = None, fov_deg: QueryFloat | None = None) -> Response:
    query = _view_or_query(request, settings, view, c2w, width, projection, height, fov_deg)
    _require(store, scene_id)
    data = await gate.run(storing, work.segments_png, store, scene_id, view, width, query)
    return Response(data, media_type="image/png")


@router.post("/{scene_id}/edits", status_code=201, response_model=SceneCreated, dependencies=[UniqueBodyKeys],
             summary="Edit the selected Gaussians; the result is a new scene (idempotent id)",
             responses=error_responses(400, 404, 409, 415, 422, 507))
async def create_edit(scene_id: SceneId, store: StoreDep, gate: RenderGateDep, response: Response,
                      body: Annotated[EditRequest, Body()]) -> SceneCreated:
    _require(store, scene_id)
    request = body.model_dump(exclude_none=True)
    meta, created = await gate.run(storing, work.create_edit, store, scene_id, request)
    response.headers["Location"] = f"/v1/scenes/{meta['id']}"
    return SceneCreated(id=meta["id"], num_gaussians=meta["num_gaussians"], timings=meta.get("timings", {}),
                        links=links(store, meta["id"], meta), cached=not created)
