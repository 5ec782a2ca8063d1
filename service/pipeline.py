"""Two panoramas -> the Gaussians a scene needs: one path for the API and the CLI.

Steps: optional scene-adaptive depth range (:mod:`service.scene_adaptive`),
the ONNX encoder, compaction (:mod:`rasterizer.compaction`: transparent
Gaussians, merge of smooth 2x2 blocks, optional cap; the scene metadata's
``compaction`` says how many each step removed), and a final guard that
drops any non-finite Gaussian. Options come as the API's ``options`` JSON
object; structured keys ``compaction`` and ``adaptive_range`` hold the
step options, ``near``/``far``, ``sh_degree`` (view-dependent colour, 1, or one colour per
Gaussian, 0) and ``rig_cap_deg`` (degrees around each camera's nadir where a tripod capture shows
the rig, 0 = off; absent = automatic, 20 where both references show a rig) go to the encoder,
``min_opacity`` is a compaction threshold.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

from pydantic import ValidationError

from rasterizer.compaction import CompactionOptions, Provenance, compact_result
from rasterizer.edit.scene import EditData
from rasterizer.gaussians import Gaussians
from rasterizer.ply import finite_rows
from rasterizer.view_colour import DEFAULT_SH_DEGREE

from .options import PipelineSettings, describe_error
from .scene_adaptive import AdaptiveRangeOptions, reconstruct_adaptive

#: Options keys that hold a JSON object of step options.
STEP_OPTION_KEYS = ("compaction", "adaptive_range")


@dataclass(frozen=True)
class PipelineOptions:
    near: float | None
    far: float | None
    compaction: CompactionOptions
    adaptive_range: AdaptiveRangeOptions
    sh_degree: int = DEFAULT_SH_DEGREE
    rig_cap_deg: float | None = None  # None: automatic (rasterizer.rig.resolve_rig_cap)

    @classmethod
    def from_dict(cls, options: dict[str, Any] | None) -> "PipelineOptions":
        """Parse an options object (:class:`service.options.PipelineSettings`, strict types); raises
        ``ValueError`` naming a bad or unknown key.

        ``{"compaction": false}`` turns every compaction step off; a null ``compaction`` or
        ``adaptive_range`` means its defaults.
        """
        opts = {k: v for k, v in (options or {}).items()
                if not (v is None and k in STEP_OPTION_KEYS)}
        try:
            settings = PipelineSettings.model_validate(opts)
        except ValidationError as exc:
            raise ValueError(describe_error(exc)) from None
        try:
            compaction = settings.compaction_options()
        except ValueError as exc:
            raise ValueError(f"options.compaction: {exc}") from None
        try:
            adaptive = settings.adaptive_options()
        except ValueError as exc:
            raise ValueError(f"options.adaptive_range: {exc}") from None
        sh_degree = DEFAULT_SH_DEGREE if settings.sh_degree is None else settings.sh_degree
        return cls(settings.near, settings.far, compaction, adaptive, sh_degree, settings.rig_cap_deg)


@dataclass(frozen=True)
class SceneBuild:
    """edit: correspondences, range maps and each Gaussian's provenance (None for a model without ``matches``)."""

    gaussians: Gaussians
    timings: dict[str, float]
    info: dict[str, Any]
    edit: EditData | None = None


def build_scene(encoder, erp_a, erp_b, c2w_a, c2w_b, options: PipelineOptions) -> SceneBuild:
    """Reconstruct and compact; ``info`` says what each step did (incl. ``compaction`` stats)."""
    if options.adaptive_range.enabled:  # off by default: then straight to the encoder
        rec = reconstruct_adaptive(encoder, erp_a, erp_b, c2w_a, c2w_b, options=options.adaptive_range,
                                   near=options.near, far=options.far, sh_degree=options.sh_degree,
                                   rig_cap_deg=options.rig_cap_deg)
    else:
        rec = encoder.reconstruct(erp_a, erp_b, c2w_a, c2w_b, near=options.near, far=options.far,
                                  sh_degree=options.sh_degree, rig_cap_deg=options.rig_cap_deg)
    timings = {str(k): float(v) for k, v in (rec.timings or {}).items()}
    info = dict(rec.info or {})
    t0 = time.perf_counter()
    provenance = Provenance.from_reconstruction(rec, c2w_a, c2w_b)
    res = compact_result(rec.gaussians, provenance, options.compaction, confidence=rec.confidence)
    gaussians, stats = res.gaussians, res.stats
    timings["compaction"] = time.perf_counter() - t0
    info["compaction"] = stats
    matches = getattr(rec, "matches", None)
    edit = None if matches is None else EditData(
        provenance.grids, provenance.height, provenance.width, matches, rec.range_maps,
        res.provenance.flat_index(len(gaussians)), res.block)

    finite = finite_rows(gaussians)
    info["dropped_non_finite"] = int(len(gaussians) - finite.sum())
    shell = int(stats.get("shell", 0))  # compaction appends the environment shell last
    if info["dropped_non_finite"]:
        shell = int(finite[len(gaussians) - shell:].sum())
        gaussians = gaussians.subset(finite)
        edit = None if edit is None else edit.subset(finite)
    info["shell"] = shell  # the last ``shell`` Gaussians are the backdrop (rasterizer.shell), not surfaces
    return SceneBuild(gaussians, timings, info, edit)
