"""Procedural panorama pairs for the stability bench: an analytic numpy ray caster.

A :class:`SyntheticScene` is a box room (seen from inside) with a few spheres,
painted with a smooth world-space texture, so every camera sees a consistent
ERP image and exact range. Geometry lives in a canonical "scene frame" in
metres (OpenCV-like: +y down). Global similarity transforms (rotation, scale)
are applied to poses only: the images do not change, which is what the
equivariance and scale cases rely on.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from rasterizer.geometry import grid_directions

Texture = Literal["full", "poles", "seam", "flat"]

#: Random but fixed sinusoid directions/frequencies of the texture (cycles per metre): coarse
#: enough (0.5 m checker, <= 1.5 cycles/m) to be matched at 64x128 input.
_RNG = np.random.default_rng(1234)
_WAVES = _RNG.normal(size=(3, 6, 3))
_WAVES /= np.linalg.norm(_WAVES, axis=-1, keepdims=True)
_WAVES *= _RNG.uniform(0.3, 1.5, size=(3, 6, 1))
_PHASES = _RNG.uniform(0, 2 * np.pi, size=(3, 6))


@dataclass(frozen=True)
class SyntheticScene:
    """A textured box room with spheres; ``texture`` picks where the pattern is painted."""

    room_lo: tuple[float, float, float] = (-2.5, -1.4, -3.0)
    room_hi: tuple[float, float, float] = (2.2, 1.3, 3.5)
    spheres: tuple[tuple[float, float, float, float], ...] = (
        (0.9, 0.5, 1.6, 0.45), (-1.2, 0.2, -1.5, 0.6), (1.5, -0.5, -2.0, 0.35), (-1.4, 0.6, 1.8, 0.4),
    )
    texture: Texture = "full"
    flat_colour: tuple[float, float, float] = (0.5, 0.5, 0.5)
    extra: dict = field(default_factory=dict, compare=False)

    def with_(self, **changes) -> "SyntheticScene":
        return replace(self, **changes)

    # -- ray casting ----------------------------------------------------------
    def cast(self, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Hit range (N,), hit points (N, 3) and primitive id (N,; 0 = room, k = sphere k) of rays."""
        o = np.asarray(origin, dtype=np.float64)
        d = np.asarray(dirs, dtype=np.float64)
        lo, hi = np.asarray(self.room_lo), np.asarray(self.room_hi)
        if np.any(o <= lo) or np.any(o >= hi):
            raise ValueError(f"camera centre {o.tolist()} is outside the room {lo.tolist()}..{hi.tolist()}")
        with np.errstate(divide="ignore", invalid="ignore"):
            t_axis = np.where(d > 0, (hi - o) / d, np.where(d < 0, (lo - o) / d, np.inf))
        t = t_axis.min(axis=-1)
        prim = np.zeros(t.shape, dtype=np.int64)
        for k, (cx, cy, cz, r) in enumerate(self.spheres, start=1):
            oc = o - np.array([cx, cy, cz])
            b = d @ oc
            disc = b * b - (oc @ oc - r * r)
            root = np.sqrt(np.maximum(disc, 0.0))
            t_near = -b - root
            t_far = -b + root
            t_hit = np.where(t_near > 1e-9, t_near, t_far)
            hit = (disc > 0) & (t_hit > 1e-9) & (t_hit < t)
            t = np.where(hit, t_hit, t)
            prim = np.where(hit, k, prim)
        return t, o + t[:, None] * d, prim

    def shade(self, points: np.ndarray, prim: np.ndarray) -> np.ndarray:
        """Colour (N, 3) in [0, 1] of surface points by texture mode."""
        p = np.asarray(points, dtype=np.float64)
        phase = np.einsum("nk,cwk->ncw", p, _WAVES) * 2 * np.pi + _PHASES
        smooth = np.sin(phase).mean(axis=-1)  # (N, 3) in about [-0.6, 0.6]
        checker = (np.floor((p + 0.137) / 0.5).sum(axis=-1) % 2)[:, None]  # offset: no cell edge on a wall
        base = 0.35 + 0.3 * checker + 0.45 * smooth
        base = base + 0.08 * (prim[:, None] % 3 == np.arange(3))  # tint per primitive
        colour = np.clip(base, 0.02, 0.98)
        flat = np.broadcast_to(np.asarray(self.flat_colour, dtype=np.float64), colour.shape)
        if self.texture == "full":
            return colour
        if self.texture == "flat":
            return flat.copy()
        lo, hi = np.asarray(self.room_lo), np.asarray(self.room_hi)
        if self.texture == "poles":
            horiz = np.hypot(p[:, 0], p[:, 2])
            on_cap = (np.isclose(p[:, 1], lo[1]) | np.isclose(p[:, 1], hi[1])) & (horiz < 0.8)
            return np.where(on_cap[:, None], colour, flat)
        if self.texture == "seam":
            on_back = np.isclose(p[:, 2], lo[2]) & (np.abs(p[:, 0]) < 1.2)
            return np.where(on_back[:, None], colour, flat)
        raise ValueError(f"unknown texture {self.texture!r}; expected full, poles, seam or flat")

    def render(self, c2w: np.ndarray, height: int, width: int, *, supersample: int = 2) -> tuple[np.ndarray, np.ndarray]:
        """ERP colour (H, W, 3) float32 in [0, 1] and range (H, W) float32 of a scene-frame camera.

        Colour is box-filtered over ``supersample``^2 rays per pixel (no aliasing
        of the texture); range is the centre ray's.
        """
        c2w = np.asarray(c2w, dtype=np.float64)
        s = int(supersample)
        dirs = grid_directions("erp", height * s, width * s).reshape(-1, 3) @ c2w[:3, :3].T
        t, pts, prim = self.cast(c2w[:3, 3], dirs)
        rgb = self.shade(pts, prim).reshape(height, s, width, s, 3).mean(axis=(1, 3))
        centre = grid_directions("erp", height, width).reshape(-1, 3) @ c2w[:3, :3].T
        rng, _, _ = self.cast(c2w[:3, 3], centre)
        return rgb.astype(np.float32), rng.reshape(height, width).astype(np.float32)


def camera(position, rotation: np.ndarray | None = None) -> np.ndarray:
    """4x4 c2w at ``position`` with ``rotation`` (identity by default)."""
    c2w = np.eye(4)
    if rotation is not None:
        c2w[:3, :3] = rotation
    c2w[:3, 3] = position
    return c2w


def similarity(c2w: np.ndarray, rotation: np.ndarray | None = None, scale: float = 1.0) -> np.ndarray:
    """Pose after the global similarity x -> scale * rotation @ x (images are unchanged by it)."""
    g = np.eye(4)
    if rotation is not None:
        g[:3, :3] = rotation
    out = g @ np.asarray(c2w, dtype=np.float64)
    out[:3, 3] *= scale
    return out


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random proper rotation matrix."""
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])
