"""Poses from the two panoramas: gravity -> SIFT matches -> upright relative pose (5-dof when a tilt
remains) -> metric scale.

Gravity: each panorama's down direction from its vertical lines or the camera's own reading
(:mod:`service.gravity`); a panorama tilted more than :data:`LEVEL_MIN_TILT_DEG` is levelled (its
bearings turned so that gravity is +y) before matching.

Features: SIFT (OpenCV, ``contrastThreshold=0.02``) on 16 perspective crops per ERP
(8 on the horizon, 4 at +50 and 4 at -50 deg pitch, each sized to the directions it keeps:
:data:`CROPS`), RootSIFT, each keypoint kept only by the crop whose axis is nearest (no
duplicates), the tripod cap below -65 deg latitude dropped. Matching: ratio 0.8 + mutual check
(0.9 when that leaves too few for a pose: :data:`SEED_RATIOS`), then upright 3-point RANSAC
(:mod:`rasterizer.relative_pose`), then matching guided by the pose (within 3 then 1.5 deg of
the epipolar plane, in front of both cameras) and robust refinement. When a second pose mode (e.g. a
180-deg flip) keeps half the inliers, :func:`service.photometric.photometric_scores` of both decides, or the answer is 422.

After the upright pose, a 5-dof refinement (full rotation and travel direction) replaces it when
the levelled pair still differs by more than :data:`RESIDUAL_TILT_DEG` of tilt.

World frame of an estimate: A's levelled frame (origin at A, OpenCV axes, +y along gravity;
``c2w_A`` is A's levelling turn, the identity for a level A). Scale: ``baseline``
(metres), else ``camera_height`` (metres above the floor: the lowest horizontal plane both images agree
on in a dense plane sweep, :func:`rasterizer.floor_sweep.floor_ratio`; else the lowest wide plane of
triangulated points, :func:`rasterizer.relative_pose.floor_scale`; 422 ``scale_failed`` when neither
finds one), else a baseline of 1. Failures raise :class:`PoseEstimationFailed` (422); one panorama flipped
as a whole against the other (mirrored, upside down) is refused as such (:mod:`service.pose_flips`).
"""

from __future__ import annotations

import copy
import hashlib
import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from rasterizer.floor_sweep import FloorHidden, floor_ratio
from rasterizer.geometry import lat_lon_from_direction, rigid_inverse
from rasterizer.gravity import level_rotation
from rasterizer.lru import LRUCache
from rasterizer.relative_pose import (
    INLIER_DEG,
    epipolar_error,
    floor_scale,
    refine_general,
    refine_upright,
    rotation_only_fraction,
    tilt_between,
    triangulate,
    upright_ransac,
    yaw_rotation,
)
from rasterizer.threads import map_threads

from .errors import BadInput
from .gravity import MAX_TILT_DEG, crop_rotations, crop_size, panorama_gravity, perspective_crops
from .images import check_not_blank, same_picture
from .matching import Distances, guided_matches, mutual_matches, putative_matches
from .photometric import gray_erp, photometric_scores, small_gray
from .pose_flips import FLIP_CHECK_SHARE, flipped

#: Options keys this module reads (not encoder options).
POSE_OPTION_KEYS = ("camera_height", "baseline", "refine_poses")

