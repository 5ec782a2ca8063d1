"""Parse and validate the non-image inputs: poses JSON, options JSON, render queries, scene ids.

Every function raises :class:`service.errors.BadInput` (422) with a message naming the
field and the problem; nothing here touches the store or the model.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BeforeValidator, ValidationError

from rasterizer.geometry import PoseError, as_c2w
from rasterizer.sweep import (
    FAR_PER_BASELINE,
    MAX_SCENE_EXTENT,
    MIN_BASELINE,
    NEAR_PER_BASELINE,
    SweepRangeError,
    baseline,
    check_scene_scale,
    default_near_far,
    distinct_numbers,
)

from .errors import BadInput
from .options import SceneOptions, describe_error
from .pipeline import STEP_OPTION_KEYS, PipelineOptions
from .poses import POSE_OPTION_KEYS, PoseOptions

Projection = Literal["erp", "perspective", "yin", "yang"]
ImageFormat = Literal["png", "jpeg"]
#: plain = front-to-back composite over black (what 3DGS viewers show); va = colour / alpha (the paper's V/A)
Compositing = Literal["plain", "va"]
COMPOSITINGS = ("plain", "va")
#: Width in pixels of a render (and of a selection mask) when the request names none.
DEFAULT_RENDER_WIDTH = 1024
#: Horizontal field of view (degrees) of a perspective render when the request names none.
DEFAULT_FOV_DEG = 90.0
#: Every footprint of a plain render of a reconstruction ends this many standard deviations from its centre,
#: but never nearer than 2 px (the 1/255 alpha rule alone reaches 3.33 at opacity 1; GaussianSplats3D cuts at
#: 2.83): the tails carry at most 8% of a
#: Gaussian's centre alpha, which a reconstruction's overlapping surfels hide. Measured on 72 views of the
#: dev scenes, 47 dB or more from the uncut render for 34% less CPU (docs/design.md, "Footprint tails").
RENDER_CUT_SIGMA = 2.25

#: Widest perspective view (degrees) whose footprints are cut. Wider views stretch the footprints towards their
#: rim into radial streaks that lose coverage when cut: at 170 deg, views of the dev scenes moved 40-43 dB from
#: the uncut render (up to 5% of the pixels by more than 8/255), at 160 deg 46.9 dB or more
#: (docs/design.md, "Footprint tails").
CUT_MAX_FOV_DEG = 160.0


def _reject_constant(name: str) -> Any:
    raise ValueError(f"{name} is not allowed")


#: JSON integers beyond this magnitude are refused (a float cannot hold them exactly, a huge one at all)
MAX_JSON_INT = 2**53


def _bounded_int(text: str) -> int:
    """A JSON integer within :data:`MAX_JSON_INT`; its digits are counted first (Python refuses to convert more than
    ``sys.get_int_max_str_digits()`` of them, in words about its own settings)."""
    if len(text.lstrip("-")) > len(str(MAX_JSON_INT)) or abs(value := int(text)) > MAX_JSON_INT:
        raise ValueError(f"integer {text[:20]}{'...' if len(text) > 20 else ''} ({len(text)} digits) is out of "
                         f"range (at most {MAX_JSON_INT} in magnitude)")
    return value


class _DuplicateKey(ValueError):
    pass


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """A JSON object's dict; a key given twice is refused (the parser would keep the last one without a word)."""
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise _DuplicateKey(f"the key {key[:40]!r} is given more than once; give each key once")
        out[key] = value
    return out


def check_unique_keys(text: str | bytes) -> None:
    """BadInput (422 ``invalid_request``) when a JSON object in ``text`` names a key twice.

    Request bodies that FastAPI parses keep the last of repeated keys without a word; the
    routes that take a JSON body run this first. Other JSON errors are left to the body's own
    validation, which names them.
    """
    try:
        json.loads(text, object_pairs_hook=_unique_keys)
    except _DuplicateKey as exc:
        raise BadInput(f"request body: {exc}", code="invalid_request") from None
    except (ValueError, RecursionError):
        pass


