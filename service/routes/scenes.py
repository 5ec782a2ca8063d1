"""``/v1/scenes``: create from two panoramas, render, download the PLY or SPZ, read metadata, delete."""

from __future__ import annotations

import hashlib
import json
from typing import Annotated

import anyio.to_thread
from fastapi import APIRouter, File, Form, Query, Request, Response, UploadFile
from fastapi.responses import StreamingResponse

from rasterizer.gaussians import MAX_STEP_PER_SIZE

from .. import scenes as work
from ..deps import (
    FormBody,
    HeavyRenderGateDep,
    InferenceGateDep,
    KnownQueryParameters,
    MetricsDep,
    ReadyRuntimeDep,
    RenderGateDep,
    SceneId,
    SettingsDep,
    SingleQueryValues,
    StoreDep,
)
from ..errors import BadInput, NotFound
from ..http_cache import NOT_MODIFIED, cache_headers, is_head, not_modified, renderer_digest
from ..images import MEDIA_TYPES
from ..inputs import (
    DEFAULT_FOV_DEG,
    DEFAULT_RENDER_WIDTH,
    Compositing,
    ImageFormat,
    Projection,
    QueryFloat,
    QueryInt,
    RenderQuery,
    check_render_query,
    check_scale_options,
    check_sweep_range,
    parse_options,
    parse_poses,
)
from ..memory import trimmed
from ..options import options_json_schema, options_markdown
from ..schemas import SceneCreated, SceneMeta, error_responses

router = APIRouter(prefix="/v1/scenes", tags=["scenes"], dependencies=[KnownQueryParameters, SingleQueryValues])