#: SIFT crops' focal length in pixels: 4.7 px per degree at a crop's centre, a little under the 2048-wide
#: grey ERP's 5.7, so a crop hardly magnifies it.
CROP_FOCAL = 268.5
#: A crop spans the directions nearest its axis (the only keypoints it keeps) and this much around them (deg):
#: about the descriptor window of a keypoint at SIFT's finer scales, so keypoints at the edge of a crop's
#: share keep theirs whole.
CROP_MARGIN_DEG = 5.0
#: SIFT keeps a crop's strongest keypoints, at most one per this many of its pixels.
CROP_PIXELS_PER_KEYPOINT = 360
TRIPOD_LAT_DEG = -65.0
MIN_INLIERS = 20
#: Fewer putative matches than this agreeing with the RANSAC pose: the views share too little.
MIN_RANSAC_INLIERS = 12
#: Lowe ratios of the putative matches that seed RANSAC, tried in turn while the matches are too few for a pose
#: (fewer than MIN_INLIERS, or fewer than MIN_RANSAC_INLIERS agreeing). Wide baselines (a tripod moved 3 m)
#: change the descriptors: 0.9, the guided matching's ratio, then keeps about three times as many. Panoramas of
#: different rooms still leave 5-8 agreeing of 80-230 (the dev scenes' 27 cross-scene pairs).
SEED_RATIOS = (0.8, 0.9)
#: A seed pose whose travel is steeper than this (deg from the horizontal plane of the levelled pair) is no
#: pose: two captures of a room are taken at about the same height (a staircase rises at under 45 deg), while a
#: vertical baseline fits any pair of mirror-symmetric patterns (its epipolar planes are the meridians).
MAX_TRAVEL_ELEVATION_DEG = 60.0
#: Rival pose with at least this share of the winner's inliers -> ambiguous.
RIVAL_SHARE = 0.8
#: Photometric scores this many times apart decide between two pose modes.
PHOTOMETRIC_MARGIN = 1.15
#: When they do not, floor shares (:func:`rasterizer.floor_sweep.floor_ratio`) this many times apart do: under the
#: true pose a horizontal plane (the floor) lines the two views up, under a wrong mode little does. Of the 18
#: dev pairs whose rival mode is refined, the true pose always held the larger share, 1.2-18x the rival's.
FLOOR_MARGIN = 1.5
#: At least this share of matches explained by a rotation alone -> no parallax.
NO_PARALLAX_SHARE = 0.8
#: A panorama is levelled when its gravity is further than this (deg) from its y axis. Line vanishing points
#: of level captures (a tripod, a synthetic render) measure 0.2-0.8 deg; smaller tilts are left to the
#: 5-dof refinement.
LEVEL_MIN_TILT_DEG = 1.0
#: Rows of the grey ERPs of the dense floor sweep (:func:`rasterizer.floor_sweep.floor_ratio`).
FLOOR_SWEEP_HEIGHT = 192
#: The 5-dof refinement of the (levelled) pair is kept when it finds more tilt than this (deg) between them.
RESIDUAL_TILT_DEG = 0.5


class PoseEstimationFailed(BadInput):
    code = "pose_estimation_failed"


@dataclass(frozen=True)
class PoseOptions:
    camera_height: float | None = None
    baseline: float | None = None
    refine_poses: bool = False

    @classmethod
    def pop_from(cls, options: dict[str, Any]) -> "PoseOptions":
        """Take the pose keys out of ``options`` (mutates it); raises ``BadInput`` on a bad value."""
        out = {}
        for key in ("camera_height", "baseline"):
            v = options.pop(key, None)
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v < 1e4):
                raise BadInput(f"options.{key}: expected a positive number of metres", code="invalid_options")
            out[key] = None if v is None else float(v)
        refine = options.pop("refine_poses", False)
        if not isinstance(refine, bool):
            raise BadInput("options.refine_poses: expected true or false", code="invalid_options")
        if out["camera_height"] is not None and out["baseline"] is not None:
            raise BadInput("options: give camera_height or baseline, not both", code="invalid_options")
        return cls(out["camera_height"], out["baseline"], refine)


def _crop_size(half_x_deg: float, half_y_deg: float) -> tuple[int, int]:
    """(width, height) in pixels of a crop reaching ``half_*_deg`` + :data:`CROP_MARGIN_DEG` from its axis."""
    return crop_size(CROP_FOCAL, half_x_deg + CROP_MARGIN_DEG, half_y_deg + CROP_MARGIN_DEG)


#: SIFT crops as (pitch, yaws, (width, height)) in degrees and pixels: 8 on the horizon, 4 at +50 and 4 at -50
#: deg pitch. A crop keeps only the keypoints nearer its axis than any other's (above :data:`TRIPOD_LAT_DEG`),
#: so each ring's size reaches the farthest such direction along the crop's x and y (the degrees below; a test
#: measures them) and the margin beyond: a third of the pixels of 100-deg square crops, for as many keypoints.
CROPS = ((0.0, tuple(45.0 * k for k in range(8)), _crop_size(22.5, 33.4)),
         (50.0, tuple(22.5 + 90.0 * k for k in range(4)), _crop_size(37.3, 29.6)),
         (-50.0, tuple(67.5 + 90.0 * k for k in range(4)), _crop_size(37.3, 39.8)))
