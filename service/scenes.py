"""Scene work, independent of HTTP: build a scene from two uploads, render it, export its PLY.

Functions here are blocking (numpy, onnxruntime, disk) and run in worker threads through
a :class:`service.limits.WorkGate`; routes only parse, dispatch and shape responses.
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, Callable, TypeVar

import numpy as np

from rasterizer.camera import DEFAULT_NEAR, camera_directions
from rasterizer.render import to_uint8
from rasterizer.rig import NoRigError, RigLayer, overlay_rig, require_rig_layer
from rasterizer.threads import map_threads

from .edits import EDIT_ARTIFACT, edit_artifacts
from .encoder import unit_image_at_size
from .errors import BadInput, ServiceError, StoreUnavailable
from .images import check_header, decode_rgb, encode
from .inputs import Poses, RenderQuery, check_estimated_scale, check_sweep_range
from .limits import check_render_budget
from .memory import release_memory
from .model_files import build_code_hash
from .photometric import MAX_ERP_WIDTH
from .pipeline import PipelineOptions, SceneBuild, build_scene
from .pose_check import check_given_poses
from .poses import PoseOptions, poses_for_scene
from .references import REFERENCES_ARTIFACT, load_references, references_bytes
from .runtime import ModelRuntime
from .store import SceneStore, StoreCorrupt, content_id

T = TypeVar("T")
log = logging.getLogger("omnisplat.service")

#: render near cull as a fraction of the scene's sweep near (scenes smaller than a room)
NEAR_CULL_PER_SWEEP_NEAR = 0.1


def storing(fn: Callable[..., T], *args: Any) -> T:
    """``fn(*args)`` in the worker (``WorkGate.run(storing, fn, ...)``), then free memory goes back to the system.
    A write the store refused (:class:`service.store.StoreFull`) leaves it as the 507 :func:`~service.errors.translate`
    makes, saying which limit refused it."""
    try:
        return fn(*args)
    finally:
        release_memory(force=True)  # after a reconstruction or an edit: its arrays are freed now


def links(store: SceneStore, scene_id: str, meta: dict) -> dict[str, str | None]:
    """The URLs of a stored scene (:class:`service.schemas.Links`): itself, its renders, downloads and viewer; the
    selections, segments and edits of its objects when it keeps the correspondences they read (null otherwise:
    a refinement that changed the Gaussians' count drops them); the scene it was made from (an edit's or a
    refinement's ``parent``; null for a reconstruction, and once that scene is deleted or evicted, so that every
    link answers). ``meta``: the scene's metadata, which every caller holds."""
    base = f"/v1/scenes/{scene_id}"
    editable = store.artifact(scene_id, EDIT_ARTIFACT) is not None
    parent = meta.get("parent")
    parent = parent if isinstance(parent, str) and store.exists(parent) else None
    return {"self": base, "render": f"{base}/render", "ply": f"{base}/gaussians.ply", "spz": f"{base}/gaussians.spz",
            "viewer": f"{base}/viewer", **{name: f"{base}/{name}" if editable else None
                                           for name in ("selections", "segments", "edits")},
            "parent": None if parent is None else f"/v1/scenes/{parent}"}


def scene_id_for(model_sha256: str, image_a: bytes, image_b: bytes, poses: Poses | None, options: dict) -> str:
    """Content hash: same image bytes + poses (or "estimated") + options + model file + build code give the same id."""
    pose_key = "estimated" if poses is None else \
        json.dumps([np.round(poses.c2w_a, 9).tolist(), np.round(poses.c2w_b, 9).tolist()])
    return content_id("scene/v1", model_sha256, build_code_hash(), hashlib.sha256(image_a).hexdigest(),
                      hashlib.sha256(image_b).hexdigest(), pose_key, json.dumps(options, sort_keys=True))


@dataclass(frozen=True)
class UploadLimits:
    max_pixels: int
    min_height: int
    min_width: int | None = None  # JPEGs wider than twice this decode at a reduced scale (service.images.jpeg_reduction)


def stored_whole(store: SceneStore, scene_id: str) -> dict | None:
    """The metadata of the stored scene a POST names when its metadata and Gaussians read whole, else None: not
    stored, or stored but damaged (:class:`~service.store.StoreCorrupt`: a truncated or foreign file), which is then
    removed so that the POST builds it again instead of answering "cached" for a scene no render can read."""
    if not store.exists(scene_id):
        return None
    try:
        meta = store.meta(scene_id)
        store.gaussians(scene_id)
        return meta
    except StoreCorrupt as exc:
        log.warning("store: %s; removed, the POST builds it again", exc)
        store.delete(scene_id)
        return None


def precheck_uploads(image_a: bytes, image_b: bytes, limits: UploadLimits) -> None:
    """Header-only checks (format, 2:1, size, pixel cap): fast 4xx before queueing for the model."""
    for field, data in (("image_a", image_a), ("image_b", image_b)):
        check_header(data, field, max_pixels=limits.max_pixels, min_height=limits.min_height, min_width=limits.min_width)


