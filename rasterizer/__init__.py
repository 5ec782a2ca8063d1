"""Numpy Gaussian splatting for panoramas: cameras, Gaussians, PLY, render, compaction, +opt (no torch).

The public entry points::

    from rasterizer import read_ply, render
    out = render(read_ply("scene.ply"), c2w, projection="perspective", width=640, height=480)

:func:`render` takes an OpenCV camera-to-world pose and returns colour (H, W, 3), alpha (H, W) and
expected range (H, W); :func:`compact` leaves out what a scene does not need; :func:`refine` is +opt.
Everything else lives in the modules by job (geometry, camera, yin_yang, sh, gaussians, ply, sweep,
splat, composite, render, compaction, refine).
"""

from .camera import Camera
from .compaction import CompactionOptions, compact
from .gaussians import Gaussians
from .ply import read_ply, write_ply
from .refine import RefineOptions, refine
from .render import RenderOutput, render

__all__ = ["Camera", "CompactionOptions", "Gaussians", "RefineOptions", "RenderOutput", "compact", "read_ply",
           "refine", "render", "write_ply"]
