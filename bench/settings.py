"""The settings the quality bench sweeps, and the ONNX model each one needs.

A :class:`Setting` is one point of the error-against-run-time plot. Kinds:

* ``"model"``: reconstruct with the ONNX encoder at (height, width, planes),
  encoder on Yin-Yang grids or raw ERP, render with the Yin-Yang or the
  direct ERP rasterizer.
* ``"oracle"``: Gaussians from the ground-truth depth of both references
  (only scenes with depth), rendered at the target: the ceiling.
* ``"copy"``: the nearest reference, rotated into the target's orientation
  (an infinite-depth warp): the floor.

A model setting with ``rig`` composites the capture rig both references show at their nadir over each
render (``rig=true`` of the render API, :mod:`rasterizer.rig`); on a scene without a detected rig it is
the plain render. A model setting with ``api`` reconstructs through the service's own path
(``service.pipeline.build_scene`` with default options: encoder, compaction) and renders as the render API does
(its near cull scaled to the sweep's near plane): what a user gets from POST + GET render.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Literal

Kind = Literal["model", "oracle", "copy"]
Rasterizer = Literal["yinyang", "direct"]

RESOLUTIONS: tuple[tuple[int, int], ...] = ((256, 512), (512, 1024))
PLANES: tuple[int, ...] = (32, 64, 128)
#: Where the paper's 2x2 ablation (encoder x rasterizer, Table 3) is run.
ABLATION_POINT: tuple[int, int, int] = (256, 512, 64)
#: A finer-feature point (512x1024, 64 planes, cost volume at 1/2 of the Gaussian grid instead of
#: the presets' 1/4): the slow end of the curve.
QUALITY_POINT: tuple[int, int, int, int] = (512, 1024, 64, 2)


@dataclass(frozen=True)
class Setting:
    """One bench configuration (see the module docstring)."""

    kind: Kind
    height: int = 0
    width: int = 0
    planes: int = 0
    erp_encoder: bool = False
    rasterizer: Rasterizer = "yinyang"
    downscale: int | None = None  # feature grid = Gaussian grid / downscale; None = exporter preset
    rig: bool = False  # composite the capture rig over the render (module docstring)
    api: bool = False  # the service's pipeline and render API (module docstring)

    @property
    def name(self) -> str:
        if self.kind == "copy":
            return "copy nearest reference"
        if self.kind == "oracle":
            return f"GT-depth oracle, {self._raster_label()} rasterizer"
        enc = "ERP" if self.erp_encoder else "YY"
        ds = "" if self.downscale is None else f", features /{self.downscale}"
        rig = ", capture rig layer" if self.rig else ""
        api = ", service pipeline" if self.api else ""
        return (f"{self.height}x{self.width}, {self.planes} planes{ds}, {enc} encoder, {self._raster_label()} "
                f"rasterizer{rig}{api}")

    @property
    def slug(self) -> str:
        if self.kind == "copy":
            return "copy"
        if self.kind == "oracle":
            return f"oracle_{self.rasterizer}"
        enc = "erp" if self.erp_encoder else "yy"
        ds = "" if self.downscale is None else f"_d{self.downscale}"
        tail = ("_rig" if self.rig else "") + ("_api" if self.api else "")
        return f"{self.height}x{self.width}_p{self.planes}{ds}_{enc}enc_{self.rasterizer}{tail}"

    @property
    def model_key(self) -> tuple[int, int, int, bool, int | None] | None:
        """(height, width, planes, erp_encoder, downscale) of the ONNX model this setting needs."""
        if self.kind != "model":
            return None
        return (self.height, self.width, self.planes, self.erp_encoder, self.downscale)

    def _raster_label(self) -> str:
        return "Yin-Yang" if self.rasterizer == "yinyang" else "direct ERP"

    def to_dict(self) -> dict:
        return {**asdict(self), "name": self.name, "slug": self.slug}


def full_grid() -> list[Setting]:
    """Resolution x planes (Yin-Yang encoder and rasterizer), a finer-feature point, the 2x2 ablation, oracle, copy."""
    grid = [Setting("model", h, w, p) for (h, w) in RESOLUTIONS for p in PLANES]
    h, w, p, ds = QUALITY_POINT
    grid.append(Setting("model", h, w, p, downscale=ds))
    h, w, p = ABLATION_POINT
    for erp_encoder in (False, True):
        for rasterizer in ("yinyang", "direct"):
            s = Setting("model", h, w, p, erp_encoder, rasterizer)
            if s not in grid:
                grid.append(s)
    grid.append(Setting("oracle"))
    grid.append(Setting("copy"))
    return grid


def short_grid(height: int = 64, width: int = 128, planes: int = 16, downscale: int = 1) -> list[Setting]:
    """One small model setting plus the copy baseline (the CI smoke run; same model as stability --short)."""
    return [Setting("model", height, width, planes, downscale=downscale), Setting("copy")]


def parse_setting(text: str) -> Setting:
    """Parse ``HxW:planes[:erp|yy][:yinyang|direct][:dK][:rig][:api]``, ``oracle[:direct]`` or ``copy``.

    ``dK`` sets the feature downscale K (default: the exporter's preset); ``rig`` the capture rig layer;
    ``api`` the service's pipeline and render API.
    """
    parts = text.strip().lower().split(":")
    api = len(parts) > 2 and parts[-1] == "api"
    if api:
        parts.pop()
    if parts[0] == "copy":
        return Setting("copy")
    if parts[0] == "oracle":
        return Setting("oracle", rasterizer=_raster(parts[1] if len(parts) > 1 else "yinyang", text))
    try:
        h, w = (int(v) for v in parts[0].split("x"))
        planes = int(parts[1])
    except (ValueError, IndexError):
        raise ValueError(f"bad setting {text!r}; expected e.g. '256x512:64:yy:yinyang', 'oracle' or 'copy'") from None
    rig = len(parts) > 2 and parts[-1] == "rig"
    if rig:
        parts.pop()
    downscale = None
    if len(parts) > 2 and parts[-1][:1] == "d" and parts[-1][1:].isdigit():
        downscale = int(parts.pop()[1:])
        if downscale <= 0:
            raise ValueError(f"bad downscale in {text!r}")
    enc = parts[2] if len(parts) > 2 else "yy"
    if enc not in ("yy", "erp"):
        raise ValueError(f"bad encoder {enc!r} in {text!r}; expected 'yy' or 'erp'")
    if w != 2 * h or h <= 0 or planes <= 0:
        raise ValueError(f"bad setting {text!r}: need W = 2H > 0 and planes > 0")
    if len(parts) > 4:
        raise ValueError(f"bad setting {text!r}: too many fields")
    return Setting("model", h, w, planes, enc == "erp", _raster(parts[3] if len(parts) > 3 else "yinyang", text),
                   downscale, rig, api)


def _raster(value: str, text: str) -> Rasterizer:
    if value not in ("yinyang", "direct"):
        raise ValueError(f"bad rasterizer {value!r} in {text!r}; expected 'yinyang' or 'direct'")
    return value  # type: ignore[return-value]
