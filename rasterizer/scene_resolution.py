"""Render at the resolution the scene holds, then resize to the requested size.

A reconstruction's Gaussians are as fine as its model grid (about 2.8 pixels per degree at
512x1024), while clients ask for views at their own screen's pitch: a 1280x720 perspective view
with a 90 deg field of view samples 14 pixels per degree, so every surfel covers about 25 pixels
and the image holds no detail at that pitch. Splatting costs per covered pixel, so such a view is
rendered on a coarser pixel grid whose footprints stay resolved, and resized bilinearly:

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


def resize_pinhole(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """Bilinear resize of a pinhole image (h, w, C) rendered by :func:`reduced_pinhole` to (height, width, C).

    Both grids share the principal point (the image centre) and square pixels; output pixel (c, r)
    samples the coarse image at ((c - (width-1)/2) s + (w-1)/2, (r - (height-1)/2) s + (h-1)/2),
    s = w / width, the same ray; samples beyond the coarse grid's border take the border pixel.
    """
    h, w = image.shape[:2]
    s = w / float(width)

    def taps(n_out, n_in, centre_out):
        x = (np.arange(n_out) - centre_out) * s + (n_in - 1) / 2.0
        x = np.clip(x, 0.0, n_in - 1)
        i0 = np.minimum(np.floor(x).astype(np.int64), max(n_in - 2, 0))
        f = (x - i0).astype(np.float32)
        return i0, np.minimum(i0 + 1, n_in - 1), f

    r0, r1, fr = taps(height, h, (height - 1) / 2.0)
    c0, c1, fc = taps(width, w, (width - 1) / 2.0)
    image = np.asarray(image, dtype=np.float32)
    rows = np.take(image, r0, axis=0)  # takes and in-place products: a third less time than fancy indexing
    rows *= (1.0 - fr)[:, None, None]
    tap = np.take(image, r1, axis=0)
    tap *= fr[:, None, None]
    rows += tap
    out = np.take(rows, c0, axis=1)
    out *= (1.0 - fc)[None, :, None]
    tap = np.take(rows, c1, axis=1)
    tap *= fc[None, :, None]
    out += tap
    return out
