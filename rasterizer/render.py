"""Render 3D Gaussians into ERP, Yin, Yang or perspective images (numpy, CPU).

Public entry point: :func:`render`. Pipeline, two phases:

1. :mod:`rasterizer.splat` (phase a): EWA projection with the camera's exact
   analytic Jacobian + 0.3 px^2 low-pass, culling, and the per-pixel
   front-to-back lists of (Gaussian, opacity-free weight g).
2. :mod:`rasterizer.composite` (phase b): alpha compositing with
   alpha = min(0.99, opacity * g), skip alpha < 1/255, stop at T < 1e-4.

:func:`render` runs them depth chunk after depth chunk
(:mod:`rasterizer.front_to_back`: pixels that stopped drop out, memory set by
the image and the chunk); :func:`rasterizer.splat.footprints` and
:func:`rasterizer.composite.composite` give the same images in one pass, and
their lists serve refinement.

Frames and pixels follow ``docs/conventions.md`` section 1: poses
are 4x4 OpenCV camera-to-world; pixel (r, c) centre at coordinate (c, r);
ERP ``lon = (c + 0.5)/W 2pi - pi``; ranges are Euclidean distances from the
camera centre (world units).

ERP has two methods: ``"direct"`` splats straight into the ERP grid (columns
wrap across the seam; footprints crossing a pole are mirrored over it);
``"yinyang"`` (OmniSplat) renders the Yin and Yang grids (H/2 x 3H/2 each),
merges premultiplied colour, alpha and range into the ERP with smooth
weights in their overlap, then divides range (and, with ``normalize``,
colour) by alpha (0 where alpha < 1/255).

Example::

    out = render(g, np.eye(4), projection="erp", width=1024)
    png = to_uint8(out.colour)
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Literal, NamedTuple

import numpy as np

from . import front_to_back, splat, yin_yang
from .camera import DEFAULT_NEAR, PROJECTIONS, Camera
from .composite import (
    composite,
    gaussian_table,
    normalise_range,
    ranked_table,
)
from .gaussians import Gaussians
from .scene_resolution import reduced_pinhole, render_scale, resize_pinhole
from .sh import sh_to_rgb
from .splat import ALPHA_MIN, Footprints, footprints
from .splat.projection import project_columns

__all__ = ["RenderOutput", "render", "render_camera", "to_uint8", "Camera", "footprints", "composite",
           "Footprints"]

#: Below this many Gaussians a second thread costs more than it saves.
_THREAD_MIN_GAUSSIANS = 20_000

Method = Literal["yinyang", "direct"]
METHODS = ("yinyang", "direct")
Resolution = Literal["exact", "scene"]
RESOLUTIONS = ("exact", "scene")


class RenderOutput(NamedTuple):
    """colour (H, W, 3) float32; alpha (H, W) float32 in [0, 1]; range (H, W) float32 (0 where empty)."""

    colour: np.ndarray
    alpha: np.ndarray
    range: np.ndarray


def _check_gaussians(gaussians: Gaussians) -> None:
    if not isinstance(gaussians, Gaussians):
        raise TypeError(f"gaussians must be a rasterizer.gaussians.Gaussians, got {type(gaussians).__name__}")
    gaussians.check_finite()


def _premultiplied(gaussians: Gaussians, camera: Camera, threads: int = 1, cut_sigma: float | None = None):
    """(colour*alpha (H, W, 3), alpha (H, W), range*alpha (H, W)) of one camera, front to back."""
    pose = splat.shared_pose(gaussians, camera)
    qcut = splat.opacity_cuts(gaussians.opacities, len(gaussians))

    def table(index, rank, n):  # colours and rows of the Gaussians the camera keeps only
        colours = sh_to_rgb(gaussians.sh[index], gaussians.means[index], camera.centre)
        return ranked_table(gaussians.opacities[index], colours, pose.ranges[index], rank, n)

    return front_to_back.premultiplied(pose, camera, qcut, table, threads=threads, cut_sigma=cut_sigma)


def render_camera(gaussians: Gaussians, camera: Camera, threads: int = 1,
                  cut_sigma: float | None = None) -> RenderOutput:
    """Render one :class:`Camera` (any kind), colour composited over black; ``threads`` row bands side by side;
    ``cut_sigma`` as :func:`render`'s."""
    _check_gaussians(gaussians)
    colour, alpha, range_sum = _premultiplied(gaussians, camera, threads, cut_sigma)
    return RenderOutput(colour, alpha, normalise_range(range_sum, alpha))