def without_bom(text: str | bytes) -> str | bytes:
    """``text`` without a leading UTF-8 byte order mark (editors on Windows write one): every JSON input takes it,
    as JSON request bodies do."""
    if isinstance(text, bytes):
        return text[3:] if text.startswith(b"\xef\xbb\xbf") else text
    return text[1:] if text.startswith("\ufeff") else text


def json_value(text: str | bytes, field: str) -> Any:
    """``text`` parsed as JSON the way every JSON input is: a repeated key, NaN / Infinity, an integer past
    :data:`MAX_JSON_INT` or nesting too deep is a 422 ``invalid_<field>`` naming ``field``."""
    try:
        return json.loads(text, parse_constant=_reject_constant, parse_int=_bounded_int, object_pairs_hook=_unique_keys)
    except _DuplicateKey as exc:
        raise BadInput(f"{field}: {exc}", code=f"invalid_{field}") from None
    except (ValueError, RecursionError) as exc:
        raise BadInput(f"{field}: not valid JSON ({exc})", code=f"invalid_{field}") from None


#: keys of the ``poses`` JSON object
POSES_KEYS = frozenset({"convention", "c2w"})
#: keys the scene metadata's ``poses`` adds (accepted and ignored, so that it can be sent back as it is)
POSES_META_KEYS = frozenset({"input_convention", "source", "support"})


@dataclass(frozen=True)
class Poses:
    convention: str
    c2w_a: np.ndarray  # 4x4 OpenCV float64
    c2w_b: np.ndarray

    def as_json(self) -> dict:
        return {"convention": "opencv", "input_convention": self.convention,
                "c2w": [self.c2w_a.tolist(), self.c2w_b.tolist()]}


def parse_poses(text: str | bytes | None) -> Poses | None:
    """``{"convention": "opencv"|"opengl", "c2w": [A, B]}`` with 4x4 or 3x4 rigid matrices.

    None for no poses (absent, empty, or ``"c2w": null``): the service estimates them.
    """
    text = None if text is None else without_bom(text)
    if text is None or not text.strip():
        return None
    obj = json_value(text, "poses")
    if not isinstance(obj, dict):
        raise BadInput('poses: expected a JSON object {"convention": ..., "c2w": [A, B]}', code="invalid_poses")
    unknown = sorted(set(obj) - POSES_KEYS - POSES_META_KEYS)
    if unknown:  # a misspelt "convention" would otherwise silently mean OpenCV
        raise BadInput(f"poses: unknown key(s) {[str(k)[:40] for k in unknown[:5]]}; expected "
                       '{"convention": "opencv"|"opengl", "c2w": [A, B]}', code="invalid_poses")
    if "c2w" in obj and obj["c2w"] is None:
        return None
    convention = obj.get("convention", "opencv")
    if convention not in ("opencv", "opengl"):
        raise BadInput(f"poses.convention: expected \"opencv\" or \"opengl\", got {json.dumps(convention)[:40]}",
                       code="invalid_poses")
    mats = obj.get("c2w")
    if not isinstance(mats, list) or len(mats) != 2:
        raise BadInput("poses.c2w: expected a list of exactly two matrices [A, B]", code="invalid_poses")
    out = []
    for name, m in zip("AB", mats):
        if not (isinstance(m, list) and all(isinstance(r, list) for r in m)
                and all(isinstance(v, (int, float)) and not isinstance(v, bool) for r in m for v in r)):
            raise BadInput(f"poses.c2w[{name}]: expected a 4x4 or 3x4 list of numbers", code="invalid_pose")
        if len(m) not in (3, 4):
            raise BadInput(f"poses.c2w[{name}]: expected 4 rows (4x4) or 3 rows (3x4), got {len(m)}",
                           code="invalid_pose")
        ragged = [(i, len(r)) for i, r in enumerate(m) if len(r) != 4]
        if ragged:
            row, count = ragged[0]
            raise BadInput(f"poses.c2w[{name}]: row {row + 1} has {count} numbers; every row of a 4x4 or 3x4 "
                           "matrix has 4", code="invalid_pose")
        try:
            out.append(as_c2w(m, convention))
        except PoseError as exc:
            raise BadInput(f"poses.c2w[{name}]: {exc}", code="invalid_pose") from None
    baseline = float(np.linalg.norm(out[0][:3, 3] - out[1][:3, 3]))
    if not baseline >= MIN_BASELINE:
        raise BadInput(f"poses: the two camera centres are identical or too close ({baseline:.3g} apart, "
                       f"less than the {MIN_BASELINE:g} needed to triangulate depth)", code="identical_camera_centres")
    try:
        check_scene_scale(out[0], out[1])
    except SweepRangeError as exc:
        raise BadInput(f"poses: {exc}", code="invalid_pose") from None
    return Poses(convention, out[0], out[1])


