"""Settings of the training-free encoder (one exported model per setting).

Everything that changes the graph's shapes or constants lives here; the
pose-dependent inputs (warp grids, near/far) are runtime inputs instead.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

from rasterizer.depth_gaussians import SURFEL_MAX_STRETCH, SURFEL_SCALE_FACTOR

#: Named settings on the error/run-time curve (see export/benchmark_depth.py).
#: Measured on m3d_bedroom (export/benchmark_depth.py): at 64x192 features
#: 32 -> 64 planes lowers AbsRel 0.16/0.09 -> 0.12/0.06 (refs 00/02); 96 and
#: 128 planes do not help further, and 128x384 features (downscale 2) with
#: the same window sizes were worse and 4-6x slower, so both presets keep
#: downscale 4 and differ in plane count.
#: 0.5.0 re-check (planar fill, quality settings otherwise): 96 / 128 planes raise the target
#: PSNR (25.34 -> 25.63 / 25.88 dB) but worsen AbsRel (00: 0.1039 -> 0.1129 / 0.1135; 02: 0.0594
#: -> 0.0672 / 0.0638), zind mean 18.80 -> 18.84 / 18.74, and ONNX time ~1.5-2x (single runs,
#: load ~3.5 on 2 cores); 128 planes with lr_tol_planes 3 (same inverse-range tolerance):
#: 0.1080 / 0.0646, 26.13 dB, zind 18.69; also excluding 3 planes around the peak: 0.1068,
#: 26.05, 18.79. So the quality preset stays at 64 planes.
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
    # features and matching (export/features.py, export/cost_volume.py):
    # "window" = ZNCC + census on the warped grey image in target windows,
    # "descriptor" = per-pixel ZNCC/census descriptors warped and correlated
    matcher: str = "window"
    zncc_radius: int = 2
    census_radii: tuple[int, ...] = (1, 3)
    # 0.5.0: zncc_eps 0.02 -> 0.002 and census_sigma 0.03 -> 0.015, quality preset, m3d_bedroom
    # AbsRel 00 / 02, delta<1.25 00 / 02, target dB, zind_room09 mean of 4 dB: 0.4.0 0.1039 /
    # 0.0594, 0.914 / 0.942, 25.34, 18.80 -> 0.0905 / 0.0530, 0.936 / 0.952, 25.41, 18.76 (fast
    # preset: 0.1526 / 0.0904, 0.855 / 0.924, 24.93, 18.14 -> 0.1208 / 0.0764, 0.912 / 0.932, 25.09, 18.42).
    # Same graph, same run time. Steps (AbsRel 00 / 02, dB, dB):
    # zncc_eps 0.01: 0.1000 / 0.0573 (depth only); 0.005: 0.0958 / 0.0553, 25.19, 18.44;
    # 0.002: 0.0912 / 0.0540, 25.20, 18.67; 0.001: 0.0906 / 0.0538 (depth only);
    # 0.002 + census_sigma 0.015: 0.0905 / 0.0530, 25.41, 18.76; + census_sigma 0.01: 0.0905 /
    # 0.0524, 25.27, 18.73; zncc_eps 0.001 + census 0.015: 0.0898 / 0.0527, 25.38, 18.52;
    # + peak_margin_scale 0.4: 25.56, 18.79 (0.6: 25.59, 18.79; fast preset 0.1208 / 0.0764,
    # 25.22, 18.42) but it lowers every opacity
    # (m3d max 0.86 -> 0.62, 0.8% of Gaussians above 0.5 instead of 6%), so it stays 0.2;
    # + fill_margin_scale 0.02 instead:
    # 0.0908 / 0.0530, 25.37, 18.68. Depth-only screens at 0.4.0 that did not pay (AbsRel 00 /
    # 02): zncc_radius 1 0.1080 / 0.0609, 3 0.1052 / 0.0607; census_radii (1, 2) 0.1069 / 0.0596,
    # (2, 4) 0.1043 / 0.0603; agg_radii (2, 8) 0.1094, (3, 6) 0.1102, (1, 4) 0.1045,
    # (2, 6, 12) 0.1134; agg_eps 3e-3 0.1030 / 0.0589, 3e-2 0.1073; zncc_weight 0.3 0.1039,
    # 0.7 0.1091; census_sigma 0.06 0.1107; readout softargmin (beta 50 / 100) 0.1331 / 0.1149;
    # lr_tol_planes 1.0 0.1058 / 0.0581, 2.0 0.1052, 3.0 0.1095; upsample_radius 1 / 4 0.1046 /
    # 0.1050; excluding 1.0 or 2.5 planes (not 1.5) around the peak for the margin: no change.
    census_sigma: float = 0.015
    zncc_eps: float = 0.002
    zncc_weight: float = 0.5
    # aggregation (export/aggregation.py)
    agg_radii: tuple[int, ...] = (2, 6)
    # 1e-2 (was 1e-3): m3d_bedroom 24.37 -> 24.42 dB, zind_room09 mean of 4 18.08 -> 18.20 dB
    # (with scale_factor 0.5); 1e-4 was worse on both
    agg_eps: float = 1e-2
    # read-out (export/readout.py)
    readout: str = "wta"  # "wta" (parabolic sub-plane) | "softargmin"
    softargmin_beta: float = 50.0
    # Two confidences from the same peak margin (export/readout.py): the fill weights use a steep
    # one (fill_margin_scale; None = peak_margin_scale), the output confidence / opacity a gentle
    # one. One shared scale had to trade depth for rendering (0.02: AbsRel 00 0.119 -> 0.112 but
    # m3d 24.37 -> 24.18 dB; 0.1: the reverse). Decoupled (with scale_factor 0.5, agg_eps 1e-2),
    # fill 0.02 / opacity 0.1: AbsRel 0.112 / 0.062, m3d 24.77 dB, zind 18.40 dB; fill 0.01 /
    # opacity 0.2: 0.109 / 0.062, 25.00 dB, 18.43 dB; opacity 0.4: 25.18 dB, 18.46 dB, same depth.
    peak_margin_scale: float = 0.2
    fill_margin_scale: float | None = 0.01
    lr_tol_planes: float = 1.5
    # fill and upsampling: "pushpull" (plain weighted pyramid) | "guided" (pyramid of local
    # linear models in the grey guide, export/aggregation.guided_push_pull, eps = fill_eps)
    # | "planar" (local linear models of inverse range in the ray direction d: exact for planes,
    # 1/r = n.d / c; export/aggregation.linear_push_pull, eps = fill_plane_scale^2 feature
    # pixels^2 on d) | "planar_guided" (d and grey together, grey eps = fill_eps).
    # guided over pushpull (fill margin 0.01, opacity margin 0.2): AbsRel 00 0.1089 -> 0.1074,
    # m3d 25.00 -> 25.11 dB, zind 18.43 -> 18.49 dB; fill_eps 3e-3: 25.22 dB but zind pano_5 -0.17 dB
    # 0.4.0, planar_guided over guided (AbsRel 00 / 02, m3d dB, zind mean of 4 dB; guided:
    # 0.1074 / 0.0614, 25.11, 18.49): scale 4 0.1039 / 0.0594, 25.34, 18.80; scale 0.5 0.1037 /
    # 0.0601, 25.53, 18.29; 1: 0.1021 / 0.0588, 25.49, 18.44; 2: 0.1025 / 0.0588, 25.43, 18.55;
    # 3: 0.1032 / 0.0591, 25.38, 18.64; 8: 0.1054 / 0.0601, 25.28, 18.81. "planar" (no grey) at
    # scale 2: 0.1028 / 0.0589, 25.30, 18.56. At scale 4, fill_eps 3e-3: 25.49, 18.64; 3e-2: 25.26,
    # 18.92. fill_margin_scale 0.02 / 0.005 with it: 25.23 / 25.42 dB, zind 18.95 / 18.64.
    fill: str = "planar_guided"
    fill_eps: float = 1e-2
    fill_plane_scale: float = 4.0
    fill_min_weight: float = 0.05
    # cascade stage (export/fine_sweep.py): fine_hypotheses per pixel (0 = off) on a grid
    # fine_downscale times smaller than the Gaussians', fine_step coarse plane steps apart; with
    # fine_fill its own left-right check (fine_lr_tol coarse steps) and planar fill at that grid.
    # 0.6.0, quality preset, torch run of the same graph (AbsRel 00 / 02, m3d 01 dB, zind mean of 4
    # dB; 0.5.0: 0.0905 / 0.0530, 25.41, 18.76): J 9 no fill 0.0794 / 0.0453, 25.79, 18.82; J 7
    # 25.82; J 13 0.0775 / 0.0478, 25.99, 18.75; J 17 25.70; step 0.25 25.75, 1.0 25.21; agg (1, 3)
    # 25.70, (4, 12) 25.89; fine_downscale 1 25.37 (4.5 s); blending by fine confidence no better.
    # With fine_fill: J 9 tol 1 / 2 / 3 / 100: 25.75 / 26.03 (J 7) / 26.38 / 25.73, zind (tol 3)
    # 18.57; J 11 tol 3 0.0750 / 0.0429, 26.50, zind 18.55; tol 6 26.31, zind 18.74; tol 4 (the
    # default) 0.0753 / 0.0432, 26.54, zind 18.68; 48 coarse planes 26.27 (AbsRel 0.092). zind's
    # poses are approximate (~0.1-3 deg): the finer grid is more sensitive to them, and its fill
    # costs 0.08 dB there at tol 4 (0.2 dB at tol 3).
    fine_hypotheses: int = 0
    fine_downscale: int = 2
    fine_step: float = 0.5
    fine_agg_radii: tuple[int, ...] = (2, 6)
    fine_fill: bool = False
    fine_lr_tol: float = 4.0
    upsample: str = "guided"  # "guided" | "bilinear"
    upsample_radius: int = 2
    upsample_eps: float = 1e-3
    # Gaussian head (export/gaussian_head.py): oriented surfels spanning the steps to the neighbouring
    # pixels (sigma = scale_factor steps), opaque so that plain front-to-back compositing covers the
    # scene (tuning log: docs/experiments.md, "Real Gaussians").
    scale_factor: float = SURFEL_SCALE_FACTOR
    ray_scale_ratio: float = 0.1
    max_stretch: float = SURFEL_MAX_STRETCH
    # opacity = min + (max - min) * confidence ** gamma; the floor is high: an unconfident pixel keeps
    # the fill's geometric depth and is drawn (nearly) opaque instead of translucent.
    opacity_min: float = 0.98
    opacity_max: float = 0.99
    opacity_gamma: float = 2.0
    # Tried in 0.4.0, did not pay: the warp GridSample as four GatherElements + lerps (indices from
    # the warp grids in the graph): 0.19 -> 0.16 s alone (8 x 1 x 64 x 192 source, 64 planes, ORT
    # 2 threads), but the whole quality model 1.39 / 0.88 / 0.91 s -> 1.44 / 0.88-1.03 / 1.28 s in
    # interleaved runs on the loaded 2-core box (load 3.5-4.2): no consistent gain. Precomputed
    # int64 indices + weights fed from numpy: 0.24 -> 0.08 s alone, but ~300 MB more inputs per pair.
    # Also not paying: an opacity factor exp(-(s / tol)^2) for "flying" pixels between
    # the sides of a depth step (s = min(v - min, max - v) / v of the filled inverse range v in a
    # 3x3 feature window): tol 0.05 m3d 25.34 -> 25.17 dB, zind mean 18.80 -> 17.79; 0.15: 25.48,
    # 18.55; 0.3: 25.40, 18.73.
    # default runtime sweep range in units of the baseline (rasterizer.sweep.default_near_far)
    near_per_baseline: float = 0.3
    far_per_baseline: float = 20.0
    name: str = "omnisplat-trainingfree"
    version: str = "0.7.0"
    extra: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.width != 2 * self.height:
            raise ValueError(f"ERP width must be 2 x height, got {self.height}x{self.width}")
        full_h, full_w = self.full_size
        if full_h % self.downscale or full_w % self.downscale:
            raise ValueError(f"grid size {full_h}x{full_w} is not divisible by downscale={self.downscale}")
        if self.matcher not in ("window", "descriptor"):
            raise ValueError(f"matcher must be 'window' or 'descriptor', got {self.matcher!r}")
        if self.readout not in ("wta", "softargmin"):
            raise ValueError(f"readout must be 'wta' or 'softargmin', got {self.readout!r}")
        if self.fill not in ("pushpull", "guided", "planar", "planar_guided"):
            raise ValueError(f"fill must be 'pushpull', 'guided', 'planar' or 'planar_guided', got {self.fill!r}")
        if self.upsample not in ("guided", "bilinear"):
            raise ValueError(f"upsample must be 'guided' or 'bilinear', got {self.upsample!r}")
        if self.fill_plane_scale <= 0:
            raise ValueError(f"fill_plane_scale must be > 0, got {self.fill_plane_scale}")
        if self.fine_hypotheses:
            if self.fine_hypotheses < 3 or self.fine_hypotheses % 2 == 0:
                raise ValueError(f"fine_hypotheses must be 0 or odd and >= 3, got {self.fine_hypotheses}")
            if full_h % self.fine_downscale or full_w % self.fine_downscale:
                raise ValueError(f"grid size {full_h}x{full_w} is not divisible by fine_downscale={self.fine_downscale}")
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
        d = asdict(self)
        d.pop("extra")
        d.update(self.extra)
        return d


def make_config(preset: str | None = None, **overrides) -> EncoderConfig:
    """An :class:`EncoderConfig` from a named preset plus explicit overrides."""
    base: dict = {}
    if preset is not None:
        if preset not in PRESETS:
            raise ValueError(f"unknown preset {preset!r}; expected one of {sorted(PRESETS)}")
        base.update(PRESETS[preset])
    base.update({k: v for k, v in overrides.items() if v is not None})
    return EncoderConfig(**base)
