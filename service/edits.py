"""Selections, automatic segments and edits of stored scenes, independent of HTTP (conventions section 3).

A scene built by a model with the ``matches`` output carries the artifact
``edit.npz`` (:class:`rasterizer.edit.scene.EditData`: packed matches, float16
range maps, each Gaussian's provenance). The first selection or segments
request builds the scene's index (superpixels of both references, kept as the
artifact ``edit_index.npz`` and in a small in-memory LRU); after that a
selection is graph work only.

* automatic segments and per-Gaussian segment labels are stored in ``edit_index.npz`` with the
  superpixels when first computed (an edited scene gets them with its Gaussians);
* selection id = content hash of scene id + canonical request; stored as the
  artifact ``selection-<id>.npz`` (per-view ERP masks, selected Gaussians);
* edit result = a new scene with id = content hash of scene id + selection +
  canonical edit (idempotent), ``meta["parent"]`` = the scene, its own
  ``references.npz`` and ``edit.npz`` so it can be selected and edited again.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import time
from collections.abc import Iterator
from typing import TYPE_CHECKING, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, StrictFloat, StrictInt, ValidationInfo, field_validator, model_validator

from rasterizer.gaussians import MAX_STEP_PER_SIZE, step_share, typical_size
from rasterizer.lru import LRUCache
from rasterizer.sweep import MAX_SCENE_EXTENT

from .errors import BadInput, NotFound, ServiceError
from .images import encode
from .inputs import RENDER_CUT_SIGMA, RenderQuery
from .references import REFERENCES_ARTIFACT, ReferencesMissing, load_references
from .store import SCENE_ID_PATTERN, SceneNotFound, SceneStore, canonical_json, content_id

if TYPE_CHECKING:
    from rasterizer.edit.scene import SceneIndex

EDIT_ARTIFACT = "edit.npz"
INDEX_ARTIFACT = "edit_index.npz"
EDIT_VERSION = "edit/v1"
#: Scene indexes kept in memory (each ~30 MB at 512 x 1024).
INDEX_CACHE = 4
#: Reference render width for the uncovered fraction of a removal.
HOLE_RENDER_WIDTH = 512


# -- requests (the HTTP bodies and the CLI's flags) ---------------------------------------------------

#: strict numbers: JSON true or "0.5" is refused, not read as 1 or 0.5
Point = tuple[StrictFloat, StrictFloat]


class SelectionRequest(BaseModel):
    """Points on one reference, or a whole automatic segment."""

    model_config = ConfigDict(extra="forbid")

    view: Literal["a", "b"] | None = Field(None, description="reference the points are on")
    points: list[Point] | None = Field(None, max_length=64, description="positive (u, v) points in [0, 1]")
    negative: list[Point] = Field(default_factory=list, max_length=64, description="negative (u, v) points")
    segment: StrictInt | None = Field(None, ge=0, le=2**31 - 1, description="label of an automatic segment "
                                      "(GET .../segments)")

    @model_validator(mode="after")
    def _one_kind(self):
        if self.segment is not None:
            if self.points or self.negative or self.view is not None:
                raise ValueError("give either a segment or view + points, not both")
            return self
        if self.view is None or not self.points:
            raise ValueError('give "view" ("a" or "b") and at least one positive point, or "segment"')
        return self

    def canonical(self) -> dict:
        if self.segment is not None:
            return {"segment": self.segment}
        # a point on the seam or a pole may be spelt -0.0: one place, one id
        return {"view": self.view, "points": [list(_unsigned_zeros(p)) for p in self.points],
                "negative": [list(_unsigned_zeros(p)) for p in self.negative]}


def check_points(points: list[Point], name: str) -> None:
    """422 unless every (u, v) point lies in [0, 1]: u = (col + 0.5) / W, v = (row + 0.5) / H on the reference's ERP."""
    for k, (u, v) in enumerate(points):
        if not (math.isfinite(u) and math.isfinite(v) and 0.0 <= u <= 1.0 and 0.0 <= v <= 1.0):
            raise BadInput(f"{name}[{k}] = [{u}, {v}]: u and v must lie in [0, 1] (u = (col + 0.5) / W, "
                           "v = (row + 0.5) / H on the reference's ERP)", code="invalid_selection")