def check_scale_options(poses_given: bool, pose_options: PoseOptions) -> None:
    """422 when ``camera_height`` or ``baseline`` come with given poses (they scale estimated poses only, and
    given poses carry their own scale) or ``refine_poses`` without them: the option would be ignored without a word."""
    given = [k for k in ("camera_height", "baseline") if getattr(pose_options, k) is not None]
    if poses_given and given:
        raise BadInput(f"options.{given[0]}: sets the scale of estimated poses only; these poses are given and "
                       "carry their own scale (leave the option out, or scale the c2w translations)",
                       code="invalid_options")
    if not poses_given and pose_options.refine_poses:
        raise BadInput("options.refine_poses: refines given poses; without poses they are estimated from the images "
                       "(leave the option out, or send poses)", code="invalid_options")
    if pose_options.baseline is not None and not pose_options.baseline >= MIN_BASELINE:
        raise BadInput(f"options.baseline: {pose_options.baseline:g} is shorter than the {MIN_BASELINE:g} needed to "
                       "triangulate depth (the baseline is the distance between the two cameras, in metres)",
                       code="invalid_options")


def check_estimated_scale(c2w_a: np.ndarray, c2w_b: np.ndarray, pose_options: PoseOptions) -> None:
    """422 naming the option when ``camera_height`` scaled the estimated poses to a baseline too short to
    triangulate (the encoder would only say that the cameras coincide)."""
    b = baseline(c2w_a, c2w_b)
    if not b >= MIN_BASELINE:
        given = (f"options.camera_height={pose_options.camera_height:g} scales the estimated poses to"
                 if pose_options.camera_height is not None else "the estimated poses have")
        raise BadInput(f"{given} a baseline of {b:.3g}, shorter than the {MIN_BASELINE:g} needed to triangulate "
                       "depth (camera_height is in metres above the floor)", code="invalid_options")


def check_sweep_range(c2w_a: np.ndarray, c2w_b: np.ndarray, options: dict,
                      per_baseline: tuple[float, float] = (NEAR_PER_BASELINE, FAR_PER_BASELINE)) -> None:
    """422 when ``options`` near/far do not fit the cameras (see :func:`rasterizer.sweep.check_scene_scale`),
    or when one of them is given and does not lie on its side of the other's automatic value
    (``per_baseline``: the model's near and far per unit of baseline)."""
    near, far = options.get("near"), options.get("far")
    try:
        check_scene_scale(c2w_a, c2w_b, near, far)
    except SweepRangeError as exc:
        raise BadInput(f"options: {exc}", code="invalid_options") from None
    if (near is None) == (far is None):  # both given: SceneOptions checked near < far; none: automatic
        return
    auto_near, auto_far = default_near_far(c2w_a, c2w_b, near_ratio=per_baseline[0], far_ratio=per_baseline[1])
    b = baseline(c2w_a, c2w_b)
    if near is not None and not near < auto_far:
        shown, limit = distinct_numbers(near, auto_far)
        raise BadInput(f"options.near={shown} must be smaller than far; no far is given and the automatic far for "
                       f"this scene is {limit} ({per_baseline[1]:g} x the baseline {b:.3g}): give a larger far too",
                       code="invalid_options")
    if far is not None and not far > auto_near:
        shown, limit = distinct_numbers(far, auto_near)
        raise BadInput(f"options.far={shown} must be larger than near; no near is given and the automatic near for "
                       f"this scene is {limit} ({per_baseline[0]:g} x the baseline {b:.3g}): give a smaller near too",
                       code="invalid_options")


