"""Compaction options (which steps run, their thresholds) and the Gaussian count a PLY size allows."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import numpy as np

from ..gaussians import Gaussians
from ..ply import ply_bytes

#: Largest block side of the smooth-region merge is 2**MAX_SMOOTH_LEVELS pixels.
MAX_SMOOTH_LEVELS = 4


class CompactionError(ValueError):
    """Bad options, or Gaussians that do not match their provenance."""


@dataclass(frozen=True)
class CompactionOptions:
    """Which compaction steps run, and their thresholds (every step can be turned off).

    min_opacity: drop opacity below this (0 = off). min_confidence: drop
    confidence below this (0 = off; needs per-Gaussian confidence).
    merge_smooth: on/off, with smooth_levels (1: 2x2 blocks, 2: also 4x4, ...
    up to 2**4; which blocks carry texture is decided scale-free, see
    rasterizer.compaction.merge.texture_ok), smooth_colour_tol (an absolute
    cap on the max - min of each DC colour channel in a block; 1 = none),
    smooth_opacity_tol (max - min opacity),
    smooth_plane_tol (rms distance from the block's plane / range) and
    smooth_max_incidence_deg (largest angle between the plane's normal and
    the ray; also what rejects depth steps). max_count, max_bytes: optional cap (None = off); max_bytes counts the PLY.
    split_textured: textured pixels of an upload finer than the grid become 2x2 surfels
    (:func:`rasterizer.compaction.split.split_textured`, which needs the upload: the service's
    ``build_scene`` runs it after the other steps, within the cap).
    """

    min_opacity: float = 1.0 / 255.0
    min_confidence: float = 0.0
    merge_smooth: bool = True
    # 2x2 blocks only. 2 (also 4x4) left 3-16% fewer Gaussians on the dev scenes, but rendered 1-5 dB
    # further from the uncompacted scene (within 0.03 dB of 1 against the target images).
    smooth_levels: int = 1
    # No absolute colour cap: the scale-free texture test (merge.texture_ok) decides, sharper than a cap of
    # 0.06 at +0-8% Gaussians (docs/design.md, Compaction). Incidence 55 deg against 45: Gaussians fewer on
    # m3d / zind 2+6 / zind 4+5 37.7 / 30.7 / 45.7% -> 49.2 / 40.5 / 54.2%; 60 deg made zind pano_6 fall to
    # 34 dB against the uncompacted render.
    smooth_colour_tol: float = 1.0
    smooth_opacity_tol: float = 0.1
    smooth_plane_tol: float = 0.002
    smooth_max_incidence_deg: float = 55.0
    max_count: int | None = None
    max_bytes: int | None = None
    split_textured: bool = True

    def __post_init__(self) -> None:
        for name in ("min_opacity", "min_confidence", "smooth_colour_tol", "smooth_opacity_tol", "smooth_plane_tol"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise CompactionError(f"{name} must be a finite number >= 0, got {v!r}")
        if not (isinstance(self.smooth_levels, (int, np.integer)) and not isinstance(self.smooth_levels, bool)
                and 1 <= self.smooth_levels <= MAX_SMOOTH_LEVELS):
            raise CompactionError(f"smooth_levels must be an integer in 1..{MAX_SMOOTH_LEVELS}, "
                                  f"got {self.smooth_levels!r}")
        if not (np.isfinite(self.smooth_max_incidence_deg) and 0 <= self.smooth_max_incidence_deg <= 90):
            raise CompactionError(f"smooth_max_incidence_deg must be in [0, 90], got {self.smooth_max_incidence_deg!r}")
        for name in ("max_count", "max_bytes"):
            v = getattr(self, name)
            if v is not None and (int(v) != v or v < 0):
                raise CompactionError(f"{name} must be a non-negative integer or null, got {v!r}")

    @classmethod
    def off(cls) -> "CompactionOptions":
        """Every step disabled (compact() then returns its input unchanged)."""
        return cls(min_opacity=0.0, min_confidence=0.0, merge_smooth=False, split_textured=False)

    @classmethod
    def from_dict(cls, d: dict | None) -> "CompactionOptions":
        """Options from a JSON object (API ``options.compaction``); unknown keys raise."""
        d = dict(d or {})
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise CompactionError(f"unknown compaction option(s) {unknown}; known: {sorted(names)}")
        return cls(**d)

    def to_dict(self) -> dict:
        return asdict(self)


def _ply_sizes(sh_coeffs: int) -> tuple[int, int]:
    """(bytes of a PLY's header, bytes per Gaussian) for ``sh_coeffs`` SH coefficients per channel."""
    header = len(ply_bytes(Gaussians.empty(int(round(np.sqrt(sh_coeffs))) - 1)))
    # the header's vertex count has more digits for larger counts; allow 12
    return header + 12, 4 * (17 + 3 * (sh_coeffs - 1))


def ply_count_for_bytes(max_bytes: int, sh_coeffs: int) -> int:
    """Largest Gaussian count whose PLY (header included) fits in ``max_bytes``."""
    header, per = _ply_sizes(sh_coeffs)
    return max(0, (int(max_bytes) - header) // per)


def ply_bytes_for_count(count: int, sh_coeffs: int) -> int:
    """Fewest bytes in which :func:`ply_count_for_bytes` fits ``count`` Gaussians (its inverse)."""
    header, per = _ply_sizes(sh_coeffs)
    return header + int(count) * per


def count_limit(opts: CompactionOptions, sh_coeffs: int) -> int | None:
    """The Gaussian count ``max_count`` / ``max_bytes`` allow (None: no cap)."""
    limit = None if opts.max_count is None else int(opts.max_count)
    if opts.max_bytes is not None:
        by_bytes = ply_count_for_bytes(int(opts.max_bytes), sh_coeffs)
        limit = by_bytes if limit is None else min(limit, by_bytes)
    return limit
