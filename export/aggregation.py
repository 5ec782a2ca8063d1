"""Edge-aware, all-convolutional filtering: box / guided filters, push-pull fill.

Everything is separable average pooling and elementwise maths with static
shapes, so it exports to ONNX and runs fast in onnxruntime. Tensors are
(N, C, h, w); the guide is (N, 1, h, w) grey in [0, 1]. ``wrap=True``
treats the width axis as periodic (ERP longitude).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


def box_filter(x: torch.Tensor, radius: int, wrap: bool = False) -> torch.Tensor:
    """Mean over a (2r+1)^2 window, separable; borders average the pixels inside."""
    k = 2 * radius + 1
    if wrap:
        x = torch.cat([x[..., -radius:], x, x[..., :radius]], dim=-1)
        x = F.avg_pool2d(x, (1, k), stride=1, padding=0)
    else:
        x = F.avg_pool2d(x, (1, k), stride=1, padding=(0, radius), count_include_pad=False)
    return F.avg_pool2d(x, (k, 1), stride=1, padding=(radius, 0), count_include_pad=False)


def guided_filter_coeffs(guide: torch.Tensor, src: torch.Tensor, radius: int, eps: float, wrap: bool = False):
    """He et al. linear coefficients (a, b) with q = a * guide + b, per channel of src."""
    mean_i = box_filter(guide, radius, wrap)
    mean_p = box_filter(src, radius, wrap)
    mean_ip = box_filter(guide * src, radius, wrap)
    var_i = box_filter(guide * guide, radius, wrap) - mean_i * mean_i
    a = (mean_ip - mean_i * mean_p) / (var_i + eps)
    b = mean_p - a * mean_i
    return a, b


def guided_upsample(guide: torch.Tensor, src: torch.Tensor, guide_fine: torch.Tensor, radius: int, eps: float,
                    wrap: bool = False) -> torch.Tensor:
    """``src`` on ``guide``'s grid -> ``guide_fine``'s grid: guided-filter coefficients fitted on the
    coarse grid, bilinearly upsampled and applied to the fine guide (edges follow the fine image)."""
    a, b = guided_filter_coeffs(guide, src, radius, eps, wrap)
    size = guide_fine.shape[-2:]
    a = F.interpolate(a, size=size, mode="bilinear", align_corners=False)
    b = F.interpolate(b, size=size, mode="bilinear", align_corners=False)
    return a * guide_fine + b


def guided_filter(guide: torch.Tensor, src: torch.Tensor, radius: int, eps: float, wrap: bool = False) -> torch.Tensor:
    """Edge-preserving smoothing of every channel of ``src`` guided by ``guide``."""
    a, b = guided_filter_coeffs(guide, src, radius, eps, wrap)
    return box_filter(a, radius, wrap) * guide + box_filter(b, radius, wrap)


class CostAggregation(nn.Module):
    """Multi-scale guided-filter aggregation of a cost volume (N, D, h, w).

    Each plane of the volume is filtered with the target image as guide at
    every radius in ``radii`` and the results are averaged: support grows
    over flat, same-coloured areas without bleeding across image edges.
    """

    def __init__(self, radii=(2, 6), eps: float = 1e-3, wrap: bool = False) -> None:
        super().__init__()
        self.radii = tuple(radii)
        self.eps = float(eps)
        self.wrap = wrap

    def forward(self, cost: torch.Tensor, guide: torch.Tensor) -> torch.Tensor:
        out = None
        for r in self.radii:
            q = guided_filter(guide, cost, r, self.eps, self.wrap)
            out = q if out is None else out + q
        return out / len(self.radii)


def pyramid_levels(height: int, width: int, min_size: int = 2) -> int:
    """How many times both sides can be halved exactly while staying >= min_size."""
    levels = 0
    while height % 2 == 0 and width % 2 == 0 and min(height, width) // 2 >= min_size:
        height, width, levels = height // 2, width // 2, levels + 1
    return levels


def push_pull(value: torch.Tensor, weight: torch.Tensor, levels: int, fallback: torch.Tensor,
              saturation: float = 0.5) -> torch.Tensor:
    """Confidence-weighted normalised-convolution pyramid fill of (N, 1, h, w) maps.

    Push: average (w x) and w down ``levels`` halvings. Pull: from coarse to
    fine, a pixel keeps its own weighted mean where its weight is high and
    takes the upsampled coarser estimate where it is low (blend by
    min(w / saturation, 1)). Where no weight exists at all the result
    tends to ``fallback`` (scalar tensor).
    """
    num, den = [value * weight], [weight]
    for _ in range(levels):
        num.append(F.avg_pool2d(num[-1], 2))
        den.append(F.avg_pool2d(den[-1], 2))
    eps = 1e-4
    est = (num[-1] + eps * fallback) / (den[-1] + eps)
    for lvl in range(levels - 1, -1, -1):
        up = F.interpolate(est, size=num[lvl].shape[-2:], mode="bilinear", align_corners=False)
        own = num[lvl] / den[lvl].clamp(min=1e-6)
        alpha = (den[lvl] / saturation).clamp(max=1.0)
        est = alpha * own + (1.0 - alpha) * up
    return est


def solve_spd(mat: dict, rhs: list) -> list:
    """Solve A x = b per pixel for a small symmetric positive definite A, unrolled (LDL^T).

    ``mat[(i, j)]`` (i >= j) and ``rhs[i]`` are tensors of one shape; no
    matrix inverse or decomposition op in the graph, only elementwise maths.
    """
    n = len(rhs)
    lo: dict = {}
    diag = []
    for j in range(n):
        dj = mat[(j, j)]
        for k in range(j):
            dj = dj - lo[(j, k)] * lo[(j, k)] * diag[k]
        dj = dj.clamp(min=1e-8)
        diag.append(dj)
        for i in range(j + 1, n):
            s = mat[(i, j)]
            for k in range(j):
                s = s - lo[(i, k)] * lo[(j, k)] * diag[k]
            lo[(i, j)] = s / dj
    y = []
    for i in range(n):
        s = rhs[i]
        for k in range(i):
            s = s - lo[(i, k)] * y[k]
        y.append(s)
    x = [None] * n
    for i in range(n - 1, -1, -1):
        s = y[i] / diag[i]
        for k in range(i + 1, n):
            s = s - lo[(k, i)] * x[k]
        x[i] = s
    return x


def linear_push_pull(value: torch.Tensor, weight: torch.Tensor, guide: torch.Tensor, levels: int,
                     fallback: torch.Tensor, saturation: float = 0.5) -> torch.Tensor:
    """Edge-aware :func:`push_pull`: the coarse estimate is a local linear model in a K-channel guide,
    v ~ a . g + b per pyramid cell.

    Push: confidence-weighted moments of value, guide and their products, averaged down ``levels``
    halvings (one pool per level). A pixel with little weight of its own takes the model at its *own*
    guide value. ``guide`` (N or 1, K, h, w) is pre-scaled so that the regularisation is
    the identity (a channel's eps is 1 in its units). With the three ray
    direction components as guide this is a *planar* fill: a plane
    n . X = c seen from the camera has inverse range (n . d) / c, exactly
    linear in the ray direction d, so a textureless wall between confident
    pixels is filled by the plane through them, not a constant. Adding the
    grey level as a fourth channel keeps the fill edge-aware: a flat curtain in front
    of a patterned wall takes the depth of the confident pixels that look like it
    instead of averaging across them. Where no weight exists the result tends to ``fallback``.

    Each level solves (C + I) a = cov + a_up (C, cov: the cell's weighted
    guide covariance and guide-value covariance; the prior is the upsampled
    coarser slope), blends with the coarser model by min(w / saturation, 1),
    and the finest pixels take the upsampled model at their own guide.
    """
    k_ch = guide.shape[1]
    guide = guide.expand(value.shape[0], k_ch, *value.shape[-2:])
    pairs = [(i, j) for i in range(k_ch) for j in range(i + 1)]
    chans = [weight, weight * value, weight * guide, weight * value * guide]
    chans += [weight * guide[:, i : i + 1] * guide[:, j : j + 1] for i, j in pairs]
    mom = [torch.cat(chans, dim=1)]
    for _ in range(levels):
        mom.append(F.avg_pool2d(mom[-1], 2))

    def fit(m: torch.Tensor, prior_eps: float, prior):
        w, wv = m[:, 0:1], m[:, 1:2]
        den = w + prior_eps
        mean_v = (wv + prior_eps * fallback) / den
        mean_g = [m[:, 2 + i : 3 + i] / den for i in range(k_ch)]
        cov = [m[:, 2 + k_ch + i : 3 + k_ch + i] / den - mean_g[i] * mean_v for i in range(k_ch)]
        mat = {}
        for n_pair, (i, j) in enumerate(pairs):
            c = m[:, 2 + 2 * k_ch + n_pair : 3 + 2 * k_ch + n_pair] / den - mean_g[i] * mean_g[j]
            mat[(i, j)] = c + 1.0 if i == j else c
        rhs = cov if prior is None else [c + p for c, p in zip(cov, prior)]
        return w, mean_v, mean_g, solve_spd(mat, rhs)

    def up(t: torch.Tensor, size) -> torch.Tensor:
        return F.interpolate(t, size=size, mode="bilinear", align_corners=False)

    _, mean_v, mean_g, a = fit(mom[-1], 1e-4, None)
    b = mean_v - sum(ai * gi for ai, gi in zip(a, mean_g))
    for lvl in range(levels - 1, 0, -1):
        size = mom[lvl].shape[-2:]
        a_up = [up(ai, size) for ai in a]
        b_up = up(b, size)
        w, mean_v, mean_g, own = fit(mom[lvl], 1e-6, a_up)
        alpha = (w / saturation).clamp(max=1.0)
        a = [alpha * o + (1.0 - alpha) * u for o, u in zip(own, a_up)]
        b = alpha * (mean_v - sum(ai * gi for ai, gi in zip(a, mean_g))) + (1.0 - alpha) * b_up
    size = value.shape[-2:]
    coarse = up(b, size) + sum(up(ai, size) * guide[:, i : i + 1] for i, ai in enumerate(a))
    alpha = (weight / saturation).clamp(max=1.0)
    return alpha * value + (1.0 - alpha) * coarse
