"""Settings of the training-free encoder (one exported model per setting).

Everything that changes the graph's shapes or constants lives here; the
pose-dependent inputs (warp grids, near/far) are runtime inputs instead.
Why each default is what it is (the ablations behind it): docs/design.md.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

from rasterizer.depth_gaussians import SURFEL_MAX_STRETCH, SURFEL_SCALE_FACTOR
from rasterizer.sweep import FAR_PER_BASELINE, NEAR_PER_BASELINE

#: Named settings on the error/run-time curve (``omnisplat-bench depth``); docs/design.md.
PRESETS: dict[str, dict] = {
    "fast": {"downscale": 4, "num_planes": 32},
    "quality": {"downscale": 4, "num_planes": 64, "fine_hypotheses": 11, "fine_fill": True},
}


@dataclass(frozen=True)
class EncoderConfig:
    """Shape and algorithm settings of :class:`export.model.OmniSplatEncoder`.

    height, width: ERP input size (W = 2H). The Yin/Yang grids are
    (H/2) x (3H/2) at full resolution; features and the cost volume live on
    grids ``downscale`` times smaller. ``erp_encoder`` runs the same pipeline
    on the raw ERP (paper Table 3 ablation).
    """

    height: int = 512
    width: int = 1024
    num_planes: int = 64
    downscale: int = 4
    erp_encoder: bool = False
    # matching (export/cost_volume.py): ZNCC + soft census on the warped grey image in target windows
    zncc_radius: int = 2
    census_radii: tuple[int, ...] = (1, 3)
    census_sigma: float = 0.015
    zncc_eps: float = 0.002
    zncc_weight: float = 0.5
    # aggregation (export/aggregation.py)
    agg_radii: tuple[int, ...] = (2, 6)
    agg_eps: float = 1e-2
    # read-out (export/readout.py): winner-take-all with a parabolic sub-plane step
    # two confidences from the same peak margin: a steep one weights the fill (fill_margin_scale;
    # None = peak_margin_scale), a gentle one gives the output confidence / opacity
    peak_margin_scale: float = 0.2
    fill_margin_scale: float | None = 0.01
    lr_tol_planes: float = 1.5
    # fill of unconfident pixels (export/aggregation.py, linear_push_pull): pyramid of local linear models of
    # inverse range in the ray direction (exact for planes; eps = fill_plane_scale^2 feature pixels^2) and the
    # grey level (eps = fill_eps)
    fill_eps: float = 1e-2
    fill_plane_scale: float = 3.0
    fill_min_weight: float = 0.05
    # cascade stage (export/fine_sweep.py): fine_hypotheses per pixel (0 = off) on a grid
    # fine_downscale times smaller than the Gaussians', fine_step coarse plane steps apart; with
    # fine_fill its own left-right check (fine_lr_tol coarse steps) and planar fill at that grid
    fine_hypotheses: int = 0
    fine_downscale: int = 2
    fine_step: float = 0.5
    fine_agg_radii: tuple[int, ...] = (2, 6)
    fine_fill: bool = False
    fine_lr_tol: float = 4.0
    # indoor layout prior (export/layout.py): floor / ceiling planes as weak, agreement-gated
    # observations of both fills, weight layout_strength x a ramp in |sin elevation| over
    # layout_elevation, agreement within layout_tol of the plane's inverse range (0 = off)
    layout_strength: float = 3.0
    layout_elevation: tuple[float, float] = (0.2, 0.5)
    layout_tol: float = 0.16
    # no floor prior within layout_nadir_deg of straight down: under each camera stands its own rig or
    # whatever it was set over (m3d 00: a low object at 0.91 m that the plane put at 1.36 m)
    layout_nadir_deg: float = 15.0
    # nothing below the floor (floor_clamp): a ray below the horizon keeps at most (1 + floor_clamp_tol) x
    # the fitted floor's range, after the coarse fill and on the final map (docs/design.md,
    # "Nothing below the floor")
    floor_clamp: bool = True
    floor_clamp_tol: float = 0.1
    # guided upsampling to the Gaussian grid (export/aggregation.py, guided_upsample); upsample_eps also
    # regularises the guided-filter smoothing after each fill
    upsample_radius: int = 2
    upsample_eps: float = 1e-3
    # Gaussian head (export/gaussian_head.py): oriented surfels spanning the steps to the neighbouring
    # pixels (sigma = scale_factor steps), opaque so that plain front-to-back compositing covers the
    # scene (docs/design.md).
    scale_factor: float = SURFEL_SCALE_FACTOR
    # sigma at confidence 1, linear in confidence from scale_factor at 0: where the depth is right a
    # narrower footprint is sharper, and the environment shell keeps the coverage (docs/design.md)
    scale_factor_confident: float = 0.4
    ray_scale_ratio: float = 0.1
    max_stretch: float = SURFEL_MAX_STRETCH
    # opacity = min + (max - min) * confidence ** gamma. Unconfident surfels are translucent so that the
    # two references' uncertain surfaces blend at a novel pose; the service's environment shell
    # (rasterizer.shell) behind them keeps plain compositing covered (docs/design.md).
    opacity_min: float = 0.3
    opacity_max: float = 0.99
    opacity_gamma: float = 2.0
    # default runtime sweep range in units of the baseline (rasterizer.sweep.default_near_far)
    near_per_baseline: float = NEAR_PER_BASELINE
    far_per_baseline: float = FAR_PER_BASELINE
    name: str = "omnisplat-trainingfree"
    version: str = "0.17.0"

    def __post_init__(self) -> None:
        if self.width != 2 * self.height:
            raise ValueError(f"ERP width must be 2 x height, got {self.height}x{self.width}")
        full_h, full_w = self.full_size
        if full_h % self.downscale or full_w % self.downscale:
            raise ValueError(f"grid size {full_h}x{full_w} is not divisible by downscale={self.downscale}")
        if not 0 < self.scale_factor_confident <= self.scale_factor:
            raise ValueError(f"need 0 < scale_factor_confident <= scale_factor, got {self.scale_factor_confident} "
                             f"and {self.scale_factor}")
        if self.fill_plane_scale <= 0:
            raise ValueError(f"fill_plane_scale must be > 0, got {self.fill_plane_scale}")
        if self.fine_hypotheses:
            if self.fine_hypotheses < 3 or self.fine_hypotheses % 2 == 0:
                raise ValueError(f"fine_hypotheses must be 0 or odd and >= 3, got {self.fine_hypotheses}")
            if full_h % self.fine_downscale or full_w % self.fine_downscale:
                raise ValueError(f"grid size {full_h}x{full_w} is not divisible by fine_downscale={self.fine_downscale}")
        lo, hi = self.layout_elevation
        if self.layout_strength < 0 or not 0 <= lo < hi <= 1 or self.layout_tol <= 0 \
                or not 0 <= self.layout_nadir_deg < 90:
            raise ValueError("need layout_strength >= 0, 0 <= layout_elevation[0] < [1] <= 1, layout_tol > 0 and "
                             f"0 <= layout_nadir_deg < 90; got {self.layout_strength}, {self.layout_elevation}, "
                             f"{self.layout_tol}, {self.layout_nadir_deg}")
        if not self.floor_clamp_tol >= 0:
            raise ValueError(f"floor_clamp_tol must be >= 0, got {self.floor_clamp_tol}")
        if self.num_planes < 3:
            raise ValueError(f"num_planes must be >= 3, got {self.num_planes}")

    @property
    def grids(self) -> tuple[str, ...]:
        return ("erp",) if self.erp_encoder else ("yin", "yang")

    @property
    def cascade(self) -> bool:
        """Whether the cascade stage runs: on, and its grid finer than the feature grid."""
        return self.fine_hypotheses > 0 and self.fine_downscale < self.downscale

    @property
    def full_size(self) -> tuple[int, int]:
        """Size of one Gaussian grid (Yin/Yang or ERP), one Gaussian per pixel."""
        if self.erp_encoder:
            return self.height, self.width
        return self.height // 2, 3 * self.height // 2

    @property
    def feature_size(self) -> tuple[int, int]:
        """Size of the feature / cost-volume grid."""
        h, w = self.full_size
        return h // self.downscale, w // self.downscale

    @property
    def num_gaussians(self) -> int:
        h, w = self.full_size
        return 2 * len(self.grids) * h * w

    def with_(self, **changes) -> "EncoderConfig":
        return replace(self, **changes)

    def to_dict(self) -> dict:
        return asdict(self)


def make_config(preset: str | None = None, **overrides) -> EncoderConfig:
    """An :class:`EncoderConfig` from a named preset plus explicit overrides."""
    base: dict = {}
    if preset is not None:
        if preset not in PRESETS:
            raise ValueError(f"unknown preset {preset!r}; expected one of {sorted(PRESETS)}")
        base.update(PRESETS[preset])
    base.update({k: v for k, v in overrides.items() if v is not None})
    return EncoderConfig(**base)
