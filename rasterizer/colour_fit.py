"""Pixel colours that reproduce each reference through the compositor: one closed-form colour-fit step.

A reference's pixel-aligned surfels overlap their grid neighbours (0.4-0.7 pixel pitches wide, so that
plain compositing closes the surface), so a render at the reference's own pose shows its image blurred
by the footprints, and so does every nearby view. Refinement (+opt, :mod:`rasterizer.refine`) undoes
that by gradient steps over full renders, seconds per scene. This module takes one Jacobi step of the
same fit at the cost of a few image-sized array passes:

* :func:`own_view_render` composites each pixel of reference v's grid from the K x K grid neighbours'
  own Gaussians only: their projected ellipses (:func:`rasterizer.splat.project`, with the render's
  low-pass), alpha = min(0.99, opacity g), front to back in range order, as
  :mod:`rasterizer.composite` does. Footprints beyond the window and the other reference's Gaussians
  are left out: the step fits each view's own blur, not the blend of two views.
* :func:`fit_reference_colours` adds ``strength * confidence * (c - render)`` to the pixel colours c,
  clipped to [0, 1]. Where the window's coverage alpha is below 1 the rest is taken as c itself (what
  lies behind is not known here). The confidence weight keeps the step off Gaussians whose depth is a
  guess, where a sharper colour at the wrong place costs the novel views more than the blur does
  (docs/design.md).
"""

from __future__ import annotations

import numpy as np

from .camera import DEFAULT_NEAR, Camera
from .composite import ALPHA_MAX, ALPHA_MIN
from .gaussians import Gaussians, rgb_to_sh_dc, sh_dc_to_rgb
from .splat import shared_pose
from .splat.projection import project_columns
from .threads import map_threads

#: Step size of the fit (x the Gaussian's confidence): 1 would be a plain Jacobi step, more
#: over-relaxes it; chosen on the dev scenes (docs/design.md).
COLOUR_FIT_STRENGTH = 1.5
#: Window of grid neighbours composited per pixel (odd): 3 x 3 covers footprints up to ~1 pitch.
COLOUR_FIT_TAPS = 3
#: Gaussians nearer their camera than this fraction of the baseline are left out of the composite (the
#: encoder's sweep starts at 0.3 baselines). A near plane at the scene's own scale gives a scene scaled
#: by any factor the same colours; a fixed one would cull a millimetre-scale scene.
NEAR_PER_BASELINE = 1e-3