def parse_options(text: str | bytes | None, accepted: set[str] | None = None,
                  ) -> tuple[dict[str, Any], PipelineOptions, PoseOptions]:
    """(options JSON object, its :class:`PipelineOptions`, its :class:`~service.poses.PoseOptions`), parsed once.

    The object is validated against :class:`service.options.SceneOptions` (strict types, no unknown
    keys, finite numbers; near < far); ``accepted`` restricts the top-level keys further (None: every
    option). The object itself is returned as sent: scene ids are hashed from it.
    """
    text = without_bom(text) if isinstance(text, (str, bytes)) else text
    if text is None or (isinstance(text, (str, bytes)) and not text.strip()):
        return {}, PipelineOptions.from_dict({}), PoseOptions()
    obj = json_value(text, "options")
    if not isinstance(obj, dict):
        raise BadInput("options: expected a JSON object", code="invalid_options")
    if len(obj) > 32:
        raise BadInput("options: too many keys", code="invalid_options")
    if accepted is not None:
        unknown = sorted(set(obj) - accepted - set(STEP_OPTION_KEYS) - set(POSE_OPTION_KEYS))
        if unknown:
            raise BadInput(f"options: unknown option(s) {unknown}; accepted: {sorted(accepted)}",
                           code="invalid_options")
    try:
        scene = SceneOptions.model_validate(obj)
    except ValidationError as exc:
        raise BadInput(describe_error(exc), code="invalid_options") from None
    pose_options = PoseOptions(scene.camera_height, scene.baseline, scene.refine_poses)
    try:
        return obj, PipelineOptions.from_dict({k: v for k, v in obj.items() if k not in POSE_OPTION_KEYS}), pose_options
    except (TypeError, ValueError, OverflowError) as exc:
        raise BadInput(f"{exc}" if str(exc).startswith("options") else f"options: {exc}",
                       code="invalid_options") from None


#: a number of a query (c2w's, width, height, fov_deg, the viewer page's): plain ASCII decimal, as JSON and JavaScript
#: write it (an optional sign and exponent)
PLAIN_DECIMAL = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_NON_FINITE = frozenset({"nan", "+nan", "-nan", "inf", "+inf", "-inf", "infinity", "+infinity", "-infinity"})
_INTEGER = re.compile(r"[+-]?[0-9]+")


def _plain(pattern: re.Pattern, kind: str, words: frozenset[str] = frozenset()):
    """A query value's check before its type's own parsing: a text must be a plain ASCII decimal ``kind``, as
    :data:`PLAIN_DECIMAL` (pydantic, as Python, also reads digit groups such as ``6_4`` as 64 and non-ASCII digits),
    or one of ``words`` (NaN and infinity for a float: numbers, whose range the route's own check refuses)."""
    def check(value):
        if isinstance(value, str) and not (pattern.fullmatch(value.strip()) or value.strip().lower() in words):
            raise ValueError(f"expected a plain decimal {kind}, got {value[:40]!r}")
        return value
    return check


#: Integer and number query parameters of the routes: plain ASCII decimals only, as the ``c2w`` query's numbers.
QueryInt = Annotated[int, BeforeValidator(_plain(_INTEGER, "integer such as 1024"))]
QueryFloat = Annotated[float, BeforeValidator(_plain(PLAIN_DECIMAL, "number such as 90 or 62.5", _NON_FINITE))]