def _render_resized(gaussians: Gaussians, camera: Camera, scale: float, threads: int,
                    cut_sigma: float | None) -> RenderOutput:
    """``camera``'s view rendered on the pinhole grid ``scale`` times as fine, resized to the camera's size:
    the colour by Catmull-Rom, which keeps the full-size render's edges (a bilinear resize kept 0.6-0.8 of
    its high-frequency energy on some views of the dev scenes; docs/design.md, "At the scene's own
    resolution"), clipped at 0 against its overshoot; alpha and range bilinearly, within their samples'
    range."""
    colour, alpha, range_sum = _premultiplied(gaussians, reduced_pinhole(camera, scale), threads, cut_sigma)
    colour = np.maximum(resize_pinhole(colour, camera.width, camera.height, kernel="cubic"), 0.0)
    stack = resize_pinhole(np.dstack([alpha, range_sum]), camera.width, camera.height)
    alpha = np.clip(stack[:, :, 0], 0.0, 1.0)
    return RenderOutput(colour, np.ascontiguousarray(alpha), normalise_range(np.ascontiguousarray(stack[:, :, 1]), alpha))


def _render_yinyang(gaussians: Gaussians, c2w: np.ndarray, width: int, height: int, near: float,
                    threads: int, divide: bool = True, scene_resolution: bool = False,
                    cut_sigma: float | None = None) -> RenderOutput:
    h = max(1, int(round(height / 2)))
    full = Camera("yin", 3 * h, h, c2w, near=near)
    pose = splat.shared_pose(gaussians, full)  # Yin and Yang, at any size, share the pose
    yin_columns = []  # the full-size Yin projection of the scale estimate, reused when the size stays
    if scene_resolution:  # the grids on the scene's own pitch; the merge resamples them bilinearly
        columns = project_columns(pose, full)
        scaled = max(1, int(round(h * render_scale(gaussians, full, columns))))
        if scaled == h:
            yin_columns.append(columns)
        h = scaled
        del columns
    w = 3 * h
    cams = [Camera(kind, w, h, c2w, near=near) for kind in ("yin", "yang")]
    colours = sh_to_rgb(gaussians.sh, gaussians.means, cams[0].centre)
    qcut = splat.opacity_cuts(gaussians.opacities, len(gaussians))

    def rank_tables():
        return gaussian_table(gaussians.opacities, colours, pose.ranges, pose.order)  # order: a sort of all N

    def one(cam, tables, columns=None):
        c, a, r = front_to_back.premultiplied(pose, cam, qcut, tables(), columns=columns, cut_sigma=cut_sigma)
        return np.concatenate([c, a[:, :, None], r[:, :, None]], axis=2)

    def yin_cols():  # handed over, not kept: Yang's render does not hold Yin's projection
        return yin_columns.pop() if yin_columns else None

    if threads > 1 and len(gaussians) >= _THREAD_MIN_GAUSSIANS:
        # numpy releases the GIL in sorts, gathers and ufunc loops: the depth sort of all Gaussians
        # runs beside the projections, then Yin (this thread) and Yang (a worker) run side by side
        with ThreadPoolExecutor(max_workers=2) as pool:
            tables = pool.submit(rank_tables)
            yang = pool.submit(one, cams[1], tables.result)
            stacks = [one(cams[0], tables.result, yin_cols()), yang.result()]
            merged = yin_yang.yin_yang_to_erp(stacks[0], stacks[1], height, width, pool=pool)
    else:
        tables = rank_tables()
        stacks = [one(cams[0], lambda: tables, yin_cols()), one(cams[1], lambda: tables)]
        merged = yin_yang.yin_yang_to_erp(stacks[0], stacks[1], height, width)
    alpha = np.clip(merged[:, :, 3], 0.0, 1.0)
    inv = _alpha_inverse(merged[:, :, 3])
    # premultiplied colour = the composite over black; divided = V/A
    colour = merged[:, :, :3] * inv[:, :, None] if divide else merged[:, :, :3]
    rng = merged[:, :, 4] * inv
    return RenderOutput(np.ascontiguousarray(colour), np.ascontiguousarray(alpha), np.ascontiguousarray(rng))


