"""Scene-adaptive sweep range: choose near/far from the scene, not from defaults.

The exported encoder spends a fixed number of planes uniformly in inverse
range between 1/far and 1/near (default near ~0.3 m, far 20 m). A room
rarely spans that: planes in front of the nearest surface and behind the
farthest wall are wasted, so tightening the range puts more planes where the
scene is. :func:`reconstruct_adaptive` runs a coarse pass (the same encoder
at the default range, or a cheaper smaller encoder), takes robust
percentiles of the *confident* ranges, widens them by a margin and reruns
with that range. The plane count itself is fixed per exported model (static
ONNX shapes); choosing it per scene would need one model per count.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, fields

import numpy as np


class AdaptiveRangeError(ValueError):
    """Bad adaptive-range options."""


@dataclass(frozen=True)
class AdaptiveRangeOptions:
    """enabled: run the adaptive step; low_pct/high_pct: percentiles of confident ranges;
    min_confidence: pixels counted as confident; margin: relative widening (near / (1+m),
    far * (1+m)); min_fraction: below this fraction of confident pixels keep the default range;
    min_ratio: far/near is never tightened below this."""

    enabled: bool = False
    low_pct: float = 1.0
    high_pct: float = 99.0
    min_confidence: float = 0.5
    margin: float = 0.15
    min_fraction: float = 0.02
    min_ratio: float = 3.0

    def __post_init__(self) -> None:
        if not (0.0 <= self.low_pct < self.high_pct <= 100.0):
            raise AdaptiveRangeError(f"need 0 <= low_pct < high_pct <= 100, got {self.low_pct}, {self.high_pct}")
        if not (0.0 <= self.min_confidence <= 1.0) or self.margin < 0 or self.min_ratio < 1.0:
            raise AdaptiveRangeError("min_confidence must be in [0, 1], margin >= 0, min_ratio >= 1")

    @classmethod
    def from_dict(cls, d: dict | None) -> "AdaptiveRangeOptions":
        """Options from a JSON object (API ``options.adaptive_range``); unknown keys raise."""
        d = dict(d or {})
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise AdaptiveRangeError(f"unknown adaptive_range option(s) {unknown}; known: {sorted(names)}")
        return cls(**d)

    def to_dict(self) -> dict:
        return asdict(self)


def range_from_maps(range_maps: np.ndarray, confidence: np.ndarray, near: float, far: float,
                    options: AdaptiveRangeOptions | None = None) -> tuple[float, float, dict]:
    """Tightened (near, far) inside the coarse pass's [near, far], and why.

    Only confident pixels whose range is not pinned at the sweep's ends
    count (a range at the last plane means "no match", not "far wall").
    """
    opts = options or AdaptiveRangeOptions()
    r = np.asarray(range_maps, dtype=np.float64).reshape(-1)
    c = np.asarray(confidence, dtype=np.float64).reshape(-1)
    ok = (c >= opts.min_confidence) & np.isfinite(r) & (r > near * 1.001) & (r < far * 0.999)
    frac = float(ok.mean()) if r.size else 0.0
    info = {"confident_fraction": round(frac, 4), "coarse_near": near, "coarse_far": far}
    if frac < opts.min_fraction or not ok.any():  # min_fraction 0 still needs one pixel to take percentiles of
        info["reason"] = "too few confident pixels; default range kept"
        return near, far, info
    lo, hi = np.percentile(r[ok], [opts.low_pct, opts.high_pct])
    new_near = max(near, float(lo) / (1.0 + opts.margin))
    new_far = min(far, float(hi) * (1.0 + opts.margin))
    if new_far < opts.min_ratio * new_near:
        # keep at least min_ratio, centred (geometrically) on the observed span
        mid = np.sqrt(new_near * new_far)
        new_near = max(near, mid / np.sqrt(opts.min_ratio))
        new_far = min(far, new_near * opts.min_ratio)
    if not new_far > new_near:  # one range everywhere, no margin and min_ratio 1: no sweep fits between them
        info.update({"p_low": float(lo), "p_high": float(hi), "reason": "confident ranges span no interval; "
                     "default range kept"})
        return near, far, info
    info.update({"p_low": float(lo), "p_high": float(hi), "near": new_near, "far": new_far})
    return new_near, new_far, info


def reconstruct_adaptive(encoder, erp_a, erp_b, c2w_a, c2w_b, *, options: AdaptiveRangeOptions | None = None,
                         coarse_encoder=None, **encoder_options):
    """Two-pass reconstruction: coarse pass -> tightened near/far -> final pass.

    ``encoder``/``coarse_encoder``: :class:`service.encoder.OnnxEncoder`
    (the coarse one defaults to ``encoder``; a smaller model is cheaper).
    ``encoder_options`` go to both passes (e.g. ``near``/``far`` of the coarse
    pass). The result's ``info["adaptive_range"]`` holds the chosen range and
    the coarse statistics; ``timings["coarse"]`` the extra seconds, and
    ``timings["total"]`` includes them. With ``options.enabled`` False it is
    one ordinary pass.
    """
    opts = options or AdaptiveRangeOptions(enabled=True)
    if not opts.enabled:
        return encoder.reconstruct(erp_a, erp_b, c2w_a, c2w_b, **encoder_options)
    t0 = time.perf_counter()
    coarse = (coarse_encoder or encoder).reconstruct(erp_a, erp_b, c2w_a, c2w_b, **encoder_options)
    t_coarse = time.perf_counter() - t0
    near, far, info = range_from_maps(coarse.range_maps, coarse.confidence, coarse.info["near"],
                                      coarse.info["far"], opts)
    final_opts = {k: v for k, v in encoder_options.items() if k not in ("near", "far")}
    rec = encoder.reconstruct(erp_a, erp_b, c2w_a, c2w_b, near=near, far=far, **final_opts)
    rec.timings["coarse"] = t_coarse
    rec.timings["total"] = rec.timings.get("total", 0.0) + t_coarse
    rec.info["adaptive_range"] = {**info, "coarse_seconds": round(t_coarse, 3),
                                  "coarse_model": (coarse_encoder or encoder).metadata.get("name")
                                  if hasattr(coarse_encoder or encoder, "metadata") else None,
                                  "options": opts.to_dict()}
    return rec