def _unsigned_zeros(values: tuple[float, ...] | None) -> tuple[float, ...] | None:
    """``values`` with -0.0 read as 0.0: the same point, colour or offset gives the same canonical request, so the
    same selection or edit id (the content hash would tell -0.0 from 0.0 and store one result twice)."""
    return None if values is None else tuple(v + 0.0 for v in values)


class EditRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")

    selection: str = Field(pattern=SCENE_ID_PATTERN, description="id from POST .../selections")
    op: Literal["remove", "keep", "recolor", "translate"]
    color: tuple[StrictFloat, StrictFloat, StrictFloat] | None = Field(None, description="recolor: RGB in [0, 1]",
                                                                        validate_default=True)
    offset: tuple[StrictFloat, StrictFloat, StrictFloat] | None = Field(
        None, validate_default=True,
        description="translate: world units; a move to where float32 positions step by more than 1/8 of the moved "
                    "Gaussians' median size is refused (invalid_edit)")

    # field validators (``op`` is checked first): an error names the key it is about, so the CLI can name its flag
    @field_validator("color")
    @classmethod
    def _color(cls, color, info: ValidationInfo):
        op = info.data.get("op")
        if op == "recolor" and (color is None or not all(math.isfinite(c) and 0.0 <= c <= 1.0 for c in color)):
            raise ValueError("the recolor op needs r, g, b, each in [0, 1]")
        if op not in (None, "recolor") and color is not None:
            raise ValueError(f"only for the recolor op, not {op}")
        return _unsigned_zeros(color)

    @field_validator("offset")
    @classmethod
    def _offset(cls, offset, info: ValidationInfo):
        op = info.data.get("op")
        if op == "translate" and (offset is None or not all(math.isfinite(c) and abs(c) <= MAX_SCENE_EXTENT
                                                            for c in offset)):
            raise ValueError(f"the translate op needs dx, dy, dz, each within +-{MAX_SCENE_EXTENT:g} (the scenes' extent)")
        if op not in (None, "translate") and offset is not None:
            raise ValueError(f"only for the translate op, not {op}")
        return _unsigned_zeros(offset)


class CorrespondencesMissing(ServiceError):
    status = 409
    code = "correspondences_missing"


_cache: LRUCache[str, SceneIndex] = LRUCache(lambda: INDEX_CACHE)  # scene id -> index; the bound is read at each insert


@contextlib.contextmanager
def scene_reads(store: SceneStore, scene_id: str) -> Iterator[None]:
    """Reads of ``scene_id``'s files: a file that vanishes because the scene was deleted meanwhile is a 404
    (:class:`service.store.SceneNotFound`), not a missing-artifact 409 or a 500."""
    try:
        yield
    except (FileNotFoundError, ReferencesMissing, CorrespondencesMissing):
        if not store.exists(scene_id):
            raise SceneNotFound(scene_id) from None
        raise


def _artifact_bytes(store: SceneStore, scene_id: str, name: str) -> bytes:
    path = store.artifact(scene_id, name)
    if path is None:
        raise FileNotFoundError(name)
    return path.read_bytes()


def edit_artifacts(edit) -> dict[str, bytes]:
    """Artifacts a new scene stores for editing (empty when the model gave no matches)."""
    return {} if edit is None else {EDIT_ARTIFACT: edit.to_bytes()}


