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


# -- layout surfaces: the room as opaque geometry where matching is not confident ---------------------------

#: Azimuth directions of the wall profile (5 degree steps) and the half-widths (degrees) of the narrow
#: kernel (the profile) and the wide one (bins the narrow one leaves without enough points).
WALL_BINS = 72
WALL_NARROW_DEG = 15.0
WALL_WIDE_DEG = 30.0
#: Wall points: between ``WALL_BAND[0]`` of the way from the camera down to the floor and ``WALL_BAND[1]``
#: of the way up to the ceiling (beds, tables and counters stand lower; lamps hang higher).
WALL_BAND = (0.5, 0.8)
#: A profile bin needs this share of the mean bin weight (narrow kernel) or of it / 4 (wide kernel).
WALL_MIN_SHARE = 0.25


def _wall_profile(pts, w, centre, gravity, axes, above, below, scale, half_deg: float):
    """Weighted median horizontal distance per azimuth (WALL_BINS,) and its weight, around one camera.

    pts (N, 3) world points, w (N,) weights; axes (WALL_BINS, 3) horizontal unit directions; above / below:
    the band's limits along gravity from the camera (scalars, up negative).
    """
    rel = pts - centre
    vert = rel @ gravity
    horiz = rel - vert.unsqueeze(-1) * gravity
    dist = torch.sqrt((horiz * horiz).sum(-1)).clamp(min=1e-6)
    band = ((vert > -above) & (vert < below)).to(pts.dtype)
    cos_half = math.cos(math.radians(half_deg))
    az = F.relu((horiz / dist.unsqueeze(-1)) @ axes.transpose(0, 1) - cos_half) / (1.0 - cos_half)  # (N, K)
    lo, hi = HIST_RANGE
    step = (hi - lo) / (HIST_BINS - 1)
    centres = torch.linspace(lo, hi, HIST_BINS, dtype=pts.dtype)
    x = torch.log(dist / scale)
    dbin = F.relu(1.0 - (x.unsqueeze(1) - centres).abs() / step)  # (N, M)
    hist = (az * (w * band).unsqueeze(-1)).transpose(0, 1) @ dbin  # (K, M)
    cum = torch.cumsum(hist, dim=1)
    total = cum[:, HIST_BINS - 1:]
    idx = (cum < 0.5 * total).to(pts.dtype).sum(1).clamp(max=HIST_BINS - 1)
    return scale * torch.exp(lo + idx * step), total.squeeze(1)


def layout_inverse(planes, rays: torch.Tensor, inv: torch.Tensor, weight: torch.Tensor, c2w: torch.Tensor,
                   narrow_deg: float = WALL_NARROW_DEG):
    """Inverse range of the estimated room along each ray, and whether the room fits.

    rays (G, h, w, 3) camera-frame unit rays; inv, weight (2G, 1, h, w) matched inverse range and its
    weight ([view][grid]); planes from :func:`fit_planes`. The room around each camera: the floor and
    ceiling planes, and walls as vertical surfaces at the weighted-median horizontal distance of both
    views' confident points per 5 degrees of azimuth (kernel half-width ``narrow_deg``; points in a band
    between the floor and the ceiling, furniture mostly below it). Returns (layout (2G, 1, h, w), 0 where
    no surface is known; fit: scalar 0 or 1, 1 when the capture is upright and at least
    ``LAYOUT_FIT_SHARE`` of each view's confident weight lies within ``LAYOUT_FIT_TOL`` of the layout:
    outdoor or open spaces, where no room fits, get 0).
    """
    gravity, floor, ceiling, upright = planes
    g_count, h, w = rays.shape[:3]
    rot, centre = c2w[:, :3, :3], c2w[:, :3, 3]
    dirs = torch.matmul(rays.reshape(1, -1, 3), rot.transpose(1, 2))  # (2, n, 3) world rays
    rng = 1.0 / inv.clamp(min=1e-6).reshape(2, -1, 1)
    pts = (centre.unsqueeze(1) + dirs * rng).reshape(-1, 3)
    wt = weight.reshape(-1)
    scale = torch.exp((wt * torch.log(rng.reshape(-1))).sum() / wt.sum().clamp(min=1e-6))
    x_axis = rot[0, :, 0] - (rot[0, :, 0] @ gravity) * gravity
    e1 = x_axis / torch.sqrt((x_axis * x_axis).sum()).clamp(min=1e-9)
    e2 = torch.linalg.cross(gravity, e1)
    ang = torch.arange(WALL_BINS, dtype=rays.dtype) * (2.0 * math.pi / WALL_BINS)
    axes = torch.cos(ang).unsqueeze(1) * e1 + torch.sin(ang).unsqueeze(1) * e2  # (K, 3)
    sin_el = (dirs * gravity).sum(-1)  # (2, n) > 0 below the horizon
    horiz = dirs - sin_el.unsqueeze(-1) * gravity
    cos_el = torch.sqrt((horiz * horiz).sum(-1)).clamp(min=1e-6)
    cos_n = math.cos(math.radians(360.0 / WALL_BINS))
    out = []
    for v in range(2):
        narrow, wn = _wall_profile(pts, wt, centre[v], gravity, axes, WALL_BAND[1] * ceiling[v], WALL_BAND[0] * floor[v],
                                   scale, narrow_deg)
        wide, ww = _wall_profile(pts, wt, centre[v], gravity, axes, WALL_BAND[1] * ceiling[v], WALL_BAND[0] * floor[v],
                                 scale, WALL_WIDE_DEG)
        ok_n = (wn >= WALL_MIN_SHARE * wn.mean()).to(rays.dtype)
        ok_w = (ww >= 0.25 * WALL_MIN_SHARE * ww.mean()).to(rays.dtype)
        inv_wall_bins = ok_n / narrow + (1.0 - ok_n) * ok_w / wide  # (K,) 0 where unknown
        known = torch.maximum(ok_n, ok_w)
        # linear interpolation between neighbouring bins (a triangle of one bin in cos of the azimuth gap)
        k = F.relu((horiz[v] / cos_el[v].unsqueeze(-1)) @ axes.transpose(0, 1) - cos_n) * known
        inv_wall = cos_el[v] * (k @ inv_wall_bins) / (k.sum(-1)).clamp(min=1e-9)
        inv_floor = torch.where(sin_el[v] > 0, sin_el[v] / floor[v].clamp(min=1e-6), torch.zeros_like(inv_wall))
        inv_ceil = torch.where(sin_el[v] < 0, -sin_el[v] / ceiling[v].clamp(min=1e-6), torch.zeros_like(inv_wall))
        inv_ceil = inv_ceil * (ceiling[v] > 0).to(rays.dtype)
        inv_floor = inv_floor * (floor[v] > 0).to(rays.dtype)
        out.append(torch.maximum(inv_wall, torch.maximum(inv_floor, inv_ceil)))
    lay = torch.stack(out).reshape(2 * g_count, 1, h, w)
    near = ((inv - lay).abs() <= LAYOUT_FIT_TOL * lay).to(inv.dtype) * (lay > 0).to(inv.dtype)
    share = (near * weight).reshape(2, -1).sum(1) / weight.reshape(2, -1).sum(1).clamp(min=1e-6)
    fit = upright * (share.min() >= LAYOUT_FIT_SHARE).to(inv.dtype)
    return lay, fit


#: The room fits when each view has this share of its confident weight within LAYOUT_FIT_TOL (relative
#: inverse range) of the layout; matched rooms put most confident points on walls, floor and ceiling.
LAYOUT_FIT_SHARE = 0.3
LAYOUT_FIT_TOL = 0.25
