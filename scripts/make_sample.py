"""Render the sample scene ``samples/room``: a synthetic room, ray cast in numpy.

The sample ships with the repository so that a user can try the service (and the tests can
use a scene) without any other data, and it is ours to redistribute. It is rendered by this
self-contained ray caster on purpose: it shares no code with ``rasterizer/`` (it reads only
numpy and Pillow), so its images and depth are an independent ground truth for the pixel and
frame conventions of docs/conventions.md.

The room is a box 4 m wide (x), 5 m deep (z) and 2.6 m high, with papered walls (a different
pattern on each wall, a skirting board), a framed picture, a door, a window, a plank floor
with a rug, a ceiling, a table, a bookshelf, a ball and a floor lamp. Surfaces are Lambertian,
lit by two point lights (with shadows) and an ambient term. Each pixel averages ``spp``
jittered rays; the depth of frame 01 is the Euclidean range along each pixel-centre ray.

World frame: OpenCV-like, x right, y down, z forward, in metres; the cameras are 1.5 m above
the floor (y = 0), the floor is y = +1.5 and the ceiling y = -1.1.

    python scripts/make_sample.py                # writes samples/room
Deterministic (fixed seeds): running it again rewrites the same files.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from PIL import Image

SEED = 20261127
WIDTH = 1024  # ERP width of the shipped sample (height = width / 2)
SPP = 8  # jittered rays per pixel

# Room box (world, metres; y down).
X0, X1 = -2.0, 2.0
Z0, Z1 = -2.5, 2.5
Y_CEIL, Y_FLOOR = -1.1, 1.5

# Pendant point lights: position (m) and intensity (irradiance at 1 m straight below the light).
# They shine mostly downwards (a quarter of it upwards), so the ceiling is not burnt out.
LIGHTS = [(np.array([0.9, -0.7, 1.1]), 2.0), (np.array([-1.1, -0.7, -1.3]), 1.7)]
AMBIENT = 0.28

# Wall features (world coordinates of their rectangles).
PICTURE = dict(z=(-0.65, 0.65), y=(-0.75, 0.15), frame=0.06)  # on the wall x = X1
DOOR = dict(x=(0.55, 1.45), y=(-0.6, Y_FLOOR))  # on the wall z = Z0
WINDOW = dict(x=(-1.3, -0.1), y=(-0.75, 0.35), frame=0.07)  # on the wall z = Z1
RUG = dict(x=(-0.9, 1.3), z=(0.45, 2.05))  # on the floor

# Camera centres and yaw (degrees about the world y axis); 01 lies between 00 and 02.
CAMERAS = {"00": (np.array([-0.42, 0.0, -0.14]), 8.0), "01": (np.array([0.0, 0.0, 0.0]), 0.0),
           "02": (np.array([0.43, 0.0, 0.13]), -12.0)}


# ---- Cameras and rays (docs/conventions.md, section 1)


def c2w_matrix(centre: np.ndarray, yaw_deg: float) -> np.ndarray:
    """Camera-to-world 4x4 (OpenCV axes): a rotation about world y by ``yaw_deg``, then ``centre``."""
    a = np.deg2rad(yaw_deg)
    rot = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = rot, centre
    return m


def erp_directions(rows: np.ndarray, cols: np.ndarray, width: int) -> np.ndarray:
    """Camera-frame unit directions (..., 3) of ERP positions (row, col) in pixels, fractional.

    A pixel's centre is (r + 0.5, c + 0.5): lon = col / W * 2 pi - pi, lat = pi/2 - row / H * pi,
    d = (cos lat sin lon, -sin lat, cos lat cos lon).
    """
    height = width // 2
    lon = cols / width * 2.0 * np.pi - np.pi
    lat = np.pi / 2.0 - rows / height * np.pi
    return np.stack([np.cos(lat) * np.sin(lon), -np.sin(lat), np.cos(lat) * np.cos(lon)], axis=-1)


def jitter(frame_index: int, width: int, spp: int) -> np.ndarray:
    """Sub-pixel offsets (spp, H, W, 2) in [0, 1), stratified over a 2 x (spp/2) grid; fixed seed."""
    height = width // 2
    rng = np.random.default_rng(SEED + 101 * frame_index)
    u = rng.random((spp, height, width, 2))
    nx = 2 if spp % 2 == 0 else 1
    ny = spp // nx  # strata: nx across, ny down
    s = np.arange(spp)
    u[..., 0] = (u[..., 0] + (s % nx)[:, None, None]) / nx
    u[..., 1] = (u[..., 1] + (s // nx)[:, None, None]) / ny
    return u


# ---- Procedural noise


class Noise:
    """Smooth 2-D value noise on a periodic 256 x 256 lattice of seeded random values."""

    def __init__(self, seed: int):
        self.table = np.random.default_rng(seed).random((256, 256))

    def __call__(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        iu, iv = np.floor(u), np.floor(v)
        fu, fv = u - iu, v - iv
        fu, fv = fu * fu * (3 - 2 * fu), fv * fv * (3 - 2 * fv)
        i0, j0 = iu.astype(np.int64) & 255, iv.astype(np.int64) & 255
        i1, j1 = (i0 + 1) & 255, (j0 + 1) & 255
        t = self.table
        a = t[i0, j0] * (1 - fu) + t[i1, j0] * fu
        b = t[i0, j1] * (1 - fu) + t[i1, j1] * fu
        return a * (1 - fv) + b * fv

    def fbm(self, u: np.ndarray, v: np.ndarray, octaves: int = 4) -> np.ndarray:
        """Sum of octaves, in [0, 1]."""
        out, amp, norm = np.zeros_like(u), 1.0, 0.0
        for k in range(octaves):
            out += amp * self(u * 2**k + 17.3 * k, v * 2**k + 5.1 * k)
            norm += amp
            amp *= 0.5
        return out / norm


NOISE = Noise(SEED)


def cell_random(i: np.ndarray, j: np.ndarray, salt: int) -> np.ndarray:
    """A random number in [0, 1) per integer cell (i, j): a hash of the cell, not a stream."""
    h = (i.astype(np.int64) * 73856093) ^ (j.astype(np.int64) * 19349663) ^ (salt * 83492791)
    h = (h ^ (h >> 13)) * 1274126177
    h = h ^ (h >> 16)
    return (h & 0xFFFF).astype(np.float64) / 65536.0


def mix(a, b, t):
    """Per-point blend of colours ``a`` and ``b`` ((3,) or (N, 3)) by weights ``t`` (N,)."""
    t = np.asarray(t)[:, None]
    return np.asarray(a) * (1 - t) + np.asarray(b) * t


def inside(a: np.ndarray, lo_hi: tuple[float, float]) -> np.ndarray:
    return (a > lo_hi[0]) & (a < lo_hi[1])


# ---- Materials: albedo (N, 3) in [0, 1] (linear) from world points (N, 3)


def wood(u: np.ndarray, v: np.ndarray, base: np.ndarray, salt: int) -> np.ndarray:
    """Wood grain: stretched noise bands along u; ``base`` (N, 3) per-point tint."""
    grain = NOISE.fbm(u * 1.5 + 3.0 * salt, v * 40.0, 3)
    rings = 0.5 + 0.5 * np.sin(grain * 18.0 + v * 25.0)
    return base * (0.72 + 0.28 * rings)[:, None]


def floor_albedo(p: np.ndarray) -> np.ndarray:
    x, z = p[:, 0], p[:, 2]
    plank_w, plank_l = 0.16, 1.1
    row = np.floor((x - X0) / plank_w)
    offset = cell_random(row, row, 3) * plank_l
    col = np.floor((z + offset) / plank_l)
    tint = cell_random(row, col, 4)
    base = mix([0.55, 0.33, 0.16], [0.70, 0.48, 0.26], tint)
    out = wood(z + offset, x, base, 1)
    fx = (x - X0) / plank_w - row
    fz = (z + offset) / plank_l - col
    seam = (fx < 0.04) | (fx > 0.96) | (fz < 0.006) | (fz > 0.994)
    out[seam] *= 0.45
    rug = inside(x, RUG["x"]) & inside(z, RUG["z"])
    if rug.any():
        out[rug] = rug_albedo(x[rug], z[rug])
    return out


def rug_albedo(x: np.ndarray, z: np.ndarray) -> np.ndarray:
    u = x - RUG["x"][0]
    v = z - RUG["z"][0]
    w, d = RUG["x"][1] - RUG["x"][0], RUG["z"][1] - RUG["z"][0]
    edge = np.minimum.reduce([u, v, w - u, d - v])
    red, cream, navy, gold = [0.55, 0.08, 0.07], [0.85, 0.78, 0.62], [0.10, 0.13, 0.35], [0.80, 0.58, 0.15]
    # diamonds in the field, bands at the border
    du = np.abs(((u * 4.0) % 1.0) - 0.5) + np.abs(((v * 4.0) % 1.0) - 0.5)
    out = mix(red, navy, (du < 0.35).astype(float))
    out = np.where((du < 0.12)[:, None], np.asarray(gold), out)
    out = np.where(((edge > 0.10) & (edge < 0.2))[:, None], np.asarray(cream), out)
    out = np.where((edge <= 0.10)[:, None], np.asarray(navy), out)
    fuzz = NOISE(u * 60.0, v * 60.0)
    return out * (0.85 + 0.3 * fuzz)[:, None]


def ceiling_albedo(p: np.ndarray) -> np.ndarray:
    x, z = p[:, 0], p[:, 2]
    n = NOISE.fbm(x * 3.0 + 40.0, z * 3.0, 4)
    out = mix([0.66, 0.65, 0.62], [0.80, 0.79, 0.76], n)
    # square coffers 1 m apart
    gx, gz = (x - X0) % 1.0, (z - Z0) % 1.0
    beam = (gx < 0.05) | (gz < 0.05)
    out[beam] *= 0.82
    return out


def stripes_wall(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Left wall: hand-printed green/cream stripes, a dotted motif in the green ones.

    The stripes wander (noise added to their phase) and each has its own shade and dot phase,
    so that the pattern does not repeat exactly: a strictly periodic wall is ambiguous to match.
    """
    period = 0.16
    a = u / period + 0.8 * NOISE.fbm(u * 1.7 + 50.0, v * 0.6, 2)
    k = np.floor(a)
    s = a - k
    green = mix([0.26, 0.46, 0.33], [0.36, 0.56, 0.30], cell_random(k, k, 21))
    out = mix(green, [0.86, 0.82, 0.66], (s > 0.5).astype(float))
    line = np.abs(s - 0.5) < 0.03
    out[line] = [0.70, 0.55, 0.25]
    dv = 0.16 + 0.08 * cell_random(k, k, 22)
    cv = ((v / dv + cell_random(k, k, 23)) % 1.0) - 0.5
    dots = ((s - 0.25) ** 2 * period**2 + (cv * dv) ** 2 < 0.025**2) & (s < 0.5)
    out[dots] = [0.88, 0.80, 0.40]
    return out * (0.9 + 0.2 * NOISE.fbm(u * 9.0, v * 9.0, 3))[:, None]