def _edit_data(store: SceneStore, scene_id: str):
    from rasterizer.edit.scene import EditData

    path = store.artifact(scene_id, EDIT_ARTIFACT)
    if path is None or store.artifact(scene_id, REFERENCES_ARTIFACT) is None:
        raise CorrespondencesMissing(f"scene {scene_id} has no stored correspondences ({EDIT_ARTIFACT}); "
                                     "it was built by a model without the matches output: rebuild it to edit")
    return EditData.from_bytes(path.read_bytes())


def scene_index(store: SceneStore, scene_id: str):
    """The scene's :class:`rasterizer.edit.scene.SceneIndex` (cached; superpixels stored on first use)."""
    from rasterizer.edit.scene import build_index

    if not store.exists(scene_id):
        raise NotFound(f"no scene with id {scene_id!r}", code="scene_not_found")
    hit = _cache.get(scene_id)
    if hit is not None:
        return hit
    with scene_reads(store, scene_id):
        data = _edit_data(store, scene_id)
        images, _ = load_references(store, scene_id)
        stored = store.artifact(scene_id, INDEX_ARTIFACT)
        saved = None
        if stored is not None:
            with np.load(stored, allow_pickle=False) as z:
                saved = {k: z[k] for k in z.files}
    index = build_index(data, images, labels=None if saved is None else saved["superpixels"])
    if saved is not None and "segments" in saved:
        index.set_segments(saved["segments"], saved["segment_sizes"])
    if saved is None or "gaussian_labels" not in saved:
        store.put_artifact(scene_id, INDEX_ARTIFACT, index_bytes(index))
    _cache.put(scene_id, index)
    return index


def index_bytes(index, keep: np.ndarray | None = None) -> bytes:
    """The ``edit_index.npz`` artifact: superpixels and automatic segments (2, He, We), per-label sizes and the
    per-Gaussian segment labels (N,), optionally for ``gaussians.subset(keep)`` only."""
    labels, sizes = index.segments()
    per_gaussian = index.gaussian_labels()
    buf = io.BytesIO()
    np.savez_compressed(buf, superpixels=index.superpixel_labels(), segments=labels, segment_sizes=sizes,
                        gaussian_labels=per_gaussian if keep is None else per_gaussian[keep])
    return buf.getvalue()


def selection_links(scene_id: str, sel_id: str) -> dict[str, str]:
    base = f"/v1/scenes/{scene_id}/selections/{sel_id}"
    return {"self": base, "mask": f"{base}/mask", "edits": f"/v1/scenes/{scene_id}/edits"}


def _selection_artifact(sel_id: str) -> str:
    return f"selection-{sel_id}.npz"


def create_selection(store: SceneStore, scene_id: str, request: dict) -> dict:
    """Select from ``{"view", "points", "negative"}`` or ``{"segment"}``; returns the 201 body."""
    from rasterizer.edit.scene import select_points, select_segment
    from rasterizer.edit.segment import SelectionError

    request = SelectionRequest.model_validate(request).canonical()  # the CLI's request hashes as the API's does
    sel_id = content_id("selection/v1", scene_id, canonical_json(request))
    t0 = time.perf_counter()
    index = scene_index(store, scene_id)
    t_index = time.perf_counter() - t0
    t0 = time.perf_counter()
    try:
        if request.get("segment") is not None:
            sel = select_segment(index, int(request["segment"]))
        else:
            sel = select_points(index, 0 if request["view"] == "a" else 1, request["points"], request.get("negative") or [])
    except SelectionError as exc:
        code = "unknown_segment" if request.get("segment") is not None else "invalid_selection"
        raise BadInput(str(exc), code=code, status=404 if code == "unknown_segment" else 422) from None
    count = int(sel.gaussians.sum())
    if count == 0 or not sel.masks.any():
        raise BadInput("the selection is empty: no Gaussian comes from the selected pixels; "
                       "place the points on an object", code="empty_selection")
    t_select = time.perf_counter() - t0
    cov = sel.coverage()
    described = {"num_gaussians": count, "coverage": {"a": cov[0], "b": cov[1]}, "consistency": sel.consistency,
                 "level": sel.level, "request": request}
    buf = io.BytesIO()
    np.savez_compressed(buf, masks=np.packbits(sel.masks, axis=-1), shape=np.array(sel.masks.shape),
                        gaussians=np.packbits(sel.gaussians), count=np.array(len(sel.gaussians)),
                        description=np.array(json.dumps(described)))
    store.put_artifact(scene_id, _selection_artifact(sel_id), buf.getvalue())
    return {"id": sel_id, **described, "timings": {"index": t_index, "select": t_select},
            "links": selection_links(scene_id, sel_id)}


