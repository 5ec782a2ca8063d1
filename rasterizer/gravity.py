"""Gravity of a panorama: the down direction in its camera frame, and the turn that levels it (numpy only).

Frames: OpenCV camera frames (x right, y down, z forward; the ERP's centre looks along +z).
A levelled panorama has gravity along +y. ``level_rotation(down)`` is the levelled-from-camera
rotation ``L``: a camera-frame bearing ``f`` is ``L f`` in the levelled frame.

Sources of ``down``:

- the camera's own reading, GPano ``PosePitchDegrees`` (the image centre's elevation above the
  horizon) and ``PoseRollDegrees``: :func:`down_from_pitch_roll`;
- the vertical vanishing point of the image's line segments: every 3D vertical line lies in a
  plane through the camera that contains gravity, so the normal ``n`` of its great circle is
  perpendicular to ``down``. :func:`vertical_from_lines` finds the direction most line normals
  are perpendicular to (RANSAC on pairs, then robust least squares).
"""

from __future__ import annotations

import numpy as np

from .geometry import unit_vectors

_Y = np.array([0.0, 1.0, 0.0])


def down_from_pitch_roll(pitch_deg: float, roll_deg: float) -> np.ndarray:
    """Unit down direction (3,) in the camera frame of an ERP whose centre is pitched ``pitch_deg`` above
    the horizon and rolled ``roll_deg`` (GPano ``PosePitchDegrees`` / ``PoseRollDegrees``).

    The camera-from-level rotation is ``Rz(roll) Rx(pitch)``; ``down = (Rz Rx)^T e_y``. A positive pitch
    (centre above the horizon) puts gravity behind the centre (negative z); a positive roll puts it to the
    right (positive x).
    """
    p, r = np.radians(pitch_deg), np.radians(roll_deg)
    rx = np.array([[1, 0, 0], [0, np.cos(p), -np.sin(p)], [0, np.sin(p), np.cos(p)]])
    rz = np.array([[np.cos(r), -np.sin(r), 0], [np.sin(r), np.cos(r), 0], [0, 0, 1]])
    return (rz @ rx).T @ _Y


def tilt_deg(down: np.ndarray) -> float:
    """Angle (deg) between ``down`` (3,) and the camera's +y axis."""
    d = unit_vectors(np.asarray(down, dtype=np.float64), 1e-12)
    return float(np.degrees(np.arccos(np.clip(d[1], -1.0, 1.0))))


def level_rotation(down: np.ndarray) -> np.ndarray:
    """(3, 3) levelled-from-camera rotation ``L`` with ``L @ down = e_y``: the smallest turn (no yaw)."""
    d = unit_vectors(np.asarray(down, dtype=np.float64), 1e-12)
    axis = np.cross(d, _Y)
    s, c = np.linalg.norm(axis), float(d @ _Y)
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    k = axis / s
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * kx + (1 - c) * (kx @ kx)


def vertical_from_lines(normals: np.ndarray, weights: np.ndarray, *, prior: np.ndarray | None = None,
                        max_tilt_deg: float = 20.0, inlier_deg: float = 0.5, min_spread_deg: float = 60.0,
                        samples: int = 400, seed: int = 0) -> tuple[np.ndarray, dict]:
    """Down direction (3,) from great-circle normals ``normals`` (N, 3) of line segments weighted by
    ``weights`` (N,) (e.g. their lengths), within ``max_tilt_deg`` of ``prior`` (default +y).

    Candidates are the segments whose great circle passes within ``max_tilt_deg`` of ``prior``.
    RANSAC on pairs (``down = n_i x n_j``) maximises the weight of normals within ``inlier_deg`` of
    perpendicular; Cauchy-weighted least squares (smallest eigenvector of the weighted scatter of the
    inliers' normals) refines. ``info``: ``lines`` (candidates), ``inliers``, ``inlier_share`` (of
    the candidates' weight), ``spread_deg`` (azimuth range of the inlier normals: small means the
    vertical lines all lie in one direction and the tilt across it is weakly determined).
    Raises ``ValueError`` when fewer than 8 candidates or inliers are found, or when the inliers'
    spread is below ``min_spread_deg``.
    """
    prior = _Y if prior is None else unit_vectors(np.asarray(prior, dtype=np.float64), 1e-12)
    n = unit_vectors(np.asarray(normals, dtype=np.float64), 1e-12)
    w = np.asarray(weights, dtype=np.float64)
    cand = np.abs(n @ prior) < np.sin(np.radians(max_tilt_deg))
    n, w = n[cand], w[cand]
    if len(n) < 8:
        raise ValueError(f"only {len(n)} near-vertical line segments")
    rng = np.random.default_rng(seed)
    p = w / w.sum()
    ij = rng.choice(len(n), size=(samples, 2), p=p)
    g = np.cross(n[ij[:, 0]], n[ij[:, 1]])
    norm = np.linalg.norm(g, axis=-1)
    ok = norm > np.sin(np.radians(5.0))  # the two great circles cross at a well-defined point
    g = g[ok] / norm[ok, None]
    g *= np.sign(g @ prior)[:, None]
    g = g[g @ prior > np.cos(np.radians(max_tilt_deg))]
    if not len(g):
        raise ValueError("no pair of near-vertical line segments meets near the vertical")
    sin_thr = np.sin(np.radians(inlier_deg))
    score = (np.abs(n @ g.T) < sin_thr).T.astype(np.float64) @ w
    down = g[int(np.argmax(score))]
    for _ in range(8):
        r = np.abs(n @ down) / sin_thr
        cw = w / (1.0 + r * r) * (r < 3.0)
        scatter = (n * cw[:, None]).T @ n
        vec = np.linalg.eigh(scatter)[1][:, 0]
        down = vec * np.sign(vec @ prior)
    inl = np.abs(n @ down) < sin_thr
    if inl.sum() < 8:
        raise ValueError(f"only {int(inl.sum())} line segments meet at one vertical vanishing point")
    az = np.degrees(np.arctan2(n[inl, 0], n[inl, 2])) % 180.0  # a normal and its negative: one azimuth
    gaps = np.diff(np.r_[np.sort(az), np.sort(az)[0] + 180.0])
    spread = float(180.0 - gaps.max())
    if spread < min_spread_deg:
        raise ValueError(f"the vertical lines lie within {spread:.0f} deg of one direction: the tilt across it is unknown")
    return down, {"lines": int(len(n)), "inliers": int(inl.sum()), "inlier_share": float(w[inl].sum() / w.sum()),
                  "spread_deg": spread}


def line_support(normals: np.ndarray, weights: np.ndarray, down: np.ndarray, *, agree_deg: float,
                 max_tilt_deg: float = 20.0) -> tuple[int, float]:
    """How many of the near-vertical segments (great circle within ``max_tilt_deg`` of +y) pass within
    ``agree_deg`` of ``down`` (3,), and their share of those segments' weight: (count, share)."""
    n = unit_vectors(np.asarray(normals, dtype=np.float64), 1e-12)
    w = np.asarray(weights, dtype=np.float64)
    cand = np.abs(n[:, 1]) < np.sin(np.radians(max_tilt_deg))
    agree = cand & (np.abs(n @ unit_vectors(np.asarray(down, dtype=np.float64), 1e-12)) < np.sin(np.radians(agree_deg)))
    total = w[cand].sum()
    return int(agree.sum()), float(w[agree].sum() / total) if total > 0 else 0.0