_IDENTITY = "1,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1"
_POSES_EXAMPLE = json.dumps({"convention": "opencv", "c2w": [
    [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
    [[1, 0, 0, 0.5], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]]})
_OPTIONS_DOC = ("optional JSON object (schema `SceneOptions`, strict types: a wrong type or an unknown key is a "
                "422), e.g. `{\"near\": 0.5, \"far\": 20, \"sh_degree\": 0}`. Every key:\n\n" + options_markdown())
_OPTIONS_SCHEMA = {"contentMediaType": "application/json", "contentSchema": options_json_schema()}
_COMPOSITING_DOC = ("`plain` (default): front-to-back alpha compositing over a black background, what every "
                    "3DGS viewer shows of `gaussians.ply`. `va`: colour divided by accumulated alpha (V/A, the "
                    "OmniSplat paper's normalisation), which fills thinly covered pixels with the surface colour "
                    "instead of darkening them. Applies to every projection (ERP through the Yin-Yang merge, "
                    "yin, yang, perspective).")
_RIG_DOC = ("`true`: composite the capture rig (a tripod) that both references show at their nadir over the render, "
            "at the render camera's own nadir, as a capture from that pose would show it. Camera-attached, so not "
            "part of the 3D scene or the PLY; the scene metadata's `rig.detected` says whether the references "
            "show one (otherwise 422). Default `false`: the scene alone, what 3DGS viewers show.")


#: the form fields of POST /v1/scenes; any other is refused (a misspelt "options" would be dropped silently)
FORM_FIELDS = ("image_a", "image_b", "poses", "options")


def _require_scene(store, scene_id: str) -> None:
    if not store.exists(scene_id):
        raise NotFound(f"no scene with id {scene_id!r}", code="scene_not_found")


@router.post(
    "", status_code=201, response_model=SceneCreated, summary="Reconstruct a scene from two ERP panoramas",
    responses=error_responses(400, 408, 413, 415, 422, 503, 507), dependencies=[FormBody],
)
async def create_scene(
    request: Request,
    response: Response,
    image_a: Annotated[UploadFile, File(description="first ERP panorama (PNG/JPEG/WebP/TIFF/BMP, one frame, width = "
                                                    "2 x height as shown: turned by its EXIF orientation)")],
    image_b: Annotated[UploadFile, File(description="second ERP panorama (any 2:1 size)")],
    settings: SettingsDep,
    store: StoreDep,
    runtime: ReadyRuntimeDep,
    gate: InferenceGateDep,
    metrics: MetricsDep,
    options: Annotated[str | None, Form(description=_OPTIONS_DOC, json_schema_extra=_OPTIONS_SCHEMA)] = None,
    poses: Annotated[str | None, Form(description='JSON {"convention": "opencv"|"opengl", "c2w": [A, B]}, '
                                                  "each camera-to-world 4x4 or 3x4 (no other keys but those the "
                                                  "scene metadata's poses add); leave out (or c2w null) to "
                                                  "estimate them from the images (world = camera A, levelled)",
                                      examples=[_POSES_EXAMPLE])] = None,
) -> SceneCreated:
    unknown = sorted(set((await request.form()).keys()) - set(FORM_FIELDS))  # the form FastAPI parsed, cached
    if unknown:
        raise BadInput(f"unknown form field(s) {[name[:40] for name in unknown[:5]]}; this request takes "
                       f"{', '.join(FORM_FIELDS)}", code="unknown_form_field")
    parsed_poses = parse_poses(poses)
    parsed_options, pipeline_options, pose_options = parse_options(options)
    check_scale_options(parsed_poses is not None, pose_options)
    if parsed_poses is not None:  # estimated poses are checked once estimated
        check_sweep_range(parsed_poses.c2w_a, parsed_poses.c2w_b, parsed_options, work.sweep_per_baseline(runtime))
    data_a, data_b = await image_a.read(), await image_b.read()
    limits = work.UploadLimits(settings.max_image_pixels, settings.min_image_height, work.read_width(runtime.encoder.height))
    await anyio.to_thread.run_sync(work.precheck_uploads, data_a, data_b, limits)
    scene_id = await anyio.to_thread.run_sync(
        work.scene_id_for, runtime.sha256, data_a, data_b, parsed_poses, parsed_options)
    response.headers["Location"] = f"/v1/scenes/{scene_id}"
    if (meta := await anyio.to_thread.run_sync(work.stored_whole, store, scene_id)) is not None:
        return SceneCreated(id=scene_id, num_gaussians=meta["num_gaussians"], timings=meta.get("timings", {}),
                            links=work.links(store, scene_id, meta), cached=True)
    await anyio.to_thread.run_sync(work.check_free_space, store, settings.min_free_store_bytes)
    meta, timings = await gate.run(work.storing, work.create_scene, runtime, store, scene_id, data_a, data_b,
                                   parsed_poses, parsed_options, pipeline_options, pose_options, limits)
    metrics.observe_stages(timings)
    metrics.scenes_created.inc()
    return SceneCreated(id=scene_id, num_gaussians=meta["num_gaussians"], timings=timings,
                        links=work.links(store, scene_id, meta))


_IMAGE_CONTENT = {t: {"schema": {"type": "string", "format": "binary"}} for t in MEDIA_TYPES.values()}


@router.get(
    "/{scene_id}/render", response_class=Response, summary="Render a novel view",
    responses={200: {"content": _IMAGE_CONTENT, "description": "the rendered image"}, 304: NOT_MODIFIED,
               **error_responses(400, 404, 413, 422, 503)},
)
async def render_scene(
    request: Request,
    scene_id: SceneId,
    store: StoreDep,
    settings: SettingsDep,
    gate: RenderGateDep,
    heavy_gate: HeavyRenderGateDep,
    metrics: MetricsDep,
    c2w: Annotated[str, Query(description="camera-to-world, 16 (4x4) or 12 (3x4) comma-separated numbers, "
                                          "row-major, OpenCV (x right, y down, z forward)",
                              examples=[_IDENTITY])],
    width: Annotated[QueryInt, Query(description="image width in pixels (ERP: height = width/2; yin/yang: width/3)")
                     ] = DEFAULT_RENDER_WIDTH,
    projection: Annotated[Projection, Query()] = "erp",
    height: Annotated[QueryInt | None, Query(description="perspective only; default = width")] = None,
    fov_deg: Annotated[QueryFloat | None, Query(description="perspective only: horizontal field of view, degrees; "
                                                       f"default {DEFAULT_FOV_DEG:g}")] = None,
    format: Annotated[ImageFormat, Query()] = "png",
    compositing: Annotated[Compositing, Query(description=_COMPOSITING_DOC)] = "plain",
    rig: Annotated[bool, Query(description=_RIG_DOC)] = False,
) -> Response:
    query = check_render_query(c2w, projection, width, height, fov_deg, format,
                               max_width=settings.max_render_width, max_pixels=settings.max_render_pixels,
                               compositing=compositing, rig=rig)
    _require_scene(store, scene_id)
    # every refusal comes before the 304 and the HEAD, which answer for a render without making it
    cost = work.check_render_cost(store, scene_id, query, settings.max_render_cost)
    layer = await gate.run(work.render_rig_layer, store, scene_id, query) if query.rig else None
    etag = _render_etag(scene_id, query)  # the render is a function of the scene and the query
    if (unchanged := not_modified(request, etag)) is not None:
        return unchanged
    if is_head(request):  # RFC 9110 9.3.2: Content-Length, known only once the image is encoded, is left out
        head = Response(media_type=MEDIA_TYPES[format], headers=cache_headers(etag))
        del head.headers["content-length"]
        return head
    if cost > settings.heavy_render_cost:  # big renders queue with reconstructions: their peaks never add
        gate = heavy_gate
    data, timings = await gate.run(trimmed, work.render_scene, store, scene_id, query, layer)
    metrics.observe_stages({f"render_{k}": v for k, v in timings.items()})
    return Response(data, media_type=MEDIA_TYPES[format],
                    headers={**cache_headers(etag),
                             "Server-Timing": ", ".join(f"{k};dur={v * 1000:.1f}" for k, v in timings.items())})


def _render_etag(scene_id: str, query: RenderQuery) -> str:
    """The quoted ETag of a render: a hash of the scene id (itself a content hash), the checked query, the
    renderer's settings for it and the renderer's code."""
    settings = sorted(query.render_kwargs(normalize=query.compositing == "va").items())
    key = (f"{scene_id}|{query.c2w.round(9).tolist()}|{query.projection}|{query.width}|{query.height}|"
           f"{query.fov_deg}|{query.format}|{query.compositing}|{query.rig}|{settings}|{renderer_digest()}")
    return '"' + hashlib.sha256(key.encode()).hexdigest()[:32] + '"'


def _file_download(request: Request, store, scene_id: str, suffix: str) -> tuple[dict[str, str], Response | None]:
    """The headers of a download of the scene's ``gaussians.{suffix}`` (its ETag, a content hash that never
    changes, and the file name), and the 304 to send instead when the client holds it (else None); a 404 for
    an unknown scene."""
    _require_scene(store, scene_id)
    etag = f'"{scene_id}-{suffix}"'
    headers = {**cache_headers(etag), "Content-Disposition": f'attachment; filename="{scene_id}.{suffix}"'}
    return headers, not_modified(request, etag)


def _file_responses(description: str) -> dict:
    """OpenAPI responses of a scene file's download: 200 binary (``description``), 304, the errors."""
    return {200: {"content": {"application/octet-stream": {"schema": {"type": "string", "format": "binary"}}},
                  "description": description}, 304: NOT_MODIFIED, **error_responses(400, 404, 422, 503)}


@router.get(
    "/{scene_id}/gaussians.ply", response_class=StreamingResponse, summary="The Gaussians as a 3DGS PLY",
    responses=_file_responses("binary little-endian INRIA 3DGS PLY in the input world frame"),
)
async def scene_ply(request: Request, scene_id: SceneId, store: StoreDep, gate: RenderGateDep) -> Response:
    headers, unchanged = _file_download(request, store, scene_id, "ply")
    if unchanged is not None:
        return unchanged
    size, blocks = await gate.run(work.ply_stream, store, scene_id)
    headers["Content-Length"] = str(size)
    if is_head(request):  # the same headers; the body (tens of MB) is not made only to be dropped
        blocks.close()
        return Response(headers=headers, media_type="application/octet-stream")

    async def chunks():  # made from the stored arrays block by block, in a worker thread
        while (block := await anyio.to_thread.run_sync(next, blocks, None)) is not None:
            yield block

    return StreamingResponse(chunks(), media_type="application/octet-stream", headers=headers)


@router.get(
    "/{scene_id}/gaussians.spz", response_class=Response, summary="The Gaussians as SPZ (compressed)",
    description="The same Gaussians as `gaussians.ply` in Niantic's SPZ format, version 2 (gzip of 8-bit "
                "colours, opacities, scales, rotations and degree-1 SH, 24-bit fixed-point positions; SPZ's "
                "RUB world, x right, y up, z back): about a fifth of the PLY's bytes, for slow links (the web "
                "viewer loads it with `format=spz`). "
                "Renders of it differ from the PLY's by its quantisation (about 49 dB on a 1024-wide ERP). "
                "422 `spz_unsupported` when a Gaussian lies beyond SPZ's 24-bit positions, or when the scene lies "
                f"so far from the origin that their step exceeds 1/{1 / MAX_STEP_PER_SIZE:g} of the Gaussians' "
                "median size (splats would show moved): download the PLY, or send poses nearer the origin.",
    responses=_file_responses("gzip-compressed SPZ version 2"),
)
async def scene_spz(request: Request, scene_id: SceneId, store: StoreDep, gate: RenderGateDep) -> Response:
    headers, unchanged = _file_download(request, store, scene_id, "spz")
    if unchanged is not None:
        return unchanged
    data = await gate.run(work.spz_file, store, scene_id)
    if is_head(request):
        return Response(headers={**headers, "Content-Length": str(len(data))}, media_type="application/octet-stream")
    return Response(data, media_type="application/octet-stream", headers=headers)


@router.get("/{scene_id}", response_model=SceneMeta, summary="Scene metadata",
            responses=error_responses(400, 404, 422))
async def scene_meta(scene_id: SceneId, store: StoreDep) -> SceneMeta:
    _require_scene(store, scene_id)
    meta = await anyio.to_thread.run_sync(store.meta, scene_id)
    return SceneMeta(**{**meta, "links": work.links(store, scene_id, meta)})


@router.delete("/{scene_id}", status_code=204, response_class=Response, summary="Delete a scene",
               responses=error_responses(400, 404, 422, 507))
async def delete_scene(scene_id: SceneId, store: StoreDep) -> Response:
    if not await anyio.to_thread.run_sync(store.delete, scene_id):
        raise NotFound(f"no scene with id {scene_id!r}", code="scene_not_found")
    return Response(status_code=204)
