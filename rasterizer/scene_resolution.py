"""Render at the resolution the scene holds, then resize to the requested size.

A reconstruction's Gaussians are as fine as its model grid (about 2.8 pixels per degree at
512x1024), while clients ask for views at their own screen's pitch: a 1280x720 perspective view
with a 90 deg field of view samples 14 pixels per degree, so every surfel covers about 25 pixels
and the image holds no detail at that pitch. Splatting costs per covered pixel, so such a view is
rendered on a coarser pixel grid whose footprints stay resolved, and resized (the colour by
Catmull-Rom, alpha and range bilinearly; :func:`resize_pinhole`):

* the scale is ``SCENE_SIGMA_PX / q`` (at most 1, at least ``MIN_SCALE``), where ``q`` is the
  ``SIGMA_QUANTILE`` quantile of the visible Gaussians' screen footprints at the requested size
  (geometric mean of the two sigmas of the EWA ellipse, px, without the low-pass filter), estimated
  on a deterministic sample of at most ``SAMPLE`` Gaussians; so 90% of the footprints keep at least
  ``SCENE_SIGMA_PX`` pixels of sigma on the coarser grid, and a scene with fine Gaussians (or a
  view close to a surface) is rendered at full size;
* scales above ``FULL_ABOVE`` render at full size (the saving would not pay for the resize).

The error this leaves against the full-size render is measured in docs/design.md ("Rendering");
renders that must equal the full-size rasterisation (tests against the slow reference loop, the
viewer comparison) use ``resolution="exact"`` of :func:`rasterizer.render.render`.
"""

from __future__ import annotations

import numpy as np

from .camera import Camera
from .splat.projection import LOW_PASS, Columns, project

#: Footprint sigma (px) that the SIGMA_QUANTILE-th smallest visible Gaussian keeps on the coarser grid.
SCENE_SIGMA_PX = 1.0
SIGMA_QUANTILE = 0.1
#: Smallest render scale, and the scale above which the full size is rendered.
MIN_SCALE = 1.0 / 3.0
FULL_ABOVE = 0.8
#: Gaussians sampled (evenly by index) to estimate the footprints.
SAMPLE = 65536