CROP_ROTATIONS = crop_rotations(CROPS)


def features(erp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit bearings (N, 3) in the panorama's camera frame and RootSIFT descriptors (N, 128) float32 of an
    ERP (RGB, or the grey of :func:`~service.photometric.gray_erp`)."""
    import cv2

    gray = gray_erp(erp)
    sizes = [size for _, yaws, size in CROPS for _ in yaws]
    axes = CROP_ROTATIONS[:, :, 2]
    bearings, descs = [], []
    for k, crop in enumerate(perspective_crops(gray, CROPS, CROP_FOCAL)):
        rot, (w, h) = CROP_ROTATIONS[k], sizes[k]
        sift = cv2.SIFT_create(nfeatures=round(w * h / CROP_PIXELS_PER_KEYPOINT), contrastThreshold=0.02)
        kps, desc = sift.detectAndCompute(crop, None)
        if desc is None or not len(kps):
            continue
        pts = np.array([kp.pt for kp in kps])
        d = np.stack([(pts[:, 0] - (w - 1) / 2) / CROP_FOCAL, (pts[:, 1] - (h - 1) / 2) / CROP_FOCAL, np.ones(len(pts))], -1)
        d = (d / np.linalg.norm(d, axis=-1, keepdims=True)) @ rot.T
        own = np.argmax(d @ axes.T, axis=1) == k
        own &= lat_lon_from_direction(d)[0] > np.radians(TRIPOD_LAT_DEG)
        desc = desc[own] / np.maximum(desc[own].sum(1, keepdims=True), 1e-7)
        bearings.append(d[own])
        descs.append(np.sqrt(desc).astype(np.float32))
    if not bearings:
        return np.zeros((0, 3)), np.zeros((0, 128), np.float32)
    return np.concatenate(bearings), np.concatenate(descs)


def _guided_refine(fa, fb, dist: Distances, yaw, t, R0=None):
    """Two rounds of guided matching + refinement; returns (yaw, t, inlier pairs, residuals deg)."""
    R0 = np.eye(3) if R0 is None else R0
    pairs = np.zeros((0, 2), int)
    for max_deg in (3.0, 1.5):
        R = R0 @ yaw_rotation(yaw)
        pairs = guided_matches(fa, fb, dist, R, t, max_deg=max_deg)
        if len(pairs) >= 5:
            yaw, t = refine_upright(fa[pairs[:, 0]], fb[pairs[:, 1]], yaw, t, R0=R0)
    R = R0 @ yaw_rotation(yaw)
    err = np.degrees(epipolar_error(fa[pairs[:, 0]], fb[pairs[:, 1]], R, t)) if len(pairs) else np.zeros(0)
    inl = err < INLIER_DEG
    return yaw, t, pairs[inl], err[inl]


def _support(pairs: np.ndarray, err_deg: np.ndarray, method: str) -> dict[str, Any]:
    return {"method": method, "inliers": int(len(pairs)),
            "residual_deg": {"median": float(np.median(err_deg)) if len(err_deg) else None,
                             "p90": float(np.percentile(err_deg, 90)) if len(err_deg) else None}}


def _pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = R, t
    return m


@dataclass(frozen=True)
class Panorama:
    """One panorama ready for matching: its grey ERP (uint8, at most :data:`service.photometric.MAX_ERP_WIDTH` wide, what the
    feature, line, floor and photometric steps read), its bearings (N, 3) and RootSIFT descriptors (N, 128)
    in its levelled frame, its levelled-from-camera rotation ``level`` (3, 3) and the gravity ``info``."""

    gray: np.ndarray
    bearings: np.ndarray
    descriptors: np.ndarray
    level: np.ndarray
    gravity: dict


#: Panoramas through :func:`prepare` kept by content for later estimates (least recently used out first): a
#: client that posts a picture again, the same pair with other options or the next pair of a walk through a
#: house, skips its features and lines (1-3.4 MB each on the dev panoramas).
PREPARED_CACHE_SIZE = 4
_prepared: LRUCache[bytes, Panorama] = LRUCache(lambda: PREPARED_CACHE_SIZE)  # the bound is read at each insert


def _content_key(gray: np.ndarray, data: bytes | None) -> bytes:
    """Digest of what :func:`prepare` reads: the grey ERP (size and pixels) and the file's bytes (its XMP)."""
    h = hashlib.blake2b(digest_size=20)
    h.update(repr(gray.shape).encode())
    h.update(np.ascontiguousarray(gray).data)
    h.update(b"-" if data is None else hashlib.blake2b(data, digest_size=20).digest())
    return h.digest()


def _readonly(pano: Panorama) -> Panorama:
    for a in (pano.gray, pano.bearings, pano.descriptors, pano.level):
        a.flags.writeable = False
    return pano


def prepare(erp: np.ndarray, data: bytes | None = None) -> Panorama:
    """Features and gravity of one panorama (``data``: the file's bytes, for the camera's own tilt reading).

    The panorama is levelled only when its tilt exceeds :data:`LEVEL_MIN_TILT_DEG`; ``gravity["applied"]``
    says whether it was. The result is kept (:data:`PREPARED_CACHE_SIZE`, arrays read-only) and returned
    again for the same grey pixels and file bytes, with its own copy of the gravity dict."""
    gray = gray_erp(erp)
    key = _content_key(gray, data)
    hit = _prepared.get(key)
    if hit is None:
        if np.may_share_memory(gray, erp):  # a grey ERP comes back as it is: keep a copy, not the caller's array
            gray = gray.copy()
        f, d = features(gray)
        down, ginfo = panorama_gravity(gray, data)
        applied = ginfo["tilt_deg"] > LEVEL_MIN_TILT_DEG
        level = level_rotation(down) if applied else np.eye(3)
        hit = _readonly(Panorama(gray, f @ level.T, d, level,
                                 {**ginfo, "down": [float(v) for v in down], "applied": bool(applied)}))
        _prepared.put(key, hit)
    return replace(hit, gravity=copy.deepcopy(hit.gravity))


def clear_prepared_cache() -> None:
    """Forget every kept :func:`prepare` result (benchmarks that time the features)."""
    _prepared.clear()


def _guided_refine_general(fa, fb, dist: Distances, R, t):
    """Guided matching + 5-dof refinement in two rounds; returns (R, t, inlier pairs, residuals deg)."""
    pairs = np.zeros((0, 2), int)
    for max_deg in (3.0, 1.5):
        pairs = guided_matches(fa, fb, dist, R, t, max_deg=max_deg)
        if len(pairs) >= 5:
            R, t = refine_general(fa[pairs[:, 0]], fb[pairs[:, 1]], R, t)
    err = np.degrees(epipolar_error(fa[pairs[:, 0]], fb[pairs[:, 1]], R, t)) if len(pairs) else np.zeros(0)
    inl = err < INLIER_DEG
    return R, t, pairs[inl], err[inl]


class _FlipVerdict:
    """Whether B matches A far better flipped (:func:`service.pose_flips.flipped`'s message, or None), found at most
    once per estimate: a weak seed asks, and so may a refusal after it. B's putative matches as sent are the seed's
    at the first ratio (``plain``, set by the estimate once it has them), not matched again."""

    def __init__(self, pa: Panorama, pb: Panorama):
        self.pa, self.pb = pa, pb
        self.plain: np.ndarray | None = None
        self._found: tuple[str | None] | None = None

    def __call__(self) -> str | None:
        if self._found is None:
            pa, pb = self.pa, self.pb
            self._found = (flipped(pa.bearings, pa.descriptors, pb.bearings, pb.descriptors, MIN_INLIERS,
                                   MIN_RANSAC_INLIERS, plain=self.plain,
                                   match=lambda d: mutual_matches(Distances(pa.descriptors, d), SEED_RATIOS[0])),)
        return self._found[0]


def _refusal(flip: _FlipVerdict, message: str, code: str = PoseEstimationFailed.code) -> PoseEstimationFailed:
    """The refusal to raise: a ``flipped_panorama`` one when B matches A far better flipped (``flip()``), else
    ``message``."""
    found = flip()
    return PoseEstimationFailed(found or message, code="flipped_panorama" if found else code)


def _tilted_beyond_search(pa: Panorama, pb: Panorama) -> str:
    """A refusal's message naming the panoramas whose lines meet beyond the tilts searched
    (:func:`service.gravity.panorama_gravity`'s ``beyond_search_deg``), or "" when none does. Such a panorama is
    levelled wrong or not at all, and a pose from it can be many degrees off (docs/design.md, "A tilt beyond the
    search is refused, not levelled")."""
    tilted = [(name, p.gravity.get("lines", {}).get("beyond_search_deg")) for name, p in (("image_a", pa), ("image_b", pb))]
    tilted = [(name, deg) for name, deg in tilted if deg is not None]
    if not tilted:
        return ""
    names, degs = " and ".join(n for n, _ in tilted), " and ".join(f"{d:.0f}" for _, d in tilted)
    one = len(tilted) == 1
    return (f"poses: {names} {'seems' if one else 'seem'} tilted by {degs} deg, beyond the {MAX_TILT_DEG:.0f} deg "
            f"searched ({'its' if one else 'their'} vertical lines meet there): level {'it' if one else 'them'} "
            "(hold the camera upright, or turn the panorama upright) or give poses")


def _floor_share(pa: Panorama, pb: Panorama, yaw: float, t: np.ndarray) -> float:
    """Share of the band below the cameras that lines up through the floor plane of the dense sweep under the
    upright pose (``yaw``, unit ``t``) in A's levelled frame; 0 when the sweep finds no floor. A share compares
    two poses, not a scale: the floor need not be seen near the cameras (``near_deg=None``), and windows that
    match with no parallax vote as well (docs/design.md, "A window that matches with no parallax does not vote")."""
    try:
        return float(floor_ratio(small_gray(pa.gray, FLOOR_SWEEP_HEIGHT), small_gray(pb.gray, FLOOR_SWEEP_HEIGHT),
                                 pa.level, pb.level, yaw_rotation(yaw), t, near_deg=None,
                                 parallax_free_votes=True)[1]["floor_share"])
    except ValueError:
        return 0.0


def _mode_choice(photometric: tuple[float, float], inliers: tuple[int, int], floor_shares) -> tuple[bool, bool]:
    """(the rival mode wins, the choice is decisive) between RANSAC's best pose mode and its rival.

    ``photometric``, ``inliers``: (best, rival) :func:`~service.photometric.photometric_scores` and guided inlier counts;
    ``floor_shares()``: (best, rival) :func:`_floor_share`, asked for only when the photometric scores are
    within :data:`PHOTOMETRIC_MARGIN`. Scores this far apart decide, else floor shares :data:`FLOOR_MARGIN`
    apart, else the inlier counts pick without deciding (the caller refuses a close rival).
    """
    best, rival = photometric
    if max(best, rival) >= PHOTOMETRIC_MARGIN * min(best, rival):
        return rival > best, True
    best_floor, rival_floor = floor_shares()
    if max(best_floor, rival_floor) > FLOOR_MARGIN * min(best_floor, rival_floor):
        return rival_floor > best_floor, True
    return inliers[1] > inliers[0], False


def estimate_poses(erp_a: np.ndarray, erp_b: np.ndarray, opts: PoseOptions, data: tuple = (None, None), *,
                   prepared: tuple[Panorama, Panorama] | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """(c2w_a, c2w_b, support info) from the images alone; raises :class:`PoseEstimationFailed`.

    The world is A's levelled frame (origin at A, +y along gravity as :func:`prepare` found it).
    ``data``: the two files' bytes when known (for the cameras' own tilt readings); ``prepared``:
    both panoramas already through :func:`prepare` (the images are then not read again)."""
    t0 = time.perf_counter()
    pa, pb = prepared if prepared is not None else map_threads(prepare, (erp_a, erp_b), data)
    fa, fb = pa.bearings, pb.bearings
    dist = Distances(pa.descriptors, pb.descriptors)  # every matching below reads it
    t_feat = time.perf_counter() - t0
    info: dict[str, Any] = {"features": [int(len(fa)), int(len(fb))], "gravity": [pa.gravity, pb.gravity]}
    if tilted := _tilted_beyond_search(pa, pb):
        raise PoseEstimationFailed(tilted)
    flip = _FlipVerdict(pa, pb)
    for k, ratio in enumerate(SEED_RATIOS):
        last = k == len(SEED_RATIOS) - 1
        pairs = putative_matches(dist, ratio)
        if ratio == SEED_RATIOS[0]:
            flip.plain = pairs
        info.update(putative_matches=int(len(pairs)), seed_ratio=ratio)
        if len(pairs) < MIN_INLIERS:
            if last:
                raise _refusal(flip, f"poses: only {len(pairs)} feature matches between the images "
                                       f"(need {MIN_INLIERS}); give poses, or images that overlap more")
            continue
        ma, mb = fa[pairs[:, 0]], fb[pairs[:, 1]]
        static = rotation_only_fraction(ma, mb)
        info["rotation_only_share"] = static
        if static >= NO_PARALLAX_SHARE:
            raise PoseEstimationFailed(f"poses: {static:.0%} of the matches move by a rotation alone: the two panoramas "
                                       "were taken from (nearly) the same point, which carries no depth",
                                       code="no_parallax")
        try:
            ransac = upright_ransac(ma, mb)
        except ValueError as exc:  # degenerate matches: no hypothesis
            raise _refusal(flip, f"poses: no relative pose fits the matches ({exc}); give poses") from None
        elevation = float(np.degrees(np.arcsin(np.clip(abs(ransac.best.t[1]), 0.0, 1.0))))
        if ransac.best.num_inliers >= MIN_RANSAC_INLIERS and elevation <= MAX_TRAVEL_ELEVATION_DEG:
            break
        if last and ransac.best.num_inliers < MIN_RANSAC_INLIERS:
            raise _refusal(flip, f"poses: only {ransac.best.num_inliers} of {len(pairs)} feature matches agree on "
                                   f"a relative pose (need {MIN_RANSAC_INLIERS}): the views share too little; give poses")
        if last:
            raise _refusal(flip, f"poses: the matches fit only a travel {elevation:.0f} deg from horizontal "
                                   f"(at most {MAX_TRAVEL_ELEVATION_DEG:.0f}): not two captures of one room at "
                                   "about the same height; give poses")
    if k > 0 or ransac.best.num_inliers < FLIP_CHECK_SHARE * len(pairs):  # a weak seed: is B flipped?
        if (refusal := _refusal(flip, "")).code == "flipped_panorama":
            raise refusal
    yaw, t, inl, err = _guided_refine(fa, fb, dist, ransac.best.yaw, ransac.best.t)
    method = "sift16-rootsift+levelled+upright3pt-ransac+guided"
    info.update(_support(inl, err, method))
    info["ransac_inliers"] = ransac.best.num_inliers

    def camera_pose(yaw_, t_):  # a levelled-frame pose as B in A's camera frame, as photometric_scores reads it
        return pa.level.T @ yaw_rotation(yaw_) @ pb.level, pa.level.T @ t_

    if ransac.rival is not None and ransac.rival.num_inliers >= 0.5 * ransac.best.num_inliers:
        ryaw, rt, rinl, rerr = _guided_refine(fa, fb, dist, ransac.rival.yaw, ransac.rival.t)
        rival = {"inliers": int(len(rinl)), "yaw_deg": float(np.degrees(ryaw)),
                 "yaw_gap_deg": float(np.degrees(abs(np.angle(np.exp(1j * (ryaw - yaw)))))),
                 "t_gap_deg": float(np.degrees(np.arccos(np.clip(rt @ t, -1, 1))))}
        if rival["yaw_gap_deg"] > 15 or rival["t_gap_deg"] > 25:
            best_score, rival_score = photometric_scores(pa.gray, pb.gray, [camera_pose(yaw, t), camera_pose(ryaw, rt)])
            rival["photometric"], info["photometric"] = rival_score, best_score
            info["rival"] = rival
            floors: list[float] = []  # (best, rival), when the floor was asked

            def floor_shares():
                floors[:] = map_threads(lambda y, tt: _floor_share(pa, pb, y, tt), (yaw, ryaw), (t, rt))
                return floors

            rival_wins, decisive = _mode_choice((best_score, rival_score), (len(inl), len(rinl)), floor_shares)
            best_floor, rival_floor = floors if floors else (None, None)
            if rival_wins:
                rival.update(inliers=int(len(inl)), photometric=best_score, yaw_deg=float(np.degrees(yaw)))
                yaw, t, inl, err, best_score, rival_score = ryaw, rt, rinl, rerr, rival_score, best_score
                best_floor, rival_floor = rival_floor, best_floor
                info.update(_support(inl, err, method))
                info["photometric"] = best_score
            if best_floor is not None:
                rival["floor_share"], info["floor_share"] = rival_floor, best_floor
            if not decisive and rival["inliers"] >= RIVAL_SHARE * len(inl):
                raise _refusal(
                    flip, f"poses: ambiguous - two relative poses {rival['yaw_gap_deg']:.0f} deg apart in yaw "
                    f"({rival['t_gap_deg']:.0f} deg in travel direction) fit the matches about equally well "
                    f"({len(inl)} vs {rival['inliers']} inliers) and the images agree about as well under both "
                    f"(photometric {max(best_score, rival_score):.2f} vs {min(best_score, rival_score):.2f}; the "
                    f"floor lines up on {info['floor_share']:.1%} vs {rival['floor_share']:.1%} of the pixels), as "
                    "in a symmetric room or when the views share little; give poses", "ambiguous_pose")
    R = yaw_rotation(yaw)
    R5, t5, inl5, err5 = _guided_refine_general(fa, fb, dist, R, t)
    info["residual_tilt_deg"] = tilt_between(R5)
    if info["residual_tilt_deg"] > RESIDUAL_TILT_DEG and len(inl5) >= MIN_INLIERS:
        R, t, inl, err = R5, t5, inl5, err5
        info.update(_support(inl, err, method + "+5dof"))
    info["timings"] = {"features": t_feat, "total": time.perf_counter() - t0}
    if len(inl) < MIN_INLIERS:
        raise _refusal(flip, f"poses: only {len(inl)} matches agree on a relative pose (need {MIN_INLIERS}); give poses")
    scale, info["scale"] = _scale(pa, pb, inl, R, t, opts)
    info["yaw_deg"] = float(np.degrees(np.arctan2(R[0, 2], R[2, 2])))
    c2w_a = np.eye(4)
    c2w_a[:3, :3] = pa.level
    return c2w_a, _pose(R @ pb.level, t * scale), info


def _scale(pa: Panorama, pb: Panorama, inl: np.ndarray, R: np.ndarray, t: np.ndarray, opts: PoseOptions) -> tuple[float, dict]:
    """Metres per unit of the unit-baseline pose: the given baseline; else the camera height over the floor's
    distance below A: from the dense floor sweep, else from the triangulated inliers ``inl`` (M, 2)
    (:func:`rasterizer.relative_pose.floor_scale`); else 1. When the sweep finds the floor hidden near the
    cameras (:class:`rasterizer.floor_sweep.FloorHidden`) the points cannot see it either: 422 ``scale_failed``."""
    if opts.baseline is not None:
        return opts.baseline, {"source": "baseline", "baseline_m": opts.baseline}
    if opts.camera_height is None:
        return 1.0, {"source": "default", "baseline_m": 1.0,
                     "note": "no camera_height or baseline given: the scene's scale is arbitrary (baseline 1)"}
    t0 = time.perf_counter()
    try:
        d, extra = floor_ratio(small_gray(pa.gray, FLOOR_SWEEP_HEIGHT), small_gray(pb.gray, FLOOR_SWEEP_HEIGHT),
                               pa.level, pb.level, R, t)
        s, floor = opts.camera_height / d, "dense"
    except FloorHidden as exc:
        raise PoseEstimationFailed(f"poses: camera_height given but {exc}; give baseline (the distance between the "
                                   "two cameras, metres) or poses instead", code="scale_failed") from None
    except ValueError as dense_exc:
        fa, fb = pa.bearings[inl[:, 0]], pb.bearings[inl[:, 1]]
        la, _ = triangulate(fa, fb, R, t)
        parallax = np.arccos(np.clip(np.sum(fa * (fb @ R.T), -1), -1, 1))
        try:
            s, extra = floor_scale(la[:, None] * fa, opts.camera_height, parallax)
        except ValueError as exc:
            raise PoseEstimationFailed(f"poses: camera_height given but {dense_exc} and {exc}; give baseline instead",
                                       code="scale_failed") from None
        floor = "points"
    return s, {"source": "camera_height", "camera_height_m": opts.camera_height, "baseline_m": s, "floor": floor,
               "seconds": time.perf_counter() - t0, **extra}


def refine_poses(erp_a: np.ndarray, erp_b: np.ndarray, c2w_a: np.ndarray, c2w_b: np.ndarray) -> tuple[np.ndarray, dict]:
    """Refine B's given pose against A (yaw about B's y axis and the travel direction; baseline kept)."""
    (fa, da), (fb, db) = map_threads(features, (erp_a, erp_b))
    rel = rigid_inverse(c2w_a) @ np.asarray(c2w_b, np.float64)
    R0, t_rel = rel[:3, :3], rel[:3, 3]
    length = float(np.linalg.norm(t_rel))
    yaw, t, inl, err = _guided_refine(fa, fb, Distances(da, db), 0.0, t_rel / length, R0=R0)
    info = _support(inl, err, "sift16-rootsift+guided-upright-refine")
    if len(inl) < MIN_INLIERS:
        info["applied"] = False
        return c2w_b, info
    info.update(applied=True, yaw_change_deg=float(np.degrees(yaw)),
                direction_change_deg=float(np.degrees(np.arccos(np.clip(t @ t_rel / length, -1, 1)))))
    return c2w_a @ _pose(R0 @ yaw_rotation(yaw), t * length), info


def poses_for_scene(erp_a: np.ndarray, erp_b: np.ndarray, poses, opts: PoseOptions,
                    data: tuple = (None, None)) -> tuple[np.ndarray, np.ndarray, dict]:
    """(c2w_a, c2w_b, metadata ``poses`` JSON) for given (:class:`service.inputs.Poses`) or missing (None) poses;
    ``data``: the two files' bytes when known (their XMP may hold the cameras' tilt). One picture sent twice (also
    re-encoded, resized or with noise: :func:`service.images.same_picture`) is refused whatever the poses say: it
    carries no depth (the estimator would refuse it by its matches, after the features' seconds); so is a panorama
    of one flat colour (:func:`service.images.check_not_blank`), whatever the poses say."""
    check_not_blank(erp_a, "image_a")
    check_not_blank(erp_b, "image_b")
    if same_picture(erp_a, erp_b):
        raise PoseEstimationFailed("image_a and image_b are the same picture: two captures from different places "
                                   "differ, and one picture twice carries no depth", code="no_parallax")
    if poses is None:
        c2w_a, c2w_b, support = estimate_poses(erp_a, erp_b, opts, data)
        source = "estimated"
    elif opts.refine_poses:
        c2w_a = poses.c2w_a
        c2w_b, support = refine_poses(erp_a, erp_b, poses.c2w_a, poses.c2w_b)
        source = "refined" if support["applied"] else "given"
    else:
        return poses.c2w_a, poses.c2w_b, {**poses.as_json(), "source": "given"}
    out = {"convention": "opencv", "c2w": [c2w_a.tolist(), c2w_b.tolist()], "source": source, "support": support}
    if poses is not None:
        out["input_convention"] = poses.convention
    return c2w_a, c2w_b, out