def damask_wall(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Right wall: a red damask of lobed medallions on a diamond lattice."""
    a, b = u / 0.3, v / 0.3
    fa, fb = (a + b) % 1.0 - 0.5, (a - b) % 1.0 - 0.5
    r = np.hypot(fa, fb)
    ang = np.arctan2(fb, fa)
    lobe = 0.22 + 0.07 * np.cos(4 * ang)
    out = mix([0.52, 0.12, 0.12], [0.78, 0.55, 0.42], (r < lobe).astype(float))
    out[(r < 0.07)] = [0.40, 0.08, 0.08]
    return out * (0.85 + 0.3 * NOISE.fbm(u * 7.0 + 9.0, v * 7.0, 3))[:, None]


def brick_wall(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Front wall: brick-pattern paper, a colour per brick, mortar lines."""
    bh, bw = 0.075, 0.24
    row = np.floor(v / bh)
    col = np.floor(u / bw + 0.5 * (row % 2))
    tint = cell_random(row, col, 7)
    out = mix([0.60, 0.30, 0.20], [0.78, 0.50, 0.34], tint)
    fv = v / bh - row
    fu = u / bw + 0.5 * (row % 2) - col
    mortar = (fv < 0.12) | (fu < 0.04)
    out[mortar] = [0.82, 0.80, 0.74]
    return out * (0.85 + 0.3 * NOISE.fbm(u * 12.0, v * 12.0 + 3.0, 3))[:, None]


def trellis_wall(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Back wall: a blue trellis of diagonal lines with small leaves."""
    a, b = (u + v) / 0.22, (u - v) / 0.22
    la, lb = np.abs((a % 1.0) - 0.5), np.abs((b % 1.0) - 0.5)
    out = mix([0.78, 0.84, 0.90], [0.20, 0.32, 0.55], ((la > 0.44) | (lb > 0.44)).astype(float))
    leaf = (la < 0.12) & (lb < 0.12) & (cell_random(np.floor(a), np.floor(b), 11) > 0.4)
    out[leaf] = [0.35, 0.55, 0.30]
    return out * (0.88 + 0.24 * NOISE.fbm(u * 8.0 + 21.0, v * 8.0, 3))[:, None]


def picture_albedo(z: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A framed 'painting': a sky, hills and a sun, from fixed coloured shapes."""
    (z0, z1), (y0, y1), f = PICTURE["z"], PICTURE["y"], PICTURE["frame"]
    u, v = (z - z0) / (z1 - z0), (y - y0) / (y1 - y0)  # v = 0 top
    sky = mix([0.35, 0.55, 0.85], [0.85, 0.75, 0.55], np.clip(v * 1.4, 0, 1))
    hill1 = v > 0.55 + 0.12 * np.sin(u * 7.0 + 1.0)
    hill2 = v > 0.70 + 0.08 * np.sin(u * 11.0 + 4.0)
    sun = (u - 0.72) ** 2 + ((v - 0.3) * 0.7) ** 2 < 0.08**2
    out = sky
    out[sun] = [0.95, 0.80, 0.25]
    out[hill1] = [0.25, 0.48, 0.20]
    out[hill2] = [0.15, 0.32, 0.12]
    out = out * (0.85 + 0.3 * NOISE.fbm(u * 40.0, v * 25.0, 3))[:, None]
    frame = (z < z0 + f) | (z > z1 - f) | (y < y0 + f) | (y > y1 - f)
    out[frame] = wood(z[frame] + y[frame], y[frame] - z[frame], np.array([[0.55, 0.40, 0.12]]), 5)
    return out


def door_albedo(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    (x0, x1), (y0, y1) = DOOR["x"], DOOR["y"]
    out = wood(y, x, np.array([[0.50, 0.30, 0.16]]), 2)
    # four recessed panels, a dark outline each
    px = (x - x0) / (x1 - x0)
    py = (y - y0) / (y1 - y0)
    for (a, b), (c, d) in [((0.12, 0.45), (0.08, 0.45)), ((0.55, 0.88), (0.08, 0.45)),
                           ((0.12, 0.45), (0.55, 0.92)), ((0.55, 0.88), (0.55, 0.92))]:
        panel = (px > a) & (px < b) & (py > c) & (py < d)
        rim = panel & ~((px > a + 0.025) & (px < b - 0.025) & (py > c + 0.012) & (py < d - 0.012))
        out[panel] *= 1.1
        out[rim] *= 0.55
    knob = (x - (x1 - 0.09)) ** 2 + (y - 0.45) ** 2 < 0.03**2
    out[knob] = [0.85, 0.70, 0.25]
    jamb = (x < x0 + 0.05) | (x > x1 - 0.05) | (y < y0 + 0.05)
    out[jamb] = [0.90, 0.89, 0.85]
    return out


def window_albedo(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A window showing a flat view: sky over a tree line; white frame and mullions."""
    (x0, x1), (y0, y1), f = WINDOW["x"], WINDOW["y"], WINDOW["frame"]
    v = (y - y0) / (y1 - y0)
    out = mix([0.55, 0.72, 0.95], [0.85, 0.90, 0.97], np.clip(v * 1.5, 0, 1))
    trees = v > 0.62 + 0.06 * NOISE.fbm(x * 12.0, np.zeros_like(x) + 3.0, 3)
    out[trees] = mix([0.12, 0.30, 0.10], [0.30, 0.50, 0.18], NOISE.fbm(x[trees] * 30.0, y[trees] * 30.0, 3))
    frame = (x < x0 + f) | (x > x1 - f) | (y < y0 + f) | (y > y1 - f)
    frame |= (np.abs(x - 0.5 * (x0 + x1)) < 0.02) | (np.abs(y - 0.5 * (y0 + y1)) < 0.02)  # mullions
    out[frame] = [0.93, 0.93, 0.92]
    return out


def wall_albedo(p: np.ndarray, wall: int) -> np.ndarray:
    """Albedo on wall 0 (x = X0), 1 (x = X1), 2 (z = Z0) or 3 (z = Z1)."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    if wall == 0:
        out = stripes_wall(z, y)
    elif wall == 1:
        out = damask_wall(z, y)
        m = inside(z, PICTURE["z"]) & inside(y, PICTURE["y"])
        out[m] = picture_albedo(z[m], y[m])
    elif wall == 2:
        out = trellis_wall(x, y)
        m = inside(x, DOOR["x"]) & inside(y, DOOR["y"])
        out[m] = door_albedo(x[m], y[m])
    else:
        out = brick_wall(x, y)
        m = inside(x, WINDOW["x"]) & inside(y, WINDOW["y"])
        out[m] = window_albedo(x[m], y[m])
    horizontal = z if wall < 2 else x
    skirting = y > Y_FLOOR - 0.1
    out[skirting] = mix([0.88, 0.87, 0.83], [0.95, 0.94, 0.90], NOISE(horizontal[skirting] * 20.0, y[skirting] * 50.0))
    out[skirting & (y < Y_FLOOR - 0.09)] *= 0.6  # the board's top edge
    return out


def books_albedo(p: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Bookshelf: a wooden case whose front (facing +x) shows rows of coloured spines."""
    y, z = p[:, 1], p[:, 2]
    out = wood(y, z, np.array([[0.45, 0.28, 0.14]]), 6)
    front = n[:, 0] > 0.5
    shelf_h = 0.36
    row = np.floor((y - SHELF["lo"][1]) / shelf_h)
    fy = (y - SHELF["lo"][1]) / shelf_h - row
    spine_w = 0.045
    col = np.floor(z / spine_w + 0.37 * row)
    h = 0.55 + 0.35 * cell_random(row, col, 9)
    book = front & (fy > 1 - h) & (fy < 0.93) & (cell_random(row, col, 12) > 0.12)
    hue = cell_random(row, col, 13)
    palette = np.array([[0.60, 0.10, 0.10], [0.10, 0.25, 0.50], [0.15, 0.40, 0.20], [0.75, 0.60, 0.20],
                        [0.35, 0.20, 0.40], [0.85, 0.82, 0.75], [0.20, 0.20, 0.22]])
    colour = palette[np.minimum((hue * len(palette)).astype(int), len(palette) - 1)]
    band = np.abs(fy - (1 - 0.6 * h)) < 0.02  # a gilt band on each spine
    colour = np.where(band[:, None], [0.85, 0.70, 0.30], colour)
    out[book] = colour[book]
    back = front & ~book & (fy < 0.93)
    out[back] *= 0.35
    return out


def ball_albedo(p: np.ndarray, n: np.ndarray) -> np.ndarray:
    """A beach ball: six coloured gores around its vertical axis, white caps."""
    lon = np.arctan2(n[:, 0], n[:, 2])
    gore = np.floor((lon + np.pi) / (2 * np.pi) * 6).astype(int) % 6
    out = np.array([[0.85, 0.15, 0.10], [0.95, 0.85, 0.15], [0.10, 0.35, 0.80],
                    [0.90, 0.90, 0.90], [0.15, 0.60, 0.25], [0.95, 0.50, 0.10]])[gore]
    out[np.abs(n[:, 1]) > 0.93] = [0.95, 0.95, 0.95]
    return out


def lamp_albedo(p: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Lamp shade: cream fabric with two brown bands; pole: dark metal."""
    y = p[:, 1]
    out = np.tile([0.90, 0.84, 0.70], (len(p), 1)) * (0.9 + 0.2 * NOISE(p[:, 0] * 80 + p[:, 2] * 80, y * 80))[:, None]
    band = (np.abs(y - (LAMP_SHADE_Y[0] + 0.04)) < 0.015) | (np.abs(y - (LAMP_SHADE_Y[1] - 0.04)) < 0.015)
    out[band] = [0.45, 0.25, 0.12]
    return out


# ---- Objects: axis-aligned boxes, a sphere, vertical capped cylinders

SHELF = dict(lo=np.array([X0, -0.35, -1.6]), hi=np.array([X0 + 0.34, Y_FLOOR, -0.4]))
TABLE_TOP = dict(lo=np.array([-0.35, 0.72, 0.95]), hi=np.array([0.85, 0.77, 1.75]))
LEG = 0.06
LAMP_XZ = np.array([1.55, -1.9])
LAMP_SHADE_Y = (-0.55, -0.25)
BALL = (np.array([-1.15, Y_FLOOR - 0.27, 1.05]), 0.27)
CRATE = dict(lo=np.array([0.25, 0.47, 1.1]), hi=np.array([0.6, 0.72, 1.45]))  # a box on the table


def flat(colour):
    return lambda p, n: np.tile(colour, (len(p), 1))


def table_albedo(p, n):
    return wood(p[:, 0], p[:, 2] + p[:, 1], np.array([[0.62, 0.40, 0.22]]), 8)


def crate_albedo(p, n):
    """A gift box: blue with a yellow ribbon cross and a lid line."""
    out = np.tile([0.15, 0.30, 0.70], (len(p), 1))
    cx, cz = 0.5 * (CRATE["lo"][0] + CRATE["hi"][0]), 0.5 * (CRATE["lo"][2] + CRATE["hi"][2])
    ribbon = (np.abs(p[:, 0] - cx) < 0.025) | (np.abs(p[:, 2] - cz) < 0.025)
    out[ribbon] = [0.95, 0.80, 0.15]
    out[np.abs(p[:, 1] - (CRATE["lo"][1] + 0.05)) < 0.006] *= 0.5
    return out


def _objects():
    """(kind, geometry, albedo function) for every object in the room."""
    objs = [("box", SHELF, books_albedo), ("box", TABLE_TOP, table_albedo), ("box", CRATE, crate_albedo)]
    (x0, _, z0), (x1, _, z1) = TABLE_TOP["lo"], TABLE_TOP["hi"]
    for lx in (x0 + 0.04, x1 - 0.04 - LEG):
        for lz in (z0 + 0.04, z1 - 0.04 - LEG):
            objs.append(("box", dict(lo=np.array([lx, TABLE_TOP["hi"][1], lz]),
                                     hi=np.array([lx + LEG, Y_FLOOR, lz + LEG])), table_albedo))
    objs += [("sphere", BALL, ball_albedo), ("cylinder", dict(xz=LAMP_XZ, r=0.2, y=LAMP_SHADE_Y), lamp_albedo)]
    objs.append(("cylinder", dict(xz=LAMP_XZ, r=0.018, y=(LAMP_SHADE_Y[1], Y_FLOOR - 0.03)), flat([0.12, 0.12, 0.13])))
    objs.append(("cylinder", dict(xz=LAMP_XZ, r=0.16, y=(Y_FLOOR - 0.03, Y_FLOOR)), flat([0.15, 0.15, 0.16])))
    return objs


OBJECTS = _objects()
EPS = 1e-6


def hit_box(o: np.ndarray, d: np.ndarray, g: dict) -> tuple[np.ndarray, np.ndarray]:
    """Entry distance (N,) (inf on a miss) and outward normal (N, 3) of rays o + t d with a box."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t0 = (g["lo"] - o) * inv
        t1 = (g["hi"] - o) * inv
    tmin = np.nan_to_num(np.minimum(t0, t1), nan=-np.inf)
    tmax = np.nan_to_num(np.maximum(t0, t1), nan=np.inf)
    near, far = tmin.max(axis=1), tmax.min(axis=1)
    t = np.where((near <= far) & (near > EPS), near, np.inf)
    axis = tmin.argmax(axis=1)
    normal = np.zeros_like(d)
    normal[np.arange(len(d)), axis] = -np.sign(d[np.arange(len(d)), axis])
    return t, normal


def hit_sphere(o, d, g):
    centre, r = g
    oc = o - centre
    b = np.einsum("ij,ij->i", oc, d)
    c = np.einsum("ij,ij->i", oc, oc) - r * r
    disc = b * b - c
    t = -b - np.sqrt(np.maximum(disc, 0.0))
    t = np.where((disc > 0) & (t > EPS), t, np.inf)
    p = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
    return t, (p - centre) / r


def hit_cylinder(o, d, g):
    """Vertical capped cylinder: axis through (x, z) = g['xz'], radius g['r'], y in g['y']."""
    (cx, cz), r, (y0, y1) = g["xz"], g["r"], g["y"]
    ox, oz = o[:, 0] - cx, o[:, 2] - cz
    a = d[:, 0] ** 2 + d[:, 2] ** 2
    b = ox * d[:, 0] + oz * d[:, 2]
    c = ox**2 + oz**2 - r * r
    disc = b * b - a * c
    with np.errstate(divide="ignore", invalid="ignore"):
        ts = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
    ys = o[:, 1] + ts * d[:, 1]
    t_side = np.where((disc > 0) & (a > 1e-12) & (ts > EPS) & (ys > y0) & (ys < y1), ts, np.inf)
    t_cap, cap_y = np.full(len(o), np.inf), np.zeros(len(o))
    for yc in (y0, y1):
        with np.errstate(divide="ignore", invalid="ignore"):
            tc = (yc - o[:, 1]) / d[:, 1]
        px, pz = ox + tc * d[:, 0], oz + tc * d[:, 2]
        ok = (tc > EPS) & (px**2 + pz**2 < r * r) & (tc < t_cap)
        t_cap = np.where(ok, tc, t_cap)
        cap_y = np.where(ok, -1.0 if yc == y0 else 1.0, cap_y)
    side = t_side <= t_cap
    t = np.where(side, t_side, t_cap)
    p = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
    n_side = np.stack([(p[:, 0] - cx) / r, np.zeros(len(o)), (p[:, 2] - cz) / r], axis=1)
    n_cap = np.stack([np.zeros(len(o)), cap_y, np.zeros(len(o))], axis=1)
    return t, np.where(side[:, None], n_side, n_cap)


HIT = {"box": hit_box, "sphere": hit_sphere, "cylinder": hit_cylinder}


def hit_room(o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exit distance (N,) of rays from inside the room box, and the surface id hit (N,).

    Surface ids: 0..3 walls x = X0, x = X1, z = Z0, z = Z1; 4 floor; 5 ceiling.
    """
    lo, hi = np.array([X0, Y_CEIL, Z0]), np.array([X1, Y_FLOOR, Z1])
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d > 0, (hi - o) / d, (lo - o) / d)
    t = np.where(np.abs(d) < 1e-12, np.inf, t)
    axis = t.argmin(axis=1)
    tt = t[np.arange(len(d)), axis]
    positive = d[np.arange(len(d)), axis] > 0
    surface = np.select([axis == 0, axis == 2, axis == 1], [np.where(positive, 1, 0), np.where(positive, 3, 2),
                                                            np.where(positive, 4, 5)])
    return tt, surface


def trace(o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linear radiance (N, 3) and hit distance (N,) of rays (origins o, unit directions d, world)."""
    t, surface = hit_room(o, d)
    obj = np.full(len(d), -1)
    normal = np.zeros_like(d)
    for k, (kind, g, _) in enumerate(OBJECTS):
        tk, nk = HIT[kind](o, d, g)
        closer = tk < t
        t = np.where(closer, tk, t)
        obj = np.where(closer, k, obj)
        normal = np.where(closer[:, None], nk, normal)
    p = o + t[:, None] * d
    albedo = np.zeros_like(d)
    room_normals = np.array([[1, 0, 0], [-1, 0, 0], [0, 0, 1], [0, 0, -1], [0, -1, 0], [0, 1, 0]], dtype=float)
    for s in range(6):
        m = (obj < 0) & (surface == s)
        if not m.any():
            continue
        normal[m] = room_normals[s]
        albedo[m] = wall_albedo(p[m], s) if s < 4 else floor_albedo(p[m]) if s == 4 else ceiling_albedo(p[m])
    for k, (_, _, fn) in enumerate(OBJECTS):
        m = obj == k
        if m.any():
            albedo[m] = fn(p[m], normal[m])
    return albedo * irradiance(p, normal)[:, None], t


def irradiance(p: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Ambient + Lambertian point-light irradiance (N,), with shadows cast by the objects."""
    e = np.full(len(p), AMBIENT)
    for pos, power in LIGHTS:
        to = pos - p
        dist = np.linalg.norm(to, axis=1)
        ldir = to / dist[:, None]
        cos = np.einsum("ij,ij->i", n, ldir)
        lit = cos > 0
        origin = p + 1e-4 * n
        for kind, g, _ in OBJECTS:
            tk, _ = HIT[kind](origin, ldir, g)
            lit &= ~(tk < dist)
        lobe = 0.25 + 0.75 * np.maximum(-ldir[:, 1], 0.0)  # -ldir: from the light to p; y is down
        e += np.where(lit, power * lobe * cos / (dist**2 + 0.25), 0.0)
    return e


def encode(linear: np.ndarray) -> np.ndarray:
    """Linear radiance -> 8-bit display values (gamma 2.2, clipped)."""
    return np.round(np.clip(linear, 0.0, 1.0) ** (1.0 / 2.2) * 255.0).astype(np.uint8)


def render(c2w: np.ndarray, frame_index: int, width: int = WIDTH, spp: int = SPP,
           rows: tuple[int, int] | None = None, chunk_rows: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """ERP image (h, W, 3) uint8 and pixel-centre range (h, W) float32 of rows [r0, r1) of a frame.

    ``rows`` defaults to the whole image; a band renders exactly the rows of the whole image
    (the jitter is drawn for the whole frame, then sliced).
    """
    height = width // 2
    r0, r1 = rows if rows is not None else (0, height)
    jit = jitter(frame_index, width, spp)
    rot, centre = c2w[:3, :3], c2w[:3, 3]
    image = np.zeros((r1 - r0, width, 3), dtype=np.uint8)
    depth = np.zeros((r1 - r0, width), dtype=np.float32)
    cols = np.arange(width, dtype=np.float64)
    for a in range(r0, r1, chunk_rows):
        b = min(a + chunk_rows, r1)
        rr = np.arange(a, b, dtype=np.float64)[:, None]
        acc = np.zeros((b - a, width, 3))
        for s in range(spp):
            dirs = (erp_directions(rr + jit[s, a:b, :, 1], cols[None, :] + jit[s, a:b, :, 0], width) @ rot.T).reshape(-1, 3)
            radiance, _ = trace(np.broadcast_to(centre, dirs.shape), dirs)
            acc += radiance.reshape(b - a, width, 3)
        image[a - r0:b - r0] = encode(acc / spp)
        dirs = (erp_directions(rr + 0.5 + 0 * cols[None, :], cols[None, :] + 0.5, width) @ rot.T).reshape(-1, 3)
        _, t = trace(np.broadcast_to(centre, dirs.shape), dirs)
        depth[a - r0:b - r0] = t.reshape(b - a, width)
    return image, depth


def scene_json() -> dict:
    frames = []
    for name, (centre, yaw) in CAMERAS.items():
        f = {"name": name, "image": f"images/{name}.png", "c2w": c2w_matrix(centre, yaw).round(6).tolist()}
        if name == "01":
            f["depth"] = "depth/01.npy"
        frames.append(f)
    return {"name": "room", "units": "metres", "convention": "opencv", "pose_accuracy": "exact",
            "source": "synthetic: scripts/make_sample.py (numpy ray caster), free to redistribute",
            "frames": frames, "splits": [{"references": ["00", "02"], "targets": ["01"]}]}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "samples" / "room")
    ap.add_argument("--width", type=int, default=WIDTH, help="ERP width (height = width / 2)")
    ap.add_argument("--spp", type=int, default=SPP, help="jittered rays per pixel")
    args = ap.parse_args(argv)
    for sub in ("images", "depth"):
        (args.out / sub).mkdir(parents=True, exist_ok=True)
    meta = scene_json()
    for i, f in enumerate(meta["frames"]):
        image, depth = render(np.array(f["c2w"]), i, args.width, args.spp)
        Image.fromarray(image).save(args.out / f["image"], optimize=True)
        if "depth" in f:
            np.save(args.out / f["depth"], depth)  # float32
        print(f"{f['name']}: {image.shape[1]}x{image.shape[0]}, range {depth.min():.3f}..{depth.max():.3f} m")
    (args.out / "scene.json").write_text(json.dumps(meta, indent=1) + "\n")


if __name__ == "__main__":
    main()
