"""The training-free OmniSplat encoder as one torch module (exported to ONNX).

Stages (each its own module, so a learned MVSplat-style backbone or cost
refinement can replace a stage without touching the geometry):

1. :class:`YinYangSampler` - ERP -> full-resolution Yin and Yang images
   (or the ERP itself in the ``erp_encoder`` ablation);
2. average pooling by ``downscale`` -> feature-grid colour; grey guide;
3. :class:`GreyFeatures` - the grey image the window matcher works on;
4. :class:`SweepCostVolume` - A<-B and B<-A sphere sweeps, each point read in
   the source grid that owns it (paper eq. 4, Yin taking the overlap), ZNCC + census
   in target windows (:class:`export.cost_volume.WindowMatcher`);
5. :class:`CostAggregation` - multi-scale guided filter per plane;
6. :class:`DepthReadout` - sub-plane depth + two peak confidences (a steep
   one weights the fill, a gentle one becomes the output confidence);
7. left-right check (A->B vs B->A) by warping, inside the graph;
8. :mod:`export.layout`: floor and ceiling planes fitted to both views' confident points,
   fed to the fills below as weak observations where nearby confident pixels agree with them,
   and a floor nothing may lie below (after the coarse fill and on the final map);
   fill of unreliable pixels (``linear_push_pull``: pyramid of local linear
   models of inverse range in the ray direction and grey level - exact for
   planes), guided-filter smoothing, guided upsampling to the Gaussian grid;
9. optional cascade stage (:class:`export.fine_sweep.FineSweep`, ``fine_hypotheses``
   > 0): a per-pixel sweep of a few hypotheses around that depth on a grid
   ``fine_downscale`` times smaller than the Gaussians', its own left-right
   check and planar fill (``fine_fill``), then the guided upsampling; the output confidence is the larger of
   the coarse one and the cascade's where its left-right check passes;
10. :class:`GaussianHead`;
11. :class:`export.matches.Matches`: each pixel's match in the other view at its
    final range, with score and a full-resolution left-right / occlusion flag.

Graph inputs (see :mod:`rasterizer.sweep` for the pose-dependent ones):
``erp_a``, ``erp_b`` (1, 3, H, W) float32 in [0, 1]; ``warp_grids``
(2, G, D, h, w, 2); ``rel_rt`` (2, 3, 4); ``inv_depths`` (D,);
``c2w`` (2, 4, 4); ``cam_quats`` (2, 4).
Outputs: ``means``, ``scales``, ``quats``, ``opacities``, ``sh_dc`` (N, .),
``range_maps``, ``confidence`` (2, G, Hg, Wg) on the Gaussian grid, ``matches``
(2, G, Hg, Wg, 5) (:mod:`export.matches`).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from rasterizer.geometry import grid_directions

from .aggregation import (
    CostAggregation,
    guided_filter,
    guided_upsample,
    linear_push_pull,
    pyramid_levels,
)
from .config import EncoderConfig
from .cost_volume import SweepCostVolume, WindowMatcher, sample_maps, stacked_source
from .features import LUMA, GreyFeatures
from .fine_sweep import FineSweep
from .gaussian_head import GaussianHead
from .layout import clamp_below_floor, fit_planes, plane_prior, with_plane_prior
from .matches import Matches
from .readout import DepthReadout, index_to_inverse, plane_step
from .select import select
from .yin_yang_sampling import YinYangSampler


class OmniSplatEncoder(nn.Module):
    """Two ERPs + sweep inputs -> Gaussians (module docstring)."""

    def __init__(self, cfg: EncoderConfig) -> None:
        super().__init__()
        self.cfg = cfg
        wrap = cfg.erp_encoder
        self.num_grids = len(cfg.grids)
        self.full_h, self.full_w = cfg.full_size
        self.feat_h, self.feat_w = cfg.feature_size
        self.sampler = None if cfg.erp_encoder else YinYangSampler(cfg.height, self.full_h, self.full_w)
        match_args = (cfg.zncc_radius, cfg.census_radii, cfg.census_sigma, cfg.zncc_eps, cfg.zncc_weight)
        self.features = GreyFeatures()
        self.cost_volume = SweepCostVolume(self.num_grids, erp_source=wrap, matcher=WindowMatcher(*match_args, wrap=wrap),
                                           aggregation=CostAggregation(cfg.agg_radii, cfg.agg_eps, wrap=wrap))
        fill_scale = cfg.peak_margin_scale if cfg.fill_margin_scale is None else cfg.fill_margin_scale
        self.readout = DepthReadout((cfg.peak_margin_scale, fill_scale))
        self.head = GaussianHead(cfg.grids, self.full_h, self.full_w, cfg.scale_factor,
                                 cfg.ray_scale_ratio, cfg.opacity_min, cfg.opacity_max,
                                 cfg.opacity_gamma, cfg.max_stretch, cfg.scale_factor_confident)
        self.matches = Matches(cfg.grids, self.full_w if wrap else 0)
        rays = np.stack([grid_directions(k, self.feat_h, self.feat_w) for k in cfg.grids]).astype(np.float32)
        self.register_buffer("feat_rays", torch.from_numpy(rays), persistent=False)  # (G, h, w, 3)
        self.register_buffer("luma", torch.tensor(LUMA).view(1, 3, 1, 1), persistent=False)
        self.levels = pyramid_levels(self.feat_h, self.feat_w)
        # planar fill guide: ray directions in units of fill_plane_scale feature-pixel pitches
        pitch = (np.pi if cfg.erp_encoder else 0.5 * np.pi) / self.feat_h
        plane_guide = rays.transpose(0, 3, 1, 2) / np.float32(pitch * cfg.fill_plane_scale)
        self.register_buffer("plane_guide", torch.from_numpy(np.ascontiguousarray(plane_guide)), persistent=False)
        self.fine = None
        if cfg.cascade:
            self.fine_h, self.fine_w = self.full_h // cfg.fine_downscale, self.full_w // cfg.fine_downscale
            fine_rays = np.stack([grid_directions(k, self.fine_h, self.fine_w) for k in cfg.grids]).astype(np.float32)
            self.register_buffer("fine_rays", torch.from_numpy(fine_rays), persistent=False)
            fine_guide = fine_rays.transpose(0, 3, 1, 2) / np.float32(pitch * cfg.fill_plane_scale)  # same angular scale
            self.register_buffer("fine_plane_guide", torch.from_numpy(np.ascontiguousarray(fine_guide)), persistent=False)
            self.fine_levels = pyramid_levels(self.fine_h, self.fine_w)
            self.fine = FineSweep(cfg.grids, cfg.fine_hypotheses, WindowMatcher(*match_args, wrap=wrap),
                                  CostAggregation(cfg.fine_agg_radii, cfg.agg_eps, wrap=wrap),
                                  DepthReadout(margin_scales=(cfg.peak_margin_scale, fill_scale)),
                                  erp_width=self.fine_w if wrap else 0)

    # -- stages ------------------------------------------------------------
    def grid_images(self, erp_a: torch.Tensor, erp_b: torch.Tensor) -> torch.Tensor:
        """(2, G, 3, Hg, Wg) full-resolution images on the Gaussian grids."""
        erps = torch.cat([erp_a, erp_b], dim=0)
        if self.sampler is None:
            return erps.unsqueeze(1)
        return self.sampler(erps)

    def lr_consistency(self, k, inv, warp_grids, rel_rt, inv_depths):
        """1 where the A->B and B->A depths agree within ``lr_tol_planes``, else 0.

        k, inv: (2, G, 1, h, w) plane index and inverse range per target map.
        For each target pixel the source location at the nearest plane is
        gathered from the warp grids; the source's own inverse range there
        (in its stacked grids, as the sweep sampled it) is compared with the
        inverse of the point's range from the source camera, |R d r + t|.
        """
        g_count, h, w = self.num_grids, self.feat_h, self.feat_w
        d_count = inv_depths.shape[0]
        idx = k.round().clamp(0, d_count - 1).to(torch.int64)  # (2, G, 1, h, w)
        # expected inverse range from the source camera, all (direction, target grid) at once
        rng = 1.0 / inv.clamp(min=1e-6)  # (2, G, 1, h, w)
        u = torch.matmul(self.feat_rays.reshape(1, g_count * h * w, 3), rel_rt[:, :, :3].transpose(1, 2))
        pt = u.reshape(2, g_count, h, w, 3) * rng.reshape(2, g_count, h, w, 1) + rel_rt[:, :, 3].reshape(2, 1, 1, 1, 3)
        expected = 1.0 / torch.sqrt((pt * pt).sum(-1)).clamp(min=1e-6)  # (2, G, h, w)
        # source location at the nearest plane for every (direction, target grid): one GatherElements
        # on the plane axis (indexing warp_grids per pairing copies the whole input)
        gather_idx = idx.reshape(2, g_count, 1, h, w, 1).expand(2, g_count, 1, h, w, 2)
        loc = torch.gather(warp_grids, 2, gather_idx).reshape(2 * g_count, h, w, 2)
        source = stacked_source(torch.stack([inv[1], inv[0]]), self.cfg.erp_encoder)  # [d] = view 1 - d
        hs, ws = source.shape[-2:]
        source = source.unsqueeze(1).expand(2, g_count, 1, hs, ws).reshape(2 * g_count, 1, hs, ws)
        seen = sample_maps(source, loc, self.cfg.erp_encoder).reshape(2, g_count, h, w)
        # one candidate step at the source's inverse range
        step = plane_step(expected, inv_depths)
        ok = ((seen - expected).abs() <= self.cfg.lr_tol_planes * step).to(k.dtype)
        return ok.reshape(2, g_count, 1, h, w)

    def observability(self, rel_rt, inv_depths):
        """(2, G, 1, h, w) in [0, 1]: 0 where depth cannot be observed (epipoles).

        The angle between the source-camera rays to a target pixel's nearest
        and farthest candidates is the parallax the whole sweep can produce;
        near the epipoles it vanishes and every plane matches equally well.
        Ramp from ``2`` to ``8`` feature pixels of travel.
        """
        g_count, h, w = self.num_grids, self.feat_h, self.feat_w
        d_count = inv_depths.shape[0]
        pitch = float(np.pi / self.feat_h) if self.cfg.erp_encoder else float(0.5 * np.pi / self.feat_h)
        out = []
        for d in range(2):
            rot, t = rel_rt[d, :, :3], rel_rt[d, :, 3]
            u = torch.matmul(self.feat_rays.reshape(g_count * h * w, 3), rot.transpose(0, 1))
            near = u / inv_depths[d_count - 1] + t
            far = u / inv_depths[0] + t
            cross = torch.linalg.cross(near, far)
            sin = torch.sqrt((cross * cross).sum(-1)) / (
                torch.sqrt((near * near).sum(-1) * (far * far).sum(-1)).clamp(min=1e-12))
            dots = (near * far).sum(-1)
            travel = select(dots < 0, 2.0, sin) / pitch  # >90 deg: plenty
            out.append(((travel - 2.0) / 6.0).clamp(0.0, 1.0).reshape(g_count, 1, h, w))
        return torch.stack(out)

    def layout(self, planes, inv, weight, rays, c2w, levels):
        """The fill's (value, weight) with the layout planes added (:func:`export.layout.with_plane_prior`)."""
        if planes is None or self.cfg.layout_strength == 0:
            return inv, weight
        plane_inv, ramp = plane_prior(planes, rays, c2w, self.cfg.layout_elevation, self.cfg.layout_nadir_deg)
        return with_plane_prior(inv, weight, plane_inv, ramp, levels, self.cfg.layout_strength, self.cfg.layout_tol)

    def floor_clamp(self, planes, inv, rays, c2w):
        """``inv`` (2G, 1, h, w) with nothing below the floor (:func:`export.layout.clamp_below_floor`)."""
        if planes is None or not self.cfg.floor_clamp:
            return inv
        return clamp_below_floor(planes, inv, rays, c2w, self.cfg.floor_clamp_tol)

    def cascade(self, inv, grey_low, grey_full, obs, rel_rt, inv_depths, c2w, planes):
        """Coarse inverse range (2G, 1, h, w) -> (refined on the fine grid, that grid's grey guide, the fine
        confidence or None).

        Guided upsampling of the coarse map seeds :class:`FineSweep`; with
        ``fine_fill`` its steep-confidence pixels that pass a fine left-right
        check (and are observable) then refill the rest by the planar fill, and its gentle confidence where
        the check passes (0 elsewhere) is returned for the output confidence (:meth:`forward`).
        """
        cfg = self.cfg
        g_count, wrap = self.num_grids, cfg.erp_encoder
        d_count = inv_depths.shape[0]
        lo, hi = inv_depths[0], inv_depths[d_count - 1]
        size = (self.fine_h, self.fine_w)
        grey = F.avg_pool2d(grey_full, cfg.fine_downscale) if cfg.fine_downscale > 1 else grey_full
        seed = guided_upsample(grey_low, inv, grey, cfg.upsample_radius, cfg.upsample_eps, wrap).clamp(min=lo, max=hi)
        # (2G, 1, h, w) one coarse candidate step at each pixel
        step = plane_step(seed, inv_depths)
        refined, conf, conf_fill = self.fine(seed, grey, self.fine_rays, rel_rt, step * cfg.fine_step, lo, hi)
        if not cfg.fine_fill:
            return refined, grey, None
        ok = self.fine.lr_consistency(refined, self.fine_rays, rel_rt,
                                      lambda e: plane_step(e, inv_depths) * cfg.fine_lr_tol)
        obs = F.interpolate(obs.reshape(2 * g_count, 1, *obs.shape[-2:]), size=size, mode="bilinear",
                            align_corners=False)
        guide = self.fine_plane_guide.unsqueeze(0).expand(2, g_count, 3, *size).reshape(2 * g_count, 3, *size)
        guide = torch.cat([guide, grey * float(cfg.fill_eps ** -0.5)], dim=1)
        value, weight = self.layout(planes, refined, conf_fill * ok * obs, self.fine_rays, c2w, self.fine_levels)
        filled = linear_push_pull(value, weight, guide, self.fine_levels, inv_depths[0])  # far: see forward()
        return guided_filter(grey, filled, 1, cfg.upsample_eps, wrap), grey, conf * ok * obs

    # -- forward -------------------------------------------------------------
    def forward(self, erp_a, erp_b, warp_grids, rel_rt, inv_depths, c2w, cam_quats):
        cfg = self.cfg
        g_count, h, w = self.num_grids, self.feat_h, self.feat_w
        wrap = cfg.erp_encoder
        full = self.grid_images(erp_a, erp_b)  # (2, G, 3, Hg, Wg)
        full_flat = full.reshape(2 * g_count, 3, self.full_h, self.full_w)
        low = F.avg_pool2d(full_flat, cfg.downscale) if cfg.downscale > 1 else full_flat
        grey_low = (low * self.luma).sum(1, keepdim=True)  # (2G, 1, h, w)
        grey_full = (full_flat * self.luma).sum(1, keepdim=True)

        feats = self.features(low).reshape(2, g_count, -1, h, w)
        cost = self.cost_volume(feats, warp_grids, grey_low)  # (2, G, D, h, w), aggregated
        d_count = cost.shape[2]
        k, conf, conf_fill = self.readout(cost.reshape(2 * g_count, d_count, h, w))  # (2G, 1, h, w)
        inv = index_to_inverse(k, inv_depths)

        ok = self.lr_consistency(k.reshape(2, g_count, 1, h, w), inv.reshape(2, g_count, 1, h, w),
                                 warp_grids, rel_rt, inv_depths)
        obs = self.observability(rel_rt, inv_depths)
        reliable = (ok * obs).reshape(2 * g_count, 1, h, w)
        weight = conf * reliable
        # where no confident pixel is anywhere near, the fill tends to the far plane: behind everything
        # seen (the mean inverse depth, ~0.6 baselines, put opaque floaters between the cameras)
        fallback = inv_depths[0]
        fill_weight = conf_fill * reliable
        use_planes = cfg.layout_strength > 0 or cfg.floor_clamp
        planes = fit_planes(self.feat_rays, inv, fill_weight, c2w) if use_planes else None
        value, value_w = self.layout(planes, inv, fill_weight, self.feat_rays, c2w, self.levels)
        guide = self.plane_guide  # (G, 3, h, w) -> per (view, grid), with the grey level as a fourth channel
        guide = guide.unsqueeze(0).expand(2, g_count, 3, h, w).reshape(2 * g_count, 3, h, w)
        guide = torch.cat([guide, grey_low * float(cfg.fill_eps ** -0.5)], dim=1)
        filled = linear_push_pull(value, value_w, guide, self.levels, fallback)
        filled = guided_filter(grey_low, filled, 1, cfg.upsample_eps, wrap)
        filled = self.floor_clamp(planes, filled, self.feat_rays, c2w)

        size = (self.full_h, self.full_w)
        fine_conf = None
        if self.fine is not None:
            filled, grey_low, fine_conf = self.cascade(filled, grey_low, grey_full, obs, rel_rt, inv_depths, c2w,
                                                       planes)
        if filled.shape[-2:] != size:
            inv_full = guided_upsample(grey_low, filled, grey_full, cfg.upsample_radius, cfg.upsample_eps, wrap)
        else:
            inv_full = filled
        inv_full = self.floor_clamp(planes, inv_full, self.head.rays, c2w)
        inv_full = inv_full.clamp(min=inv_depths[0], max=inv_depths[d_count - 1])
        conf_full = weight if cfg.downscale == 1 else F.interpolate(weight, size=size, mode="bilinear", align_corners=False)
        if fine_conf is not None:  # a match the cascade confirms at its finer grid is confident there
            conf_full = torch.maximum(conf_full, F.interpolate(fine_conf, size=size, mode="bilinear", align_corners=False))
        rng = (1.0 / inv_full).reshape(2, g_count, *size)
        conf_full = conf_full.reshape(2, g_count, *size)

        means, scales, quats, opac, sh_dc = self.head(rng, conf_full, full, c2w, cam_quats)

        def tol(expected):  # lr_tol_planes candidate steps at the other view's inverse range
            return self.cfg.lr_tol_planes * plane_step(expected, inv_depths)

        matches = self.matches(rng, conf_full, self.head.rays, rel_rt, tol)
        return means, scales, quats, opac, sh_dc, rng, conf_full, matches
