"""Refuse a dual-fisheye frame sent as a panorama.

Consumer 360 cameras record two fisheye image circles side by side on black, in a 2:1 frame (a Ricoh
Theta's dual-fisheye files, an Insta360's .insp photos), and their apps stitch the equirectangular
panorama from it. Such a frame passes every check of an upload (2:1, an ordinary photo) but is no
panorama: a scene built from it would be nonsense, with no error. It is recognised by its geometry:
two circles as tall as the frame, centred at a quarter and three quarters of its width; the frame's
corners outside them are black, and the picture reaches their rim all the way round.

An equirectangular panorama is black in those corners only where the scene is black near both poles
at longitudes -180, 0 and 180 deg (a night sky above, a black nadir patch below). Then the circles'
rim is dark where it climbs towards the poles, at the top and bottom of each circle, while a
fisheye frame's rim is dark only where the scene happens to be (a dark door, a shadow: 18% of the
rim of a bedroom's frame). So the test asks for most of the rim lit, and its top and bottom most of all.
"""

from __future__ import annotations

import numpy as np

from .errors import BadInput

#: Rows of the strided view the test reads (a few thousand pixels per region are plenty).
SAMPLE_ROWS = 256
#: Luma (0-255) under which a pixel counts as black (JPEG noise on black stays under about 10).
DARK_LUMA = 24.0
#: The corners: pixels farther than this from both circles' centres, in circle radii (the frame's
#: half height); the margin leaves room for circles up to 6% larger than the frame's height.
CORNER_RADII = 1.06
#: The rim: pixels between these distances from the nearer centre, in circle radii (circles a few
#: percent smaller than the frame leave their black border outside this band).
RIM_RADII = (0.80, 0.94)
#: Angular sectors of each circle's rim; a sector is lit when most of its pixels are not black.
RIM_SECTORS = 48
#: A frame is a dual fisheye when this share of the corners is black, this share of the rim's sectors lit,
#: and this share of the sectors within POLAR_DEG of the circles' top and bottom.
BLACK_CORNERS = 0.98
LIT_RIM = 0.6
LIT_POLAR_RIM = 0.75
POLAR_DEG = 30.0


def looks_dual_fisheye(rgb: np.ndarray) -> bool:
    """Whether an (H, 2H, 3) uint8 image is two fisheye circles on black rather than an ERP panorama."""
    h, w = rgb.shape[:2]
    if h < 8 or w != 2 * h:
        return False
    step = max(1, h // SAMPLE_ROWS)
    small = rgb[::step, ::step].astype(np.float32)
    luma = 0.299 * small[:, :, 0] + 0.587 * small[:, :, 1] + 0.114 * small[:, :, 2]
    # pixel centres in circle radii (half the frame's height), from the left circle's centre
    y = ((np.arange(luma.shape[0]) * step + 0.5) / (0.5 * h) - 1.0)[:, None]
    x = (np.arange(luma.shape[1]) * step + 0.5) / (0.5 * h) - 1.0
    right = x > 1.0  # nearer the right circle, centred 2 radii to the right
    dx = np.where(right, x - 2.0, x)[None, :]
    dist = np.hypot(dx, y)
    dark = luma < DARK_LUMA
    corners = dist > CORNER_RADII
    if not corners.any() or dark[corners].mean() < BLACK_CORNERS:
        return False
    rim = (dist > RIM_RADII[0]) & (dist < RIM_RADII[1])
    angle = np.arctan2(y, dx)  # (-pi, pi]
    sector = np.minimum((angle + np.pi) / (2.0 * np.pi) * RIM_SECTORS, RIM_SECTORS - 1).astype(np.int64)
    sector = sector + RIM_SECTORS * right[None, :]
    count = np.bincount(sector[rim], minlength=2 * RIM_SECTORS)
    lit = np.bincount(sector[rim], weights=~dark[rim], minlength=2 * RIM_SECTORS)
    lit_sector = ((count > 0) & (lit > 0.5 * count)).reshape(2, RIM_SECTORS)
    centre = (np.arange(RIM_SECTORS) + 0.5) * (360.0 / RIM_SECTORS) - 180.0  # sector centre angle, deg
    polar = np.abs(np.abs(centre) - 90.0) <= POLAR_DEG  # the circles' top (-90) and bottom (+90)
    return bool(lit_sector.mean() >= LIT_RIM and lit_sector[:, polar].mean() >= LIT_POLAR_RIM)


def check_not_dual_fisheye(rgb: np.ndarray, field: str) -> None:
    """422 ``dual_fisheye`` when an upload is a camera's raw dual-fisheye frame (see the module docstring)."""
    if looks_dual_fisheye(rgb):
        raise BadInput(f"{field}: this is a dual-fisheye frame (two image circles on black), not an equirectangular "
                       "panorama; send the stitched 2:1 panorama your camera's app exports", code="dual_fisheye")