def parse_c2w_query(text: str) -> np.ndarray:
    """``c2w`` query: 16 or 12 comma-separated numbers, row-major, OpenCV camera-to-world.

    Each number is a plain decimal (:data:`PLAIN_DECIMAL`): Python's ``float`` also reads digit groups (``0_5`` as 5)
    and non-ASCII digits, which the viewer page's script (and most clients) read as no number at all, so the
    camera the service renders would not be the one the request names.
    """
    parts = [p.strip() for p in str(text).split(",")]
    if len(parts) not in (12, 16):
        raise BadInput(f"c2w: expected 16 (4x4) or 12 (3x4) comma-separated numbers, got {len(parts)}",
                       code="invalid_pose")
    if any(p.lower() in _NON_FINITE for p in parts):
        raise BadInput("c2w: contains NaN or Inf", code="invalid_pose")
    bad = next((k for k, p in enumerate(parts) if not PLAIN_DECIMAL.fullmatch(p)), None)
    if bad is not None:
        raise BadInput(f"c2w: entry {bad + 1} ({parts[bad][:40]!r}) is not a number; write plain decimal numbers "
                       "such as 0.5, -2 or 1e-3", code="invalid_pose")
    values = [float(p) for p in parts]
    if not all(math.isfinite(v) for v in values):
        raise BadInput("c2w: contains NaN or Inf", code="invalid_pose")
    try:
        return as_c2w(np.array(values).reshape(-1, 4), "opencv")
    except PoseError as exc:
        raise BadInput(f"c2w: {exc}", code="invalid_pose") from None


@dataclass(frozen=True)
class RenderQuery:
    c2w: np.ndarray
    projection: str
    width: int
    height: int | None
    fov_deg: float
    format: str
    compositing: str = "plain"
    rig: bool = False  # composite the capture rig both references show at their nadir (rasterizer.rig)

    def render_kwargs(self, *, normalize: bool, reconstruction: bool = True) -> dict[str, Any]:
        """Keyword arguments of :func:`rasterizer.render.render` for this query (pose passed apart).

        ``reconstruction``: the Gaussians are a scene this service built (or an edit of one), whose
        overlapping surfels hide their footprints' tails, so a plain composite's footprints end at
        :data:`RENDER_CUT_SIGMA`; False for any other PLY, whose sparse Gaussians may show their tails (the
        1/255 rule alone). V/A (``normalize``) is never cut: dividing by alpha shows a tail's colour at full
        strength wherever nothing else covers the pixel (an isolated object's rim), nor is a perspective view
        wider than :data:`CUT_MAX_FOV_DEG`.
        """
        # "scene": a view finer than the scene's Gaussians is rendered at their pitch and resized
        # (rasterizer.scene_resolution; docs/design.md, "At the scene's own resolution")
        narrow = self.projection != "perspective" or self.fov_deg <= CUT_MAX_FOV_DEG
        cut = RENDER_CUT_SIGMA if reconstruction and not normalize and narrow else None
        kwargs: dict[str, Any] = {"projection": self.projection, "width": self.width, "normalize": normalize,
                                  "resolution": "scene", "cut_sigma": cut}
        if self.projection == "perspective":
            kwargs.update(height=self.height, fov_deg=self.fov_deg)
        return kwargs

    def output_size(self) -> tuple[int, int]:
        """(height, width) of the rendered image."""
        if self.projection == "erp":
            return self.width // 2, self.width
        if self.projection in ("yin", "yang"):
            return self.width // 3, self.width
        return (self.height if self.height is not None else self.width), self.width


#: field of view of a perspective render, degrees, horizontal and vertical alike
MIN_FOV_DEG, MAX_FOV_DEG = 1.0, 170.0


def check_fov(fov_deg: float) -> float:
    """``fov_deg`` (horizontal, degrees) when within :data:`MIN_FOV_DEG`..:data:`MAX_FOV_DEG`; else a 400-class
    ``invalid_render_query`` naming it (renders and the viewer page's camera)."""
    if not (math.isfinite(fov_deg) and MIN_FOV_DEG <= fov_deg <= MAX_FOV_DEG):
        raise BadInput(f"fov_deg: must be between {MIN_FOV_DEG:g} and {MAX_FOV_DEG:g} degrees, got {fov_deg}",
                       code="invalid_render_query")
    return fov_deg