def selection_info(store: SceneStore, scene_id: str, sel_id: str) -> dict:
    """The body of ``GET .../selections/{sel_id}``, where a selection's 201 ``Location`` and ``links.self`` point:
    what its 201 said, less the timings; 404 when the scene or the selection is unknown. A selection stored without
    that description is described by what its masks and Gaussians say (count and coverage)."""
    from rasterizer.edit.scene import Selection

    if not store.exists(scene_id):
        raise NotFound(f"no scene with id {scene_id!r}", code="scene_not_found")
    with scene_reads(store, scene_id), np.load(_selection_path(store, scene_id, sel_id), allow_pickle=False) as z:
        described = json.loads(str(z["description"])) if "description" in z.files else None
    if described is None:
        masks, gaussians = load_selection(store, scene_id, sel_id)
        cov = Selection(masks, gaussians, float("nan"), None).coverage()
        described = {"num_gaussians": int(gaussians.sum()), "coverage": {"a": cov[0], "b": cov[1]}}
    return {"id": sel_id, **described, "links": selection_links(scene_id, sel_id)}


def _selection_path(store: SceneStore, scene_id: str, sel_id: str):
    """The file of a stored selection; 404 when the id is not one or no such selection is stored."""
    path = store.artifact(scene_id, _selection_artifact(sel_id)) if len(sel_id) == 32 and sel_id.isalnum() else None
    if path is None:
        raise NotFound(f"no selection {sel_id!r} on scene {scene_id}", code="selection_not_found")
    return path


def load_selection(store: SceneStore, scene_id: str, sel_id: str) -> tuple[np.ndarray, np.ndarray]:
    """(masks (2, He, We) bool, gaussians (N,) bool) of a stored selection; 404 when unknown."""
    if not store.exists(scene_id):
        raise NotFound(f"no scene with id {scene_id!r}", code="scene_not_found")
    path = _selection_path(store, scene_id, sel_id)
    with scene_reads(store, scene_id), np.load(path, allow_pickle=False) as z:
        shape = tuple(int(s) for s in z["shape"])
        masks = np.unpackbits(z["masks"], axis=-1, count=shape[-1]).astype(bool)
        gauss = np.unpackbits(z["gaussians"], count=int(z["count"])).astype(bool)
    return masks, gauss