def _at_model_size(erp: np.ndarray, height: int) -> np.ndarray:
    """The panorama at the encoder's input size: fed to the encoder and kept for refinement."""
    if erp.shape[0] == height:
        return erp
    return unit_image_at_size(erp, height, 2 * height)


def check_free_space(store: SceneStore, need_bytes: int) -> None:
    """507 before any work when the store's disk has less than ``need_bytes`` free."""
    try:
        free = shutil.disk_usage(store.root).free
    except OSError as exc:
        raise StoreUnavailable(f"the scene store cannot be read ({exc.strerror})") from None
    if free < need_bytes:
        raise StoreUnavailable(f"the scene store's disk has {free} bytes free, less than the {need_bytes} "
                               "a new scene may need; no work was done")


#: The options that set the compaction steps able to empty a scene, as the API names them (the CLI passes its flags).
STEP_OPTIONS = {"min_opacity": "min_opacity (with compaction.min_confidence)",
                "cap": "compaction.max_count / compaction.max_bytes"}


def check_not_empty(build: SceneBuild, step_names: dict[str, str] = STEP_OPTIONS) -> None:
    """422 ``empty_scene`` when no Gaussian survived the reconstruction (the API's POST and the CLI's reconstruct).

    When compaction removed every Gaussian the encoder gave, the message names the options that did it
    (``step_names``: compaction step -> option or flag): near/far, poses and images did not empty the scene then."""
    if len(build.gaussians):
        return
    stats = build.info.get("compaction") or {}
    removed = stats.get("removed") or {}
    parts = [f"{name} removed {removed[step]}" for step, name in step_names.items() if removed.get(step)]
    counts = f"of the {stats.get('input')} Gaussians the encoder gave, {', '.join(parts)}" if parts else ""
    if parts and stats.get("output") == 0:
        raise BadInput(f"the reconstruction is empty: {counts}; loosen that setting (a lower opacity threshold, "
                       "a larger cap)", code="empty_scene")
    raise BadInput("the reconstruction is empty: no Gaussian survived (near/far, poses or images leave nothing to "
                   f"triangulate; sweep range {build.info.get('near')}..{build.info.get('far')})"
                   + (f"; {counts}" if counts else ""), code="empty_scene")