def check_colour_fit(value) -> float:
    """``value`` as a fit strength (a finite number >= 0); raises ValueError saying what was sent."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not (np.isfinite(value) and value >= 0):
        raise ValueError(f"colour_fit: expected a finite number >= 0 (0 turns the colour-fit step off), got {value!r}")
    return float(value)


def _grid_composite(part: Gaussians, colours: np.ndarray, c2w: np.ndarray, kind: str, height: int, width: int,
                    taps: int, near: float) -> tuple[np.ndarray, np.ndarray]:
    """One grid of :func:`own_view_render`: (colour (H W, 3), coverage alpha (H W,)) float32.

    The Gaussians are projected once; the window composite then runs band by band of
    :data:`BAND_PIXELS` pixels (:func:`_band_composite`), whose temporaries stay in the CPU cache
    (every pixel's arithmetic is its own, so the bands give the same values as one pass).
    """
    r = taps // 2
    camera = Camera(kind, width, height, c2w, near=near)
    proj = project_columns(shared_pose(part, camera), camera)
    # per pixel-aligned Gaussian: centre offset from its own pixel (px), conic, opacity; its range
    # (float64, the rasterizer's sort key); culled ones (behind, too near, outside the domain) keep
    # opacity 0 and an infinite range
    k = proj.index
    # one padded plane per parameter (component-major: the tap loop's array passes run on contiguous rows)
    pad_w = width + 2 * r
    par = np.zeros((6, height + 2 * r, pad_w), dtype=np.float32)
    dist = np.full((height + 2 * r, pad_w), np.inf)
    n_px = height * width
    if k.size == n_px and (k.size == 0 or (k[0] == 0 and k[-1] == n_px - 1 and np.all(k[1:] > k[:-1]))):
        # every pixel's Gaussian projected (the usual case): the planes' interiors in row-major order
        inner = (slice(r, r + height), slice(r, r + width))
        par[(0,) + inner] = proj.mx.reshape(height, width) - np.arange(width)
        par[(1,) + inner] = proj.my.reshape(height, width) - np.arange(height)[:, None]
        for c, col in enumerate((proj.con_a, proj.con_b, proj.con_c), start=2):
            par[(c,) + inner] = col.reshape(height, width)
        par[(5,) + inner] = part.opacities.reshape(height, width)
        dist[inner] = proj.ranges.reshape(height, width)
    else:
        row, col = k // width, k % width
        at = (row + r) * pad_w + (col + r)  # flat index into a padded plane
        planes = par.reshape(6, -1)
        planes[0, at] = proj.mx - col
        planes[1, at] = proj.my - row
        planes[2, at] = proj.con_a
        planes[3, at] = proj.con_b
        planes[4, at] = proj.con_c
        planes[5, at] = part.opacities[k]
        dist.reshape(-1)[at] = proj.ranges
    rgb = np.zeros((3, height + 2 * r, pad_w), dtype=np.float32)
    rgb[:, r:r + height, r:r + width] = np.asarray(colours, dtype=np.float32).reshape(height, width, 3).transpose(2, 0, 1)
    out = np.empty((3, height, width), dtype=np.float32)
    cover = np.empty((height, width), dtype=np.float32)
    rows = max(1, BAND_PIXELS // width)
    for r0 in range(0, height, rows):
        r1 = min(height, r0 + rows)
        _band_composite(par[:, r0:r1 + 2 * r], dist[r0:r1 + 2 * r], rgb[:, r0:r1 + 2 * r], r, out[:, r0:r1],
                        cover[r0:r1])
    return out.reshape(3, -1).T, cover.reshape(-1)


#: Pixels per band of the window composite: its (taps^2, band) temporaries, about 280 bytes a pixel at
#: 3 x 3 taps, then stay in the CPU's cache instead of streaming image-sized arrays through memory
#: (and their pages are reused instead of faulted in anew for every grid).
BAND_PIXELS = 16384


def _band_composite(par: np.ndarray, dist: np.ndarray, rgb: np.ndarray, r: int, out: np.ndarray, cover: np.ndarray
                    ) -> None:
    """The window composite of one band of h rows: par (6, h + 2r, w + 2r), dist (h + 2r, w + 2r) and
    rgb (3, h + 2r, w + 2r) padded planes; writes colour into out (3, h, w) and coverage into cover (h, w).

    Arrays are tap-major, (T, h w) with T = (2r + 1)^2, so every pass runs over whole image rows. Front
    to back is range order with ties in window order (a stable sort): each tap's place in it is counted
    from the T (T - 1) / 2 pairwise comparisons of the window's ranges, far cheaper than sorting
    h w rows of T keys; the transmittance is then the running product in that order.
    """
    height, width = out.shape[1:]
    n_px = height * width
    offsets = [(di, dj) for di in range(-r, r + 1) for dj in range(-r, r + 1)]
    windows = [(slice(r + di, r + di + height), slice(r + dj, r + dj + width)) for di, dj in offsets]
    n_taps = len(offsets)
    alpha = np.empty((n_taps, height, width), dtype=np.float32)
    rng = np.empty(alpha.shape, dtype=np.float64)
    dx, dy, term = (np.empty((height, width), dtype=np.float32) for _ in range(3))
    skip = np.empty((height, width), dtype=bool)
    for t, ((di, dj), win) in enumerate(zip(offsets, windows)):
        q = par[(slice(None),) + win]
        a = alpha[t]
        np.subtract(-dj, q[0], out=dx)  # pixel centre minus the neighbour's projected centre
        np.subtract(-di, q[1], out=dy)
        np.multiply(q[2], dx, out=a)  # q2 dx dx + 2 q3 dx dy + q4 dy dy, products left to right
        a *= dx
        np.multiply(2, q[3], out=term)
        term *= dx
        term *= dy
        a += term
        np.multiply(q[4], dy, out=term)
        term *= dy
        a += term
        a *= np.float32(-0.5)
        np.exp(a, out=a)
        a *= q[5]
        np.minimum(a, ALPHA_MAX, out=a)
        np.greater_equal(a, ALPHA_MIN, out=skip)
        np.logical_not(skip, out=skip)
        a[skip] = 0.0  # skipped, as the compositor does (NaN too)
        rng[t] = dist[win]
    alpha = alpha.reshape(n_taps, n_px)
    rng = rng.reshape(n_taps, n_px)
    # place of each tap front to back: the taps before it in range order, ties in window order. Tap s starts
    # before all T - 1 - s later taps and moves behind each one that is not behind it (never below 0).
    place = np.repeat(np.arange(n_taps - 1, -1, -1, dtype=np.min_scalar_type(n_taps))[:, None], n_px, axis=1)
    before = np.empty(n_px, dtype=bool)
    for t in range(1, n_taps):
        for s in range(t):
            np.less_equal(rng[s], rng[t], out=before)
            place[t] += before
            place[s] -= before
    flat = place.astype(np.intp)  # (T, h w) flat index of each tap in the front-to-back array
    flat *= n_px
    flat += np.arange(n_px)
    front = np.empty((n_taps, n_px), dtype=np.float32)
    front.reshape(-1)[flat] = alpha
    # alpha x transmittance before it, the running product taken front to back
    trans = np.subtract(np.float32(1.0), front[0])
    for t in range(1, n_taps):
        keep = np.subtract(np.float32(1.0), front[t])
        front[t] *= trans
        trans *= keep
    weight = front.reshape(-1)[flat]  # back to window order
    out[...] = 0.0
    for t, win in enumerate(windows):
        wt = weight[t].reshape(height, width)
        for c in range(3):
            out[c] += wt * rgb[(c,) + win]
    np.subtract(np.float32(1.0), trans.reshape(height, width), out=cover)


def _check_taps(taps: int) -> None:
    if isinstance(taps, bool) or not isinstance(taps, (int, np.integer)) or taps < 1 or taps % 2 == 0:
        raise ValueError(f"taps must be a positive odd integer, got {taps!r}")


def own_view_render(gaussians: Gaussians, colours: np.ndarray, c2w: np.ndarray, grids: tuple[str, ...],
                    height: int, width: int, taps: int = COLOUR_FIT_TAPS, near: float = DEFAULT_NEAR
                    ) -> tuple[np.ndarray, np.ndarray]:
    """One reference's pixel-aligned Gaussians composited at its own pose, each pixel from its grid
    neighbours (module docstring); Gaussians nearer the camera than ``near`` are left out, as in a render.

    gaussians: N = G H W Gaussians in [grid][row][col] order, placed by the reference at ``c2w`` (4x4
    OpenCV camera-to-world); colours (N, 3) their colour seen from it; grids: the G grid kinds
    (:data:`rasterizer.camera.PROJECTIONS` names), each ``height`` x ``width`` pixels; taps: odd window
    size. Returns (colour (N, 3) float32 composited over black, alpha (N,) float32 coverage).
    """
    _check_taps(taps)
    n1 = height * width
    if len(gaussians) != len(grids) * n1 or np.shape(colours) != (len(gaussians), 3):
        raise ValueError(f"need {len(grids)} x {height} x {width} Gaussians and (N, 3) colours; got "
                         f"{len(gaussians)} and {np.shape(colours)}")
    parts = [_grid_composite(gaussians.subset(slice(gi * n1, (gi + 1) * n1)), colours[gi * n1:(gi + 1) * n1],
                             c2w, kind, height, width, taps, near) for gi, kind in enumerate(grids)]
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def fit_reference_colours(layout: Gaussians, confidence: np.ndarray, c2w: np.ndarray, grids: tuple[str, ...], *,
                          strength: float = COLOUR_FIT_STRENGTH, taps: int = COLOUR_FIT_TAPS) -> Gaussians:
    """``layout`` with pixel colours moved one fit step towards reproducing each reference (module docstring).

    layout: N = 2 G H W pixel-aligned Gaussians of two views in [view][grid][row][col] order, colour in
    the SH DC band (higher bands are left as they are); confidence (2, G, H, W) in [0, 1]; c2w (2, 4, 4)
    the poses the layout's means are in; grids: the G grid kinds. strength 0 returns ``layout``.
    """
    v_count, g_count, h, w = np.shape(confidence)
    n = g_count * h * w
    if v_count != 2 or len(layout) != 2 * n or len(grids) != g_count:
        raise ValueError(f"need two views' pixel-aligned layout; got {len(layout)} Gaussians and grids {grids} "
                         f"for confidence {np.shape(confidence)}")
    strength = check_colour_fit(strength)
    _check_taps(taps)
    if strength == 0:
        return layout
    rgb = sh_dc_to_rgb(layout.sh[:, 0, :]).astype(np.float32)
    weight = np.float32(strength) * np.clip(np.asarray(confidence, dtype=np.float32), 0.0, 1.0).reshape(-1, 1)
    poses = np.asarray(c2w, dtype=np.float64)
    baseline = float(np.linalg.norm(poses[0, :3, 3] - poses[1, :3, 3]))
    if not (np.isfinite(baseline) and baseline > 0):
        raise ValueError(f"the two camera centres must differ, got a baseline of {baseline}")
    n1 = h * w
    jobs = [(v, gi, kind) for v in range(2) for gi, kind in enumerate(grids)]

    def one(job):
        v, gi, kind = job
        part = slice((v * g_count + gi) * n1, (v * g_count + gi + 1) * n1)
        render, cover = _grid_composite(layout.subset(part), rgb[part], poses[v], kind, h, w, taps,
                                        NEAR_PER_BASELINE * baseline)
        residual = cover[:, None] * rgb[part] - render  # c - (render + (1 - cover) c)
        return part, np.clip(rgb[part] + weight[part] * residual, 0.0, 1.0)

    done = map_threads(one, jobs)  # the four grids, two at a time
    new = rgb.copy()
    for part, colours in done:
        new[part] = colours
    sh = layout.sh.copy()
    sh[:, 0, :] = rgb_to_sh_dc(new)
    return layout.with_(sh=sh)