def check_camera_reach(pose: np.ndarray) -> np.ndarray:
    """``pose`` (a checked 4x4 c2w) when its camera lies within :data:`MAX_SCENE_EXTENT` of the origin, as the
    scenes' own cameras (float32 positions beyond cannot resolve a room); else a 422 ``invalid_pose`` naming c2w
    (renders and the viewer page's camera)."""
    reach = float(np.abs(pose[:3, 3]).max())
    if not reach <= MAX_SCENE_EXTENT:
        shown, limit = distinct_numbers(reach, MAX_SCENE_EXTENT)
        raise BadInput(f"c2w: the camera lies {shown} from the origin; render cameras, as the scenes' cameras, "
                       f"must lie within {limit} of it", code="invalid_pose")
    return pose


def check_render_query(c2w: str | np.ndarray, projection: str, width: int, height: int | None, fov_deg: float | None,
                       fmt: str,
                       *, max_width: int, max_pixels: int, compositing: str = "plain", rig: bool = False) -> RenderQuery:
    """The render query of the API (``c2w`` as its query text) or the CLI (a checked 4x4 OpenCV c2w); 422 naming
    the parameter that is out of range. ``height`` and ``fov_deg`` are None where the request names none: only a
    perspective render takes them (default: square, :data:`DEFAULT_FOV_DEG`)."""
    pose = check_camera_reach(c2w if isinstance(c2w, np.ndarray) else parse_c2w_query(c2w))
    if compositing not in COMPOSITINGS:
        raise BadInput(f"compositing: expected plain or va, got {compositing!r}", code="invalid_render_query")
    if projection not in ("erp", "perspective", "yin", "yang"):
        raise BadInput(f"projection: expected erp, perspective, yin or yang, got {projection!r}",
                       code="invalid_render_query")
    if fmt not in ("png", "jpeg"):
        raise BadInput(f"format: expected png or jpeg, got {fmt!r}", code="invalid_render_query")
    min_width = {"erp": 8, "yin": 6, "yang": 6}.get(projection, 1)
    if not (min_width <= width <= max_width):
        raise BadInput(f"width: must be between {min_width} and {max_width}, got {width}", code="invalid_render_query")
    if projection == "erp" and width % 2:
        raise BadInput(f"width: an ERP render needs an even width (W = 2H), got {width}", code="invalid_render_query")
    if projection in ("yin", "yang") and width % 3:
        raise BadInput(f"width: a {projection} render needs a width divisible by 3 (w = 3h), got {width}",
                       code="invalid_render_query")
    if height is not None and projection != "perspective":
        raise BadInput("height: only a perspective render takes a height", code="invalid_render_query")
    if height is not None and not (1 <= height <= max_width):
        raise BadInput(f"height: must be between 1 and {max_width}, got {height}", code="invalid_render_query")
    if fov_deg is not None and projection != "perspective":  # as height: it would be dropped
        raise BadInput(f"fov_deg: only a perspective render takes a field of view (this one is {projection})",
                       code="invalid_render_query")
    fov_deg = check_fov(DEFAULT_FOV_DEG if fov_deg is None else fov_deg)
    if projection == "perspective" and height is not None:
        vertical = math.degrees(2.0 * math.atan(math.tan(math.radians(fov_deg) / 2.0) * height / width))
        if vertical > MAX_FOV_DEG:  # a tall, narrow view: rays near 90 deg off axis leave rows blank
            raise BadInput(f"height: a {width}x{height} perspective view at fov_deg {fov_deg:g} (horizontal) spans "
                           f"{vertical:.1f} degrees vertically, more than {MAX_FOV_DEG:g}; lower height or fov_deg",
                           code="invalid_render_query")
    query = RenderQuery(pose, projection, int(width), None if height is None else int(height), float(fov_deg), fmt,
                        compositing, bool(rig))
    h, w = query.output_size()
    if h * w > max_pixels:
        raise BadInput(f"render size {w}x{h} exceeds the limit of {max_pixels} pixels", code="invalid_render_query")
    return query
