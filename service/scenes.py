"""Scene work, independent of HTTP: build a scene from two uploads, render it, export its PLY.

Functions here are blocking (numpy, onnxruntime, disk) and run in worker threads through
a :class:`service.limits.WorkGate`; routes only parse, dispatch and shape responses.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import BadInput, ServiceError
from .images import check_header, decode_rgb, encode, to_uint8_safe
from .inputs import Poses, RenderQuery
from .jobs import REFERENCES_ARTIFACT, references_bytes
from .pipeline import PipelineOptions, build_scene
from .poses import PoseOptions, poses_for_scene
from .runtime import ModelRuntime
from .store import SceneStore, content_id


def links(scene_id: str) -> dict[str, str]:
    base = f"/v1/scenes/{scene_id}"
    return {"self": base, "render": f"{base}/render", "ply": f"{base}/gaussians.ply"}


def scene_id_for(model_sha256: str, image_a: bytes, image_b: bytes, poses: Poses | None, options: dict) -> str:
    """Content hash: same image bytes + poses (or "estimated") + options + model file give the same id."""
    pose_key = "estimated" if poses is None else \
        json.dumps([np.round(poses.c2w_a, 9).tolist(), np.round(poses.c2w_b, 9).tolist()])
    return content_id("scene/v1", model_sha256, hashlib.sha256(image_a).hexdigest(),
                      hashlib.sha256(image_b).hexdigest(), pose_key, json.dumps(options, sort_keys=True))


@dataclass(frozen=True)
class UploadLimits:
    max_pixels: int
    min_height: int


def precheck_uploads(image_a: bytes, image_b: bytes, limits: UploadLimits) -> None:
    """Header-only checks (format, 2:1, size, pixel cap): fast 4xx before queueing for the model."""
    for field, data in (("image_a", image_a), ("image_b", image_b)):
        check_header(data, field, max_pixels=limits.max_pixels, min_height=limits.min_height)


def _at_model_size(erp: np.ndarray, runtime: ModelRuntime) -> np.ndarray:
    """The panorama at the encoder's input size (what refinement compares renders against)."""
    from rasterizer.yin_yang import resize_erp

    height = int(runtime.metadata.get("input_height") or erp.shape[0])
    if erp.shape[0] == height:
        return erp
    return resize_erp(np.asarray(erp, dtype=np.float32) / 255.0, height, 2 * height)


def create_scene(runtime: ModelRuntime, store: SceneStore, scene_id: str, image_a: bytes, image_b: bytes,
                 poses: Poses | None, options: dict, limits: UploadLimits) -> tuple[dict, dict[str, float]]:
    """Decode, reconstruct and store; returns (scene metadata, this run's stage timings)."""
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    erp_a, head_a = decode_rgb(image_a, "image_a", max_pixels=limits.max_pixels, min_height=limits.min_height)
    erp_b, head_b = decode_rgb(image_b, "image_b", max_pixels=limits.max_pixels, min_height=limits.min_height)
    timings["decode"] = time.perf_counter() - t0

    rest = dict(options)
    pose_options = PoseOptions.pop_from(rest)
    try:
        pipeline_options = PipelineOptions.from_dict(rest)
    except ValueError as exc:
        raise BadInput(f"options: {exc}", code="invalid_options") from None
    t0 = time.perf_counter()
    c2w_a, c2w_b, poses_json = poses_for_scene(erp_a, erp_b, poses, pose_options)
    timings["poses"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    build = build_scene(runtime.encoder, erp_a, erp_b, c2w_a, c2w_b, pipeline_options)
    timings.update(build.timings)
    timings.setdefault("reconstruct", time.perf_counter() - t0)
    gaussians = build.gaussians

    meta = {
        "model": {k: runtime.metadata.get(k) for k in ("name", "version", "sha256")},
        "inputs": {"image_a": {**head_a.describe(), "sha256": hashlib.sha256(image_a).hexdigest()},
                   "image_b": {**head_b.describe(), "sha256": hashlib.sha256(image_b).hexdigest()}},
        "poses": poses_json,
        "options": options,
        "info": build.info,
        "compaction": build.info["compaction"],
        "parent": None,
        "created_at": time.time(),
    }
    t0 = time.perf_counter()
    meta["timings"] = timings
    references = {REFERENCES_ARTIFACT: references_bytes(*(_at_model_size(img, runtime) for img in (erp_a, erp_b)))}
    stored = store.put(scene_id, gaussians, meta, artifacts=references)
    timings["store"] = time.perf_counter() - t0
    return stored, timings


def render_scene(store: SceneStore, scene_id: str, query: RenderQuery) -> tuple[bytes, dict[str, float]]:
    """Render one view of a stored scene to PNG/JPEG bytes; never returns NaN pixels."""
    from rasterizer.render import render  # renderer owner's module; numpy only

    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    gaussians = store.gaussians(scene_id)
    timings["load"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    kwargs = {"projection": query.projection, "width": query.width, "normalize": True}  # no black holes
    if query.projection == "perspective":
        kwargs.update(height=query.height, fov_deg=query.fov_deg)
    out = render(gaussians, query.c2w, **kwargs)
    timings["render"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    rgb = to_uint8_safe(out.colour)
    h, w = query.output_size()
    if rgb.shape[:2] != (h, w):
        raise ServiceError(f"renderer returned {rgb.shape[:2]}, expected {(h, w)}", code="render_failed",
                           status=500)
    data = encode(rgb, query.format)
    timings["encode"] = time.perf_counter() - t0
    return data, timings


def ply_path(store: SceneStore, scene_id: str) -> Path:
    """The scene's PLY on disk, written (atomically) on first request."""
    existing = store.artifact(scene_id, "gaussians.ply")
    if existing is not None:
        return existing
    from rasterizer.ply import ply_bytes

    return store.put_artifact(scene_id, "gaussians.ply", ply_bytes(store.gaussians(scene_id)))