def footprint_sigmas(gaussians, camera: Camera, columns: Columns | None = None) -> np.ndarray:
    """(n,) geometric-mean screen sigma (px) of the visible Gaussians of a sample of at most SAMPLE.

    ``columns``: optional :func:`~rasterizer.splat.projection.project_columns` of all ``gaussians``
    into ``camera``; the sample is then read from them (the same values) instead of projected.
    """
    n = len(gaussians)
    step = -(-n // SAMPLE) if n > SAMPLE else 1
    if columns is not None:
        sel = columns.index % step == 0
        a, b, c = columns.cov_a[sel] - LOW_PASS, columns.cov_b[sel], columns.cov_c[sel] - LOW_PASS
    else:
        if step > 1:
            gaussians = gaussians.subset(np.arange(0, n, step))
        proj = project(gaussians, camera)
        a, b, c = proj.cov[:, 0] - LOW_PASS, proj.cov[:, 1], proj.cov[:, 2] - LOW_PASS
    return np.sqrt(np.sqrt(np.maximum(a * c - b * b, 0.0)))


def render_scale(gaussians, camera: Camera, columns: Columns | None = None) -> float:
    """Scale in [MIN_SCALE, 1] of the pixel grid to render ``camera``'s view on (module docstring);
    ``columns`` as in :func:`footprint_sigmas`."""
    sigma = footprint_sigmas(gaussians, camera, columns)
    if sigma.size == 0:
        return 1.0
    q = float(np.quantile(sigma, SIGMA_QUANTILE))
    scale = max(MIN_SCALE, SCENE_SIGMA_PX / q) if q > 0 else 1.0
    return 1.0 if scale > FULL_ABOVE else scale


def reduced_pinhole(camera: Camera, scale: float) -> Camera:
    """The pinhole camera of ``camera``'s view on a pixel grid ``scale`` times as fine (same field of view)."""
    w = max(2, int(round(camera.width * scale)))
    h = max(2, int(np.ceil(camera.height * w / camera.width)))
    return Camera("perspective", w, h, camera.c2w, fov_deg=camera.fov_deg, near=camera.near)


def _grid_samples(n_out: int, n_in: int, scale: float) -> np.ndarray:
    """(n_out,) positions on a coarse axis of ``n_in`` pixels of an output axis of ``n_out`` pixels,
    ``scale`` coarse pixels per output pixel, both centred on the principal point and clipped to the coarse
    grid's outermost pixel centres (beyond them the border pixel is repeated)."""
    x = (np.arange(n_out) - (n_out - 1) / 2.0) * scale + (n_in - 1) / 2.0
    return np.clip(x, 0.0, n_in - 1)


def _linear_taps(n_out: int, n_in: int, scale: float) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The two bilinear taps (indices, float32 weights) of each output position on a coarse axis."""
    x = _grid_samples(n_out, n_in, scale)
    i0 = np.minimum(np.floor(x).astype(np.int64), max(n_in - 2, 0))
    f = (x - i0).astype(np.float32)
    return [i0, np.minimum(i0 + 1, n_in - 1)], [1.0 - f, f]


def _cubic_taps(n_out: int, n_in: int, scale: float) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The four Catmull-Rom taps (indices, float32 weights summing to 1) of each output position on a coarse
    axis; indices beyond the grid take its border pixel."""
    x = _grid_samples(n_out, n_in, scale)
    i = np.floor(x).astype(np.int64)
    t = x - i
    t2, t3 = t * t, t * t * t
    weights = [0.5 * (-t3 + 2.0 * t2 - t), 0.5 * (3.0 * t3 - 5.0 * t2 + 2.0),
               0.5 * (-3.0 * t3 + 4.0 * t2 + t), 0.5 * (t3 - t2)]
    return ([np.clip(i + k, 0, n_in - 1) for k in (-1, 0, 1, 2)],
            [w.astype(np.float32) for w in weights])


def _resample(image: np.ndarray, taps, axis: int) -> np.ndarray:
    """Weighted sum of ``image``'s slices along ``axis`` (0 rows, 1 columns) at each tap."""
    shape = (-1, 1, 1) if axis == 0 else (1, -1, 1)
    out = None
    for index, weight in zip(*taps):
        part = np.take(image, index, axis=axis)  # takes and in-place products: a third less time than fancy indexing
        part *= weight.reshape(shape)
        if out is None:
            out = part
        else:
            out += part
    return out


def resize_pinhole(image: np.ndarray, width: int, height: int, kernel: str = "linear") -> np.ndarray:
    """Resize a pinhole image (h, w, C) rendered by :func:`reduced_pinhole` to (height, width, C) float32.

    Both grids share the principal point (the image centre) and square pixels; output pixel (c, r)
    samples the coarse image at ((c - (width-1)/2) s + (w-1)/2, (r - (height-1)/2) s + (h-1)/2),
    s = w / width, the same ray; samples beyond the coarse grid's border take the border pixel.
    ``kernel``: "linear" (bilinear: within the samples' range, exact on linear ramps) or "cubic"
    (Catmull-Rom, separable: exact on quadratics away from the border, sharper, and it overshoots by up to
    about a tenth of an edge's step, so its output may leave the input's range).
    """
    if kernel not in ("linear", "cubic"):
        raise ValueError(f"kernel must be 'linear' or 'cubic', got {kernel!r}")
    taps = _cubic_taps if kernel == "cubic" else _linear_taps
    h, w = image.shape[:2]
    s = w / float(width)
    image = np.asarray(image, dtype=np.float32)
    rows = _resample(image, taps(height, h, s), 0)
    return _resample(rows, taps(width, w, s), 1)
