"""The ``options`` of ``POST /v1/scenes``: one pydantic model with strict types, its JSON schema and its errors.

The form field stays a JSON object (multipart cannot nest), validated here with strict types: a
string where a boolean or a number belongs, a boolean where a number belongs, a non-finite number or
an unknown key is a 422 naming the field. The rasterizer keeps its own dataclasses
(:class:`rasterizer.compaction.CompactionOptions`, :class:`service.scene_adaptive.AdaptiveRangeOptions`):
:class:`service.pipeline.PipelineOptions` builds them from these models by keyword, and their
defaults are the dataclasses' own (one source of truth).
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from rasterizer.compaction import CompactionOptions, ply_bytes_for_count
from rasterizer.compaction.split import MIN_UPLOAD_RATIO
from rasterizer.rig import MAX_RIG_CAP_DEG
from rasterizer.view_colour import DEFAULT_SH_DEGREE, SH_DEGREES

from .scene_adaptive import AdaptiveRangeOptions

_COMPACTION = CompactionOptions()
_ADAPTIVE = AdaptiveRangeOptions()
_STRICT = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)


class CompactionSettings(BaseModel):
    """Steps that shrink the scene after the encoder (``rasterizer.compaction``); each can be turned off."""

    model_config = _STRICT

    min_opacity: float = Field(_COMPACTION.min_opacity, ge=0.0, lt=1.0,
                               description="drop Gaussians less opaque than this (0: keep all)")
    min_confidence: float = Field(_COMPACTION.min_confidence, ge=0.0, le=1.0,
                                  description="drop Gaussians whose match confidence is below this (0: off)")
    merge_smooth: bool = Field(_COMPACTION.merge_smooth, description="merge smooth 2x2 blocks into one Gaussian")
    smooth_colour_tol: float = Field(_COMPACTION.smooth_colour_tol, ge=0.0, le=1.0,
                                     description="a cap on a merged block's colour range per channel (0..1; 1 = none: "
                                     "blocks merge when their texture is small against the image's contrast)")
    smooth_opacity_tol: float = Field(_COMPACTION.smooth_opacity_tol, ge=0.0, le=1.0,
                                      description="largest spread of a block's opacities")
    smooth_plane_tol: float = Field(_COMPACTION.smooth_plane_tol, ge=0.0, le=1.0,
                                    description="largest rms distance of a block from its plane, relative to range")
    smooth_max_incidence_deg: float = Field(_COMPACTION.smooth_max_incidence_deg, ge=0.0, le=90.0,
                                            description="largest angle between a block's plane normal and the ray")
    max_count: int | None = Field(_COMPACTION.max_count, ge=1, description="keep at most this many Gaussians: flat blocks "
                                  "merge further, least textured first, then the least visible are dropped (null: no cap)")
    max_bytes: int | None = Field(_COMPACTION.max_bytes, ge=0, description="keep the PLY within this many bytes "
                                  "(null: no cap)")
    split_textured: bool = Field(_COMPACTION.split_textured, description=(
        f"where an upload is at least {MIN_UPLOAD_RATIO:g}x as wide as the model's input, split each textured "
        "pixel's Gaussian of that reference into 2x2 finer ones that carry the upload's detail (within max_count / "
        "max_bytes)"))

    def build(self) -> CompactionOptions:
        return CompactionOptions(**self.model_dump())


class AdaptiveRangeSettings(BaseModel):
    """A coarse encoder pass that tightens near/far to the scene before the full pass (off by default)."""

    model_config = _STRICT

    enabled: bool = Field(_ADAPTIVE.enabled, description="run the adaptive step (one extra encoder pass)")
    low_pct: float = Field(_ADAPTIVE.low_pct, ge=0.0, le=100.0, description="percentile of confident ranges -> near")
    high_pct: float = Field(_ADAPTIVE.high_pct, ge=0.0, le=100.0, description="percentile of confident ranges -> far")
    min_confidence: float = Field(_ADAPTIVE.min_confidence, ge=0.0, le=1.0, description="pixels counted as confident")
    margin: float = Field(_ADAPTIVE.margin, ge=0.0, le=100.0, description="relative widening: near/(1+m), far*(1+m)")
    min_fraction: float = Field(_ADAPTIVE.min_fraction, ge=0.0, le=1.0,
                                description="below this fraction of confident pixels the default range stays")
    min_ratio: float = Field(_ADAPTIVE.min_ratio, ge=1.0, le=1e6, description="far/near is never tightened below this")

    def build(self) -> AdaptiveRangeOptions:
        return AdaptiveRangeOptions(**self.model_dump())


class PipelineSettings(BaseModel):
    """What the reconstruction does with two posed panoramas (:class:`service.pipeline.PipelineOptions`)."""

    model_config = _STRICT

    near: float | None = Field(None, gt=0.0, description="nearest depth of the sweep in metres (null: automatic)")
    far: float | None = Field(None, gt=0.0, description="farthest depth of the sweep in metres (null: automatic)")
    min_opacity: float | None = Field(None, ge=0.0, lt=1.0, description="shorthand for compaction.min_opacity")
    sh_degree: int | None = Field(DEFAULT_SH_DEGREE, ge=min(SH_DEGREES), le=max(SH_DEGREES),
                                  description="1: view-dependent colour (each reference sees its own image); "
                                              "0: one colour per Gaussian; null: 1")
    rig_cap_deg: float | None = Field(None, ge=0.0, le=MAX_RIG_CAP_DEG, description="re-colour the pixels within "
                                      "this many degrees of each camera's nadir, where tripod captures show the rig, "
                                      "from the other panorama (0: off; null: 20 where both references show a rig "
                                      "at their nadir, the metadata's 'rig', else 0)")
    compaction: CompactionSettings | Literal[False] = Field(
        default_factory=CompactionSettings, description="compaction steps; false keeps every Gaussian")
    adaptive_range: AdaptiveRangeSettings | bool = Field(
        default_factory=AdaptiveRangeSettings, description="adaptive depth range; true/false is enabled only. With "
        "near/far given, they are the coarse pass's range and the final one comes from its depths")

    @model_validator(mode="after")
    def _near_below_far(self) -> "PipelineSettings":
        if self.near is not None and self.far is not None and not self.near < self.far:
            raise ValueError("near must be smaller than far")
        return self

    @model_validator(mode="after")
    def _no_option_left_unused(self) -> "PipelineSettings":
        """Options that another option overrides are refused, not dropped: the request would not be what it says.
        Settings of a step that is off count too: an ``adaptive_range`` object without ``"enabled": true`` (its
        default is off) and ``smooth_*`` tolerances beside ``"merge_smooth": false`` would change nothing."""
        adaptive = self.adaptive_range
        if isinstance(adaptive, AdaptiveRangeSettings) and not adaptive.enabled:
            unused = sorted(adaptive.model_fields_set - {"enabled"})
            if unused:
                raise ValueError(f"adaptive_range.{', adaptive_range.'.join(unused)} set, but the adaptive range is "
                                 'off ("enabled" is false or left out, and off by default): add "enabled": true, or '
                                 "leave the settings out")
        if self.compaction is not False and not self.compaction.merge_smooth:
            unused = sorted(k for k in self.compaction.model_fields_set if k.startswith("smooth_"))
            if unused:
                raise ValueError(f"compaction.{', compaction.'.join(unused)} set, but compaction.merge_smooth is false: "
                                 "the tolerances only steer the smooth merge; leave them out, or the merge on")
        if self.min_opacity is None:
            return self
        if self.compaction is False:
            raise ValueError("min_opacity drops Gaussians, which compaction false keeps; give one of them")
        if "min_opacity" in self.compaction.model_fields_set and self.compaction.min_opacity != self.min_opacity:
            raise ValueError(f"min_opacity {self.min_opacity:g} and compaction.min_opacity {self.compaction.min_opacity:g} "
                             "disagree; give one of them")
        return self

    @model_validator(mode="after")
    def _cap_holds_a_gaussian(self) -> "PipelineSettings":
        """A byte cap too small for the PLY of one Gaussian would only end as an empty scene after the work."""
        cap = None if self.compaction is False else self.compaction.max_bytes
        if cap is None:
            return self
        degree = DEFAULT_SH_DEGREE if self.sh_degree is None else self.sh_degree
        smallest = ply_bytes_for_count(1, (degree + 1) ** 2)
        if cap < smallest:
            raise ValueError(f"compaction.max_bytes={cap} cannot hold the PLY of one Gaussian at sh_degree {degree} "
                             f"(at least {smallest} bytes)")
        return self

    def compaction_options(self) -> CompactionOptions:
        if self.compaction is False:
            return CompactionOptions.off()
        if self.min_opacity is None:
            return self.compaction.build()
        return self.compaction.model_copy(update={"min_opacity": self.min_opacity}).build()

    def adaptive_options(self) -> AdaptiveRangeOptions:
        if isinstance(self.adaptive_range, bool):
            return AdaptiveRangeSettings(enabled=self.adaptive_range).build()
        return self.adaptive_range.build()


class SceneOptions(PipelineSettings):
    """The ``options`` form field of ``POST /v1/scenes`` (a JSON object; every key optional)."""

    camera_height: float | None = Field(None, gt=0.0, lt=1e4, description="without poses: the cameras' height "
                                        "above the floor in metres, which sets the scale")
    baseline: float | None = Field(None, gt=0.0, lt=1e4, description="without poses: the distance between the "
                                   "two cameras in metres, which sets the scale")
    refine_poses: bool = Field(False, description="refine the given poses against the images")

    @model_validator(mode="after")
    def _one_scale(self) -> "SceneOptions":
        if self.camera_height is not None and self.baseline is not None:
            raise ValueError("give camera_height or baseline, not both")
        return self


def describe_error(exc: ValidationError, prefix: str = "options") -> str:
    """One line per problem, ``options.compaction.max_count: Input should be a valid integer (got true)``."""
    errors = exc.errors(include_url=False)
    # a JSON object refused by the other branch of "object or false" only repeats what its fields say
    specific = [e for e in errors if not isinstance(e.get("input"), (dict, list))] or errors
    lines = []
    for err in specific[:8]:
        loc = ".".join(str(p) for p in err.get("loc", ()) if not str(p).startswith(("function-", "literal[")))
        loc = loc.replace(".CompactionSettings", "").replace(".AdaptiveRangeSettings", "").replace(".bool", "")
        got = err.get("input")
        shown = "" if isinstance(got, (dict, list)) else f" (got {str(got)[:40]!r})" if isinstance(got, str) \
            else f" (got {got!r})"
        msg = str(err.get("msg", "invalid")).removeprefix("Value error, ")
        if len(loc) > 80:  # an unknown key is named by its start, not a megabyte of it
            loc = f"{loc[:60]}... ({len(loc)} characters)"
        if err.get("type") == "extra_forbidden":
            msg = "unknown option (see the SceneOptions schema at /docs)"
        lines.append(f"{prefix}{'.' + loc if loc else ''}: {msg}{shown}")
    return "; ".join(dict.fromkeys(lines))


def _inline(schema: Any, defs: dict[str, Any]) -> Any:
    if isinstance(schema, dict):
        ref = schema.get("$ref")
        if isinstance(ref, str) and ref.startswith("#/$defs/"):
            return _inline(defs[ref.removeprefix("#/$defs/")], defs)
        return {k: _inline(v, defs) for k, v in schema.items() if k != "$defs"}
    if isinstance(schema, list):
        return [_inline(v, defs) for v in schema]
    return schema


def options_json_schema() -> dict[str, Any]:
    """The JSON schema of :class:`SceneOptions` with every reference inlined (for the form field's OpenAPI)."""
    schema = SceneOptions.model_json_schema()
    return _inline(schema, schema.get("$defs", {}))


def options_markdown() -> str:
    """Every option, its type and its default, as Markdown for the form field's description at /docs."""
    rows = []

    def add(model: type[BaseModel], prefix: str) -> None:
        for name, field in model.model_fields.items():
            ann = field.annotation
            text = ann.__name__ if isinstance(ann, type) else str(ann).replace("typing.", "")
            if name in ("compaction", "adaptive_range"):
                rows.append(f"- `{name}` (object or {'false' if name == 'compaction' else 'bool'}): {field.description}")
                continue
            default = field.get_default(call_default_factory=True)
            rows.append(f"- `{prefix}{name}` ({text}, default `{default!r}`): {field.description or ''}")

    add(SceneOptions, "")
    add(CompactionSettings, "compaction.")
    add(AdaptiveRangeSettings, "adaptive_range.")
    return "\n".join(rows)