def _view_image(maps: np.ndarray, view: str, width: int) -> np.ndarray:
    """Nearest-neighbour resize of one view's (He, We[, C]) map to a (width / 2, width) ERP."""
    m = maps[0 if view == "a" else 1]
    he, we = m.shape[:2]
    rows = np.minimum(((np.arange(width // 2) + 0.5) * he / (width // 2)).astype(np.int64), he - 1)
    cols = np.minimum(((np.arange(width) + 0.5) * we / width).astype(np.int64), we - 1)
    return m[rows[:, None], cols[None, :]]


def _render_values(store: SceneStore, scene_id: str, colours: np.ndarray, query: RenderQuery) -> tuple[np.ndarray, np.ndarray]:
    """Render the scene with per-Gaussian flat ``colours`` (N, 3) in [0, 1]: (colour (H, W, 3), alpha (H, W))."""
    from rasterizer.gaussians import rgb_to_sh_dc
    from rasterizer.render import render

    g = store.gaussians(scene_id)
    sh = rgb_to_sh_dc(colours)[:, None, :]
    out = render(g.with_(sh=sh), query.c2w, **query.render_kwargs(normalize=True))
    return out.colour, out.alpha


def mask_png(store: SceneStore, scene_id: str, sel_id: str, view: str | None, width: int,
             query: RenderQuery | None) -> bytes:
    """PNG, 255 = selected: the reference's mask (``view``) or the selected Gaussians rendered at ``query``."""
    masks, gauss = load_selection(store, scene_id, sel_id)
    if query is None:
        img = _view_image(masks, view, width)
    else:
        colour, alpha = _render_values(store, scene_id, np.repeat(gauss[:, None], 3, 1).astype(np.float32), query)
        img = (colour[..., 0] >= 0.5) & (alpha >= 0.5)
    return encode(np.where(img, 255, 0).astype(np.uint8)[..., None].repeat(3, -1), "png")


def segments_png(store: SceneStore, scene_id: str, view: str | None, width: int, query: RenderQuery | None) -> bytes:
    """PNG of the automatic segments: one colour per label (:func:`rasterizer.edit.ops.palette`) in every view;
    black where nothing is rendered."""
    from scipy.spatial import cKDTree

    from rasterizer.edit.ops import palette

    index = scene_index(store, scene_id)
    labels, sizes = index.segments()
    colours = palette(sizes.size)
    if query is None:
        return encode(colours[_view_image(labels, view, width)], "png")
    per_gauss = index.gaussian_labels()
    colour, alpha = _render_values(store, scene_id, colours[per_gauss].astype(np.float32) / 255.0, query)
    present = np.unique(per_gauss)
    nearest = cKDTree(colours[present].astype(np.float32) / 255.0).query(colour.reshape(-1, 3))[1]
    img = colours[present][nearest].reshape(colour.shape)
    img[alpha < 0.5] = 0
    return encode(img, "png")


def edit_id_for(scene_id: str, request: dict) -> str:
    return content_id(EDIT_VERSION, scene_id, canonical_json(request))


def _uncovered(gaussians, masks: np.ndarray, c2ws) -> dict[str, float]:
    """Per reference: fraction of the removed object's pixels no remaining Gaussian covers (alpha < 0.5);
    ``gaussians`` without the environment shell."""
    from rasterizer.render import render

    out = {}
    for v, name in enumerate(("a", "b")):
        if len(gaussians) == 0:
            out[name] = 1.0
            continue
        alpha = render(gaussians, c2ws[v], width=HOLE_RENDER_WIDTH, cut_sigma=RENDER_CUT_SIGMA).alpha  # as the API shows
        m = _view_image(masks, name, HOLE_RENDER_WIDTH)
        out[name] = float((alpha[m] < 0.5).mean()) if m.any() else 0.0
    return out


def check_translated(before, after, moved: np.ndarray) -> None:
    """422 ``invalid_edit`` when a translate edit moves the ``moved`` Gaussians (bool (N,)) beyond
    :data:`MAX_SCENE_EXTENT` from the origin, or to where float32 positions step by more than
    :data:`~rasterizer.gaussians.MAX_STEP_PER_SIZE` of their :func:`~rasterizer.gaussians.typical_size` (and by more
    than where they were): the stored scene, its renders and its PLY would show the moved object scrambled."""
    reach = float(np.abs(after.means[moved]).max(initial=0.0))
    if not reach <= MAX_SCENE_EXTENT:
        raise BadInput(f"the translate edit would move Gaussians beyond {MAX_SCENE_EXTENT:g} from the origin, where "
                       "no camera may render them (earlier translations add up); translate by less",
                       code="invalid_edit")
    if not moved.any():
        return
    step = float(np.spacing(np.float32(reach)))
    size = typical_size(before.scales[moved])
    if step > max(MAX_STEP_PER_SIZE * size, float(np.spacing(np.float32(np.abs(before.means[moved]).max())))):
        raise BadInput(f"the translate edit would move the selection {reach:.4g} from the origin, where float32 positions "
                       f"step by {step:.3g}, {step_share(step, size)} its Gaussians' median size {size:.3g} (at most "
                       f"{MAX_STEP_PER_SIZE:g} keeps them in place): translate by less", code="invalid_edit")


def create_edit(store: SceneStore, scene_id: str, request: dict) -> tuple[dict, bool]:
    """Apply ``request`` ({"selection", "op", "color", "offset"}) and store the result as a new scene.

    Returns (its metadata, created). Idempotent: the same request on the same scene gives the same id.
    """
    request = EditRequest.model_validate(request).model_dump(exclude_none=True)  # one canonical form, one id
    with store.hold(scene_id), scene_reads(store, scene_id):  # the budget never evicts the scene being edited
        return _create_edit(store, scene_id, request)


def _create_edit(store: SceneStore, scene_id: str, request: dict) -> tuple[dict, bool]:
    from rasterizer.edit.ops import edit_gaussians

    _edit_data(store, scene_id)  # 409 before anything else when the scene cannot be edited
    masks, selected = load_selection(store, scene_id, request["selection"])
    new_id = edit_id_for(scene_id, request)
    if store.exists(new_id):
        return store.meta(new_id), False
    t0 = time.perf_counter()
    parent = store.meta(scene_id)
    g = store.gaussians(scene_id)
    if selected.shape != (len(g),):
        raise ServiceError("stored selection does not match the scene's Gaussians", code="store_corrupt", status=500)
    op = request["op"]
    # the environment shell (the last ``shell`` Gaussians) goes with the selected pixels when they are
    # removed, recoloured or moved, but is not part of an extracted object
    shell = np.zeros(len(g), dtype=bool)
    shell[len(g) - int(parent.get("shell", 0)):] = True
    if op == "keep":
        selected = selected & ~shell
    edited = edit_gaussians(g, selected, op, color=request.get("color"), offset=request.get("offset"))
    if len(edited) == 0:  # a scene without Gaussians has no PLY rows, segments or renders worth storing
        advice = "select less" if op == "remove" else "select an object (the environment shell is not kept)"
        raise BadInput(f"the {op} edit would leave a scene without any Gaussian (the selection holds "
                       f"{int(selected.sum())} of {len(g)}); {advice}", code="empty_scene")
    if op == "translate":
        check_translated(g, edited, selected)
    timings = {"edit": time.perf_counter() - t0}
    info = {"op": op, "selection": request["selection"], "num_selected": int(selected.sum())}
    data = _edit_data(store, scene_id)
    keep = None
    if op in ("remove", "keep"):
        keep = ~selected if op == "remove" else selected
        data = data.subset(keep)
        shell = shell[keep]
    if op == "remove":
        t0 = time.perf_counter()
        _, c2ws = load_references(store, scene_id)
        info["uncovered"] = _uncovered(edited.subset(~shell), masks, c2ws)  # the backdrop is no surface
        timings["uncovered"] = time.perf_counter() - t0
    meta = {k: v for k, v in parent.items() if k not in ("id", "num_gaussians", "created_at", "links", "timings")}
    meta.update({"parent": scene_id, "shell": int(shell.sum()), "edit": {**info, "request": request, "version": EDIT_VERSION},
                 "timings": timings, "created_at": time.time()})
    artifacts = {REFERENCES_ARTIFACT: _artifact_bytes(store, scene_id, REFERENCES_ARTIFACT),
                 EDIT_ARTIFACT: data.to_bytes(),
                 INDEX_ARTIFACT: index_bytes(scene_index(store, scene_id), keep)}  # same references: same segments
    if not store.exists(scene_id):  # deleted while the edit ran: its result is not wanted either
        raise SceneNotFound(scene_id)
    return store.put(new_id, edited, meta, artifacts=artifacts), True
