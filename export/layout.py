"""Indoor layout prior: floor and ceiling as horizontal planes, fed to the fill as weak observations.

On real captures most unconfident pixels are textureless floor and ceiling; the planar fill then
extrapolates them from whatever confident pixels lie nearby (furniture, walls) and smears them.
This stage gives the fill a geometric fallback instead (an indoor layout prior):

1. gravity = the mean of the two cameras' down axes (OpenCV camera y) in the world; captures whose
   cameras are not both upright (down axes more than ``UPRIGHT_DEG`` apart) get no prior;
2. the world heights along gravity of both views' confident points, below and above the cameras
   (|sin elevation| > ``ELEVATION_FIT``), go into one confidence-weighted log-distance histogram
   each. The ceiling is its mode; the floor is the farthest peak below the cameras that holds at
   least ``FLOOR_PEAK_SHARE`` of the heaviest one's weight (3-bin sums), since bed, table and dresser tops are nearer
   and often heavier (on m3d the mode switched between the floor and the furniture tops when
   the sweep's range moved by a few percent, docs/design.md). Each is
   refined by the weighted mean of the points within 1.5 bins. Scale-free: distances are in units
   of the geometric-mean range of the confident points;
3. each pixel's plane inverse range (floor below the horizon, ceiling above), with a weight that
   ramps with |sin elevation| from ``elevation[0]`` to ``elevation[1]`` (the horizon is walls and
   furniture), is zero within ``nadir_deg`` of straight down (under a camera stands its own rig or
   what it was set over, not the floor) and is gated by agreement: the confidence-weighted share of nearby confident pixels
   (a push-pull pyramid) within ``tol`` of the plane, squared. So a bed or table whose confident
   edges sit off the floor keeps its own fill, while an empty floor between confident floor
   pixels takes the plane;
4. the fill sees (w v + s p m) / (w + s m) with weight w + s m, where w, v are its own weight and
   inverse range, p, m the plane's inverse range and gated weight, and s = ``strength``;
5. nothing lies below the floor: after the coarse fill and on the final map, a ray below the horizon
   keeps at most (1 + ``tol``) times the floor's range along it (:func:`clamp_below_floor`). The
   fill extrapolates textureless floor from far confident pixels and sinks it; surfels under the
   floor then show through it from every viewpoint (on zind_room09 10-12% of the coarse pixels,
   drawn as dark stains on the floor between the cameras; docs/design.md, "Nothing below the
   floor").

Measurements behind the defaults: docs/design.md.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from .aggregation import push_pull

#: Cameras whose down axes differ by more than this (degrees) get no prior (not an upright capture).
UPRIGHT_DEG = 10.0
#: Points with |sin elevation| above this take part in the floor / ceiling fit.
ELEVATION_FIT = 0.25
#: Histogram of log(plane distance / scale): bins over [log 0.05, log 5].
HIST_BINS = 96
HIST_RANGE = (math.log(0.05), math.log(5.0))
#: The floor is the farthest histogram peak holding at least this share of the heaviest peak's weight.
FLOOR_PEAK_SHARE = 0.5
#: Rays with sin(elevation below the horizon) under this are left to the walls (floor range > 20 x height).
CLAMP_MIN_SIN = 0.05


def _level_distance(dist: torch.Tensor, weight: torch.Tensor, farthest_share: float | None = None) -> torch.Tensor:
    """One level's distance from weighted positive distances (N,); scalar.

    The log histogram's mode, or with ``farthest_share`` the farthest local peak of its 3-bin sums
    (a level's whole weight, however the bins split it) of at least that share of the heaviest;
    refined by the weighted mean within 1.5 bins.
    """
    lo, hi = HIST_RANGE
    step = (hi - lo) / (HIST_BINS - 1)
    centres = torch.linspace(lo, hi, HIST_BINS, dtype=dist.dtype)
    x = torch.log(dist.clamp(min=1e-3))
    hist = (F.relu(1.0 - (x.unsqueeze(1) - centres).abs() / step) * weight.unsqueeze(1)).sum(0)
    if farthest_share is None:
        k = torch.argmax(hist)
    else:
        padded = F.pad(hist, (1, 1))
        mass = padded[:-2] + hist + padded[2:]
        padded = F.pad(mass, (1, 1))
        peak = (mass >= padded[:-2]) & (mass > padded[2:]) & (mass >= farthest_share * mass.max())
        bins = torch.arange(HIST_BINS)
        k = torch.where(peak, bins, torch.zeros_like(bins)).max()  # the heaviest is a peak: never empty
    near = ((x - centres[k]).abs() <= 1.5 * step).to(dist.dtype) * weight
    return torch.exp((near * x).sum() / near.sum().clamp(min=1e-6))


def _sin_elevation(rays: torch.Tensor, rot: torch.Tensor, gravity: torch.Tensor) -> torch.Tensor:
    """(2, G h w) sine of each camera-frame ray's elevation below the horizon, per view (rot (2, 3, 3))."""
    world = torch.matmul(rays.reshape(1, -1, 3), rot.transpose(1, 2))
    return (world * gravity).sum(-1)


def fit_planes(rays: torch.Tensor, inv: torch.Tensor, weight: torch.Tensor, c2w: torch.Tensor):
    """Floor and ceiling of both views from their confident points.

    rays (G, h, w, 3) camera-frame unit rays; inv, weight (2G, 1, h, w) inverse range and fill
    weight ([view][grid]); c2w (2, 4, 4). Returns (gravity (3,) world unit down axis, floor and
    ceiling (2,) per view: distance below / above that camera along gravity, upright scalar 0 or 1).
    """
    rot, centre = c2w[:, :3, :3], c2w[:, :3, 3]
    down = rot[:, :, 1]  # (2, 3) camera y axes in the world
    gravity = down.sum(0)
    gravity = gravity / torch.sqrt((gravity * gravity).sum()).clamp(min=1e-12)
    upright = ((down[0] * down[1]).sum() >= math.cos(math.radians(UPRIGHT_DEG))).to(inv.dtype)
    height = centre @ gravity  # (2,) camera positions along gravity
    sin_el = _sin_elevation(rays, rot, gravity).reshape(-1)  # > 0 below the horizon
    rng = (1.0 / inv.clamp(min=1e-6)).reshape(-1)
    w = weight.reshape(-1)
    h_mean = height.mean()
    level = (height.reshape(2, 1) - h_mean + rng.reshape(2, -1) * sin_el.reshape(2, -1)).reshape(-1)
    scale = torch.exp((w * torch.log(rng)).sum() / w.sum().clamp(min=1e-6))
    below = (sin_el > ELEVATION_FIT).to(inv.dtype)
    above = (sin_el < -ELEVATION_FIT).to(inv.dtype)
    floor = h_mean + scale * _level_distance(level / scale, w * below, FLOOR_PEAK_SHARE)
    ceiling = h_mean - scale * _level_distance(-level / scale, w * above)
    return gravity, floor - height, height - ceiling, upright


def plane_prior(planes, rays: torch.Tensor, c2w: torch.Tensor, elevation: tuple[float, float], nadir_deg: float = 0.0):
    """Plane inverse range and ramp weight (2G, 1, h, w) for camera-frame rays (G, h, w, 3); no weight
    within ``nadir_deg`` degrees of straight down."""
    gravity, floor, ceiling, upright = planes
    g_count, h, w = rays.shape[:3]
    sin_el = _sin_elevation(rays, c2w[:, :3, :3], gravity)
    dist = torch.where(sin_el > 0, floor.reshape(2, 1), ceiling.reshape(2, 1))
    inv = sin_el.abs() / dist.clamp(min=1e-6)
    lo, hi = elevation
    ramp = ((sin_el.abs() - lo) / (hi - lo)).clamp(0.0, 1.0) * upright * (dist > 0).to(inv.dtype)
    if nadir_deg > 0:
        ramp = ramp * (sin_el < math.cos(math.radians(nadir_deg))).to(inv.dtype)
    return inv.reshape(2 * g_count, 1, h, w), ramp.reshape(2 * g_count, 1, h, w)


def with_plane_prior(inv: torch.Tensor, weight: torch.Tensor, plane_inv: torch.Tensor, ramp: torch.Tensor,
                     levels: int, strength: float, tol: float):
    """(value, weight) (N, 1, h, w) for the fill: the plane as weak, agreement-gated observations."""
    on_plane = ((inv - plane_inv).abs() <= tol * plane_inv).to(inv.dtype)
    agree = push_pull(on_plane, weight * ramp, levels, torch.zeros((), dtype=inv.dtype)).clamp(0.0, 1.0)
    prior = strength * ramp * agree * agree
    total = weight + prior
    return (weight * inv + prior * plane_inv) / total.clamp(min=1e-9), total


def clamp_below_floor(planes, inv: torch.Tensor, rays: torch.Tensor, c2w: torch.Tensor, tol: float) -> torch.Tensor:
    """Inverse range (2G, 1, h, w) with no point beyond (1 + tol) x the floor's range along its ray.

    rays (G, h, w, 3) camera-frame unit rays of ``inv``'s grid; applies below the horizon
    (sin elevation > ``CLAMP_MIN_SIN``) of upright captures with a floor below the cameras.
    """
    gravity, floor, _, upright = planes
    g_count, h, w = rays.shape[:3]
    sin_el = _sin_elevation(rays, c2w[:, :3, :3], gravity)  # (2, G h w)
    dist = floor.reshape(2, 1)
    on = (sin_el > CLAMP_MIN_SIN).to(inv.dtype) * (dist > 0).to(inv.dtype) * upright
    floor_inv = on * sin_el / (dist.clamp(min=1e-6) * (1.0 + tol))
    return torch.maximum(inv, floor_inv.reshape(2 * g_count, 1, h, w))
