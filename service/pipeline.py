"""Two panoramas -> the Gaussians a scene needs: one path for the API and the CLI.

Steps: optional scene-adaptive depth range (:mod:`service.scene_adaptive`),
the ONNX encoder, compaction (:mod:`rasterizer.compaction`: transparent
Gaussians, merge of smooth 2x2 blocks, optional cap, then textured pixels split
into 2x2 where the uploads are finer than the grid; the scene metadata's
``compaction`` says how many each step removed or added), and a final guard that
drops any non-finite Gaussian. Options come as the API's ``options`` JSON
object; structured keys ``compaction`` and ``adaptive_range`` hold the
step options, ``near``/``far``, ``sh_degree`` (view-dependent colour, 1, or one colour per
Gaussian, 0) and ``rig_cap_deg`` (degrees around each camera's nadir where a tripod capture shows
the rig, 0 = off; absent = automatic, 20 where both references show a rig) go to the encoder,
``min_opacity`` is a compaction threshold.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from pydantic import ValidationError

from rasterizer.compaction import CompactionOptions, Provenance, compact_result
from rasterizer.compaction.options import count_limit
from rasterizer.compaction.result import CompactionResult
from rasterizer.compaction.split import fine_erp, split_textured, texture_ratio
from rasterizer.edit.scene import EditData
from rasterizer.gaussians import Gaussians
from rasterizer.ply import finite_rows
from rasterizer.rig import rig_mask
from rasterizer.threads import map_threads
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


def _fine_uploads(uploads, grids: tuple[str, ...], height: int, width: int) -> list:
    """Each upload's (:func:`~rasterizer.compaction.split.fine_erp`, its
    :func:`~rasterizer.compaction.split.texture_ratio`) for grids of ``height`` x ``width``, or None where the
    upload is not finer than them: the split's image-only work, one upload after the other."""
    out = []
    for erp in uploads:
        fine = fine_erp(erp, grids, height, width)
        out.append(None if fine is None else (fine, texture_ratio(fine)))
    return out


def _timed(fn, *args):
    """(fn(*args), its wall seconds)."""
    t0 = time.perf_counter()
    return fn(*args), time.perf_counter() - t0


def _split_textured(res: CompactionResult, provenance: Provenance, uploads, opts: CompactionOptions,
                    rig_cap_deg: float | None, detail: list | None = None) -> CompactionResult:
    """:func:`~rasterizer.compaction.split.split_textured` of the pixels of each reference whose upload is finer
    than the grids (the other's stay whole), never in the rig cap, within the options' count cap.

    detail: :func:`_fine_uploads` of ``uploads`` for the provenance's grids when the caller made it (None: made here).
    """
    grids, h, w = provenance.grids, provenance.height, provenance.width
    if detail is None:
        detail = map_threads(lambda erp: _fine_uploads([erp], grids, h, w)[0], uploads)
    if all(d is None for d in detail):  # nothing finer than the grid: reported as no split
        return replace(res, stats={**res.stats, "split_textured": {"split": 0, "added": 0, "seconds": 0.0}})
    exclude = None
    if rig_cap_deg:
        exclude = np.broadcast_to(rig_mask(grids, h, w, rig_cap_deg), (provenance.views, len(grids), h, w))
    return split_textured(res, [None if d is None else d[0] for d in detail],
                          ratios=[None if d is None else d[1] for d in detail], exclude=exclude,
                          limit=count_limit(opts, res.gaussians.sh.shape[1]))


@dataclass(frozen=True)
class SceneBuild:
    """edit: correspondences, range maps and each Gaussian's provenance (None for a model without ``matches``)."""

    gaussians: Gaussians
    timings: dict[str, float]
    info: dict[str, Any]
    edit: EditData | None = None


def build_scene(encoder, erp_a, erp_b, c2w_a, c2w_b, options: PipelineOptions, *,
                uploads: tuple[np.ndarray, np.ndarray] | None = None) -> SceneBuild:
    """Reconstruct and compact; ``info`` says what each step did (incl. ``compaction`` stats).

    uploads: the two panoramas as uploaded when ``erp_a`` / ``erp_b`` are already resampled (default: those),
    the source of the detail finer than the encoder's grid (:mod:`rasterizer.compaction.split`).
    """
    uploads = uploads or (erp_a, erp_b)
    # the split's image-only work runs beside the graph, whose two threads leave a core partly idle
    grids, size = getattr(encoder, "grids", None), getattr(encoder, "grid_size", None)
    layout = None if grids is None or size is None else (tuple(grids), *size)  # (grids, height, width)
    job = None
    with ThreadPoolExecutor(max_workers=1) as side:
        if options.compaction.split_textured and layout is not None:
            job = side.submit(_timed, _fine_uploads, uploads, *layout)
        if options.adaptive_range.enabled:  # off by default: then straight to the encoder
            rec = reconstruct_adaptive(encoder, erp_a, erp_b, c2w_a, c2w_b, options=options.adaptive_range,
                                       near=options.near, far=options.far, sh_degree=options.sh_degree,
                                       rig_cap_deg=options.rig_cap_deg)
        else:
            rec = encoder.reconstruct(erp_a, erp_b, c2w_a, c2w_b, near=options.near, far=options.far,
                                      sh_degree=options.sh_degree, rig_cap_deg=options.rig_cap_deg)
        detail, detail_seconds = job.result() if job is not None else (None, 0.0)
    timings = {str(k): float(v) for k, v in (rec.timings or {}).items()}
    if job is not None:
        timings["split_detail"] = detail_seconds  # beside the encoder, not after it
    info = dict(rec.info or {})
    t0 = time.perf_counter()
    provenance = Provenance.from_reconstruction(rec, c2w_a, c2w_b)
    if layout != (provenance.grids, provenance.height, provenance.width):
        detail = None  # made for other grids than the reconstruction's (or not made): made for its own
    res = compact_result(rec.gaussians, provenance, options.compaction, confidence=rec.confidence)
    timings["compaction"] = time.perf_counter() - t0
    if options.compaction.split_textured:
        t0 = time.perf_counter()
        res = _split_textured(res, provenance, uploads, options.compaction, info.get("rig_cap_deg"), detail)
        timings["split_textured"] = time.perf_counter() - t0
    gaussians, stats = res.gaussians, res.stats
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