def _alpha_inverse(alpha: np.ndarray) -> np.ndarray:
    """1 / alpha where alpha >= 1/255, 0 elsewhere: the guarded colour-by-alpha division."""
    inv = np.zeros_like(alpha)
    ok = alpha >= ALPHA_MIN
    inv[ok] = 1.0 / alpha[ok]
    return inv


def _under_backdrop(front: RenderOutput, back: RenderOutput) -> RenderOutput:
    """Plain composites of some Gaussians and of a backdrop behind all of them, the backdrop put under the
    rest: colour C_f + (1 - A_f) C_b, alpha A_f + (1 - A_f) A_b (front-to-back compositing split at the
    backdrop, whose transmittance in front is 1 - A_f), range the alpha-weighted mean of the two."""
    keep = 1.0 - front.alpha
    colour = front.colour + keep[:, :, None] * back.colour
    alpha = np.clip(front.alpha + keep * back.alpha, 0.0, 1.0)
    range_sum = front.range * front.alpha + keep * (back.range * back.alpha)
    return RenderOutput(colour.astype(np.float32), alpha.astype(np.float32),
                        normalise_range(range_sum.astype(np.float32), alpha.astype(np.float32)))


def render(gaussians: Gaussians, c2w, *, projection: str = "erp", width: int, height: int | None = None,
           fov_deg: float = 90.0, method: str = "yinyang", near: float = DEFAULT_NEAR,
           threads: int = 2, normalize: bool | None = None, resolution: Resolution = "exact",
           backdrop: int = 0, cut_sigma: float | None = None) -> RenderOutput:
    """Render Gaussians seen from pose ``c2w``.

    Parameters
    ----------
    gaussians : Gaussians, world frame. NaN/Inf anywhere raises
        :class:`~rasterizer.gaussians.GaussiansError` (a ValueError) naming the field.
    c2w : 4x4 (or 3x4) OpenCV camera-to-world pose; validated by
        :func:`rasterizer.geometry.as_c2w` (PoseError, a ValueError).
    projection : "erp" | "yin" | "yang" | "perspective". Gaussians are composited front to back
        by range, except in a perspective view, which sorts by camera-frame z as every 3DGS
        viewer does (so the API's perspective render is what a viewer shows).
    width, height : image size in pixels. Default height: W/2 (erp), W/3
        (yin, yang), W (perspective).
    fov_deg : horizontal field of view of the perspective camera.
    method : ERP only. "yinyang" (default; Yin and Yang merged into the ERP) or
        "direct" (splatted straight into the ERP grid). Other projections ignore it.
    near : Gaussians closer than this range (world units) are culled.
    threads : when > 1, ERP "yinyang" renders Yin and Yang in two threads; other projections
        composite that many row bands side by side (the same result up to float rounding); a
        ``backdrop`` is rendered in a thread of its own beside the rest.
    normalize : divide colour by alpha where alpha >= 1/255 (OmniSplat's V/A
        normalisation; thin coverage then shows the surface colour instead of a
        darkened or black hole) or, when False, return the plain front-to-back
        composite over black that every 3DGS viewer shows. None (default) keeps
        each method's historical behaviour: divided for the "yinyang" ERP, plain
        for everything else. The alpha and range outputs are the same either way.
    resolution : "exact" (default) rasterises at the requested size. "scene" renders a perspective
        view, or the Yin and Yang grids of a "yinyang" ERP, on a coarser pixel grid where the
        requested one is finer than the scene's Gaussians, and resizes it (a perspective view's colour by Catmull-Rom)
        (:mod:`rasterizer.scene_resolution`); other projections render exactly.
    backdrop : with ``resolution="scene"``, for a perspective view or a "yinyang" ERP: the last
        ``backdrop`` Gaussians are a backdrop behind all the others (the environment shell of a
        reconstruction, :mod:`rasterizer.shell`). They are then rendered apart, each part at its own
        scene resolution, and composited under the rest (the front's transmittance is 1 - its
        alpha): the shell's wide discs cost about a third of a render at the surfels' resolution.
        0 (default), or a count outside 1..N-1, renders everything in one pass.
    cut_sigma : ends every footprint this many standard deviations (Mahalanobis radius) from its
        centre, besides the 1/255 alpha rule, which alone (None, default, as the official rasterizer)
        reaches 3.33 at opacity 1; never nearer than 2 px along its narrowest axis, so that a sub-pixel
        Gaussian's footprint, the pixel filter, is not cut (:func:`rasterizer.splat.projection.sigma_cuts`). A tail
        beyond the cut carries ``exp(-cut_sigma^2 / 2)`` of the Gaussian's alpha at its centre; in a
        reconstruction's stacks of overlapping surfels the service's cut
        (``service.inputs.RENDER_CUT_SIGMA``) leaves renders 47 dB or more from the uncut ones for about
        a third less CPU time (docs/design.md, "Footprint tails").

    Returns
    -------
    RenderOutput(colour (H, W, 3) float32, alpha (H, W) float32 in [0, 1],
    range (H, W) float32 expected Euclidean range, 0 where nothing was drawn).
    """
    if projection not in PROJECTIONS:
        raise ValueError(f"projection must be one of {PROJECTIONS}, got {projection!r}")
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if resolution not in RESOLUTIONS:
        raise ValueError(f"resolution must be one of {RESOLUTIONS}, got {resolution!r}")
    width = int(width)
    if width <= 0:
        raise ValueError(f"width must be positive, got {width}")
    if height is None:
        height = {"erp": width // 2, "yin": width // 3, "yang": width // 3}.get(projection, width)
    height = int(height)
    if height <= 0:
        raise ValueError(f"height must be positive, got {height}")
    if cut_sigma is not None and not (isinstance(cut_sigma, (int, float, np.floating, np.integer))
                                      and not isinstance(cut_sigma, bool) and np.isfinite(cut_sigma) and cut_sigma > 0):
        raise ValueError(f"cut_sigma must be a positive number of standard deviations, got {cut_sigma!r}")
    _check_gaussians(gaussians)
    yinyang = projection == "erp" and method == "yinyang"
    if resolution == "scene" and 0 < int(backdrop) < len(gaussians) and (yinyang or projection == "perspective"):
        out = _render_over_backdrop(gaussians, c2w, len(gaussians) - int(backdrop), projection=projection,
                                    width=width, height=height, fov_deg=fov_deg, method=method, near=near,
                                    threads=threads, resolution=resolution, cut_sigma=cut_sigma)
        normalize = yinyang if normalize is None else normalize  # each method's default, as below
    elif yinyang:
        cam = Camera("erp", width, height, c2w, near=near)  # validates pose and sizes
        return _render_yinyang(gaussians, cam.c2w, width, height, near, int(threads),
                               divide=True if normalize is None else bool(normalize),
                               scene_resolution=resolution == "scene", cut_sigma=cut_sigma)
    else:
        camera = Camera(projection, width, height, c2w, fov_deg=fov_deg, near=near)
        scale = render_scale(gaussians, camera) if resolution == "scene" and projection == "perspective" else 1.0
        if scale < 1.0:
            out = _render_resized(gaussians, camera, scale, int(threads), cut_sigma)
        else:
            out = render_camera(gaussians, camera, int(threads), cut_sigma)
    if not normalize:
        return out
    colour = out.colour * _alpha_inverse(out.alpha)[:, :, None]
    return RenderOutput(np.ascontiguousarray(colour, dtype=np.float32), out.alpha, out.range)


def _render_over_backdrop(gaussians: Gaussians, c2w, n: int, *, threads: int, **kwargs) -> RenderOutput:
    """Plain :func:`render` of the first ``n`` Gaussians and, apart, of the backdrop after them, each at its
    own resolution (``kwargs``), the backdrop put under the rest (:func:`_under_backdrop`); with ``threads`` > 1
    the backdrop renders in a thread of its own (numpy releases the GIL)."""
    kwargs = dict(kwargs, threads=threads, normalize=False)
    front, back = gaussians.subset(slice(0, n)), gaussians.subset(slice(n, len(gaussians)))
    if int(threads) > 1:
        with ThreadPoolExecutor(max_workers=1) as pool:
            behind = pool.submit(render, back, c2w, **kwargs)
            return _under_backdrop(render(front, c2w, **kwargs), behind.result())
    return _under_backdrop(render(front, c2w, **kwargs), render(back, c2w, **kwargs))


def to_uint8(colour: np.ndarray) -> np.ndarray:
    """Float colour (any range) to uint8: clip to [0, 1], scale by 255, round half up; NaN -> 0, +Inf -> 255.

    The one float-to-8-bit conversion (API renders, reference images, CLI, benches).
    """
    c = np.nan_to_num(np.asarray(colour, dtype=np.float32), nan=0.0, posinf=1.0, neginf=0.0)
    return (np.clip(c, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