def create_scene(runtime: ModelRuntime, store: SceneStore, scene_id: str, image_a: bytes, image_b: bytes,
                 poses: Poses | None, options: dict, pipeline_options: PipelineOptions,
                 pose_options: PoseOptions, limits: UploadLimits) -> tuple[dict, dict[str, float]]:
    """Decode, reconstruct and store; returns (scene metadata, this run's stage timings)."""
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    # side by side (Pillow's decoders release the GIL); image_a's error is raised first, as in turn
    (erp_a, head_a), (erp_b, head_b) = map_threads(
        lambda data, field: decode_rgb(data, field, max_pixels=limits.max_pixels, min_height=limits.min_height,
                                       min_width=limits.min_width),
        (image_a, image_b), ("image_a", "image_b"))
    timings["decode"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    c2w_a, c2w_b, poses_json = poses_for_scene(erp_a, erp_b, poses, pose_options,
                                               (image_a, image_b))  # features 2048 wide, before the model resample; XMP tilt
    timings["poses"] = time.perf_counter() - t0
    if poses is None:
        check_estimated_scale(c2w_a, c2w_b, pose_options)
        check_sweep_range(c2w_a, c2w_b, options, sweep_per_baseline(runtime))
    t0 = time.perf_counter()
    height = runtime.encoder.height
    uploads = (erp_a, erp_b)  # the split's finer detail (rasterizer.compaction.split)
    erp_a, erp_b = map_threads(_at_model_size, uploads, (height, height))  # resampled once, here
    timings["resample"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    build = build_scene(runtime.encoder, erp_a, erp_b, c2w_a, c2w_b, pipeline_options, uploads=uploads)
    del uploads
    stages = dict(build.timings)
    timings["resample"] += stages.pop("resample", 0.0)  # the encoder's own, after the one above
    timings.update(stages)
    timings.setdefault("reconstruct", time.perf_counter() - t0)
    check_not_empty(build)
    if poses is not None:  # given: do they belong to these images?
        t0 = time.perf_counter()
        if check_given_poses(erp_a, erp_b, c2w_a, c2w_b, build.info.get("mean_confidence"), poses.convention) is not None:
            timings["pose_check"] = time.perf_counter() - t0
    gaussians = build.gaussians

    meta = {
        "model": {k: runtime.metadata.get(k) for k in ("name", "version", "sha256")},
        "inputs": {"image_a": {**head_a.describe(), "sha256": hashlib.sha256(image_a).hexdigest()},
                   "image_b": {**head_b.describe(), "sha256": hashlib.sha256(image_b).hexdigest()}},
        "poses": poses_json,
        "options": options,
        "info": build.info,
        "compaction": build.info["compaction"],
        "shell": build.info["shell"],  # the last ``shell`` Gaussians are the environment shell (rasterizer.shell)
        "rig": build.info["rig"],  # whether the references show a capture rig (rasterizer.rig)
        "parent": None,
        "created_at": time.time(),
    }
    t0 = time.perf_counter()
    meta["timings"] = timings
    references = {REFERENCES_ARTIFACT: references_bytes(erp_a, erp_b)}
    references.update(edit_artifacts(build.edit))  # correspondences for selections / edits (~8 MB at 512 x 1024)
    stored = store.put(scene_id, gaussians, meta, artifacts=references)
    timings["store"] = time.perf_counter() - t0
    return stored, timings


def read_width(model_height: int) -> int:
    """The widest ERP that a reconstruction's stages read: the pose features' and checks' grey panorama
    (:data:`service.photometric.MAX_ERP_WIDTH`) or the split's detail, twice as fine as the grid of a model
    ``model_height`` rows high (:func:`rasterizer.compaction.split.fine_grids`)."""
    return max(MAX_ERP_WIDTH, 4 * model_height)


def sweep_per_baseline(runtime: ModelRuntime) -> tuple[float, float]:
    """The loaded model's automatic near and far per unit of baseline (:func:`rasterizer.sweep.default_near_far`)."""
    return runtime.encoder.near_per_baseline, runtime.encoder.far_per_baseline


def check_render_cost(store: SceneStore, scene_id: str, query: RenderQuery, max_cost: float) -> float:
    """The render's :func:`~service.limits.render_cost` (pixel-Gaussians); 413 beyond ``max_cost``."""
    h, w = query.output_size()
    return check_render_budget(h, w, int(store.meta(scene_id).get("num_gaussians") or 0), max_cost)


def render_rig_layer(store: SceneStore, scene_id: str, query: RenderQuery) -> RigLayer | None:
    """The rig layer a ``rig=true`` render composites (None for ``rig=false``); 422 ``no_rig`` when the
    references show none, 409 when they were not kept. Checked before a 304 or a HEAD, which render nothing."""
    if not query.rig:
        return None
    images, _ = load_references(store, scene_id)
    try:
        return require_rig_layer(*images)
    except NoRigError as exc:
        raise BadInput(f"rig=true: {exc}; render without rig", code="no_rig") from None


def render_scene(store: SceneStore, scene_id: str, query: RenderQuery,
                 layer: RigLayer | None = None) -> tuple[bytes, dict[str, float]]:
    """Render one view of a stored scene to PNG/JPEG bytes; never returns NaN pixels.

    layer: :func:`render_rig_layer`'s answer for this query when the caller already has it.
    """
    from rasterizer.render import render  # renderer owner's module; numpy only

    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    if layer is None:  # before the render: a scene without a rig fails fast
        layer = render_rig_layer(store, scene_id, query)
    gaussians = store.gaussians(scene_id)
    meta = store.meta(scene_id)
    sweep_near = (meta.get("info") or {}).get("near")
    timings["load"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    # plain (default): what every 3DGS viewer shows of the PLY; va: the paper's colour / alpha
    kwargs = query.render_kwargs(normalize=query.compositing == "va")
    if isinstance(sweep_near, (int, float)) and sweep_near > 0:  # cull scaled to the scene (mm baselines)
        kwargs["near"] = min(DEFAULT_NEAR, NEAR_CULL_PER_SWEEP_NEAR * float(sweep_near))
    shell = meta.get("shell")
    if isinstance(shell, int) and not isinstance(shell, bool):  # the shell, last, is rendered at its own resolution
        kwargs["backdrop"] = shell
    out = render(gaussians, query.c2w, **kwargs)
    h, w = query.output_size()
    colour = out.colour
    if layer is not None:
        colour = overlay_rig(colour, camera_directions(query.projection, h, w, query.fov_deg), layer)
    timings["render"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    rgb = to_uint8(colour)
    if rgb.shape[:2] != (h, w):
        raise ServiceError(f"renderer returned {rgb.shape[:2]}, expected {(h, w)}", code="render_failed",
                           status=500)
    data = encode(rgb, query.format)
    timings["encode"] = time.perf_counter() - t0
    return data, timings


def ply_stream(store: SceneStore, scene_id: str) -> tuple[int, Iterator[bytes]]:
    """(size, chunks) of the scene's PLY, made from its stored arrays as it is sent (no second copy on disk).

    The Gaussians are read (or taken from the cache) here, so a scene deleted or evicted while the
    download runs still sends the whole file; one deleted before is a 404.
    """
    from rasterizer.ply import ply_stream as stream

    return stream(store.gaussians(scene_id))


def spz_file(store: SceneStore, scene_id: str) -> bytes:
    """The scene's Gaussians as an SPZ file (:mod:`rasterizer.spz`: about a fifth of the PLY's bytes, made in
    about 0.6 s for 500k Gaussians); a scene SPZ's 24-bit positions cannot hold, or hold only in steps coarser
    than its Gaussians' size allows (:func:`rasterizer.spz.check_position_step`), is a 422 ``spz_unsupported``."""
    from rasterizer.spz import SpzError, spz_bytes

    try:
        return spz_bytes(store.gaussians(scene_id))
    except SpzError as exc:
        raise ServiceError(str(exc), code="spz_unsupported", status=422) from None
