"""Given poses against their images: a swapped pair, the other axis convention, inverted matrices, or panoramas whose
forward axis is not at the image centre, that are mirrored or one of which is upside down, are refused.

A scene built on poses that do not belong to its images comes out as nonsense without a word: two uploads in
the wrong order, poses written in OpenGL's axes (y up, z backwards) sent as OpenCV's, world-to-camera matrices
sent as camera-to-world, or panoramas from a tool whose longitude origin or direction differs from ours (the forward
axis at column 0 or W/4 instead of W/2; longitude growing to the left), or one panorama upside down. Matching cannot
confirm such poses, so the reconstruction's mean confidence is low. Below :data:`CHECK_BELOW_CONFIDENCE` the poses are
read ten ways (:func:`readings`: as given, with image_a and image_b swapped, with both cameras in the other convention, as
world-to-camera matrices sent as camera-to-world, with both cameras turned about their vertical axis by a quarter,
half or three quarters of a turn, for mirrored panoramas, and for either panorama upside down) and each reading is
scored against the images:

1. Photometric agreement (:func:`service.photometric.photometric_scores`: the share of textured pixels of A that find
   their window in B along the epipolar curve). An alternative that agrees :data:`MISMATCH_RATIO` times better is a
   422 ``poses_mismatch`` that names it; the given reading :data:`MISMATCH_RATIO` times better than every
   alternative passes.
2. Between those margins (pairs far apart, or readings that are nearly the same relative pose), the images' SIFT
   matches decide (:func:`feature_support`): an alternative under which :data:`FEATURE_MARGIN` times as many of
   them as under the given reading (and :data:`MIN_FEATURE_SUPPORT` or more) lie on their epipolar planes with
   both rays meeting in front of the cameras is refused. A wrong reading sends the rays of most true matches apart
   or off their epipolar planes, whatever the baseline. Matches that move by a turn of the camera alone (one
   place, or one picture twice) are a 422 ``no_parallax``: they carry no depth whatever the poses say.

The margins on the dev scenes: docs/design.md, "Given poses are checked against their images".
"""

from __future__ import annotations

from typing import NoReturn

import numpy as np

from rasterizer.geometry import OPENGL_TO_OPENCV, rigid_inverse
from rasterizer.relative_pose import INLIER_DEG, epipolar_error, rotation_only_fraction, triangulate, yaw_rotation
from rasterizer.threads import map_threads

from .errors import BadInput
from .matching import Distances, putative_matches
from .photometric import photometric_scores
from .poses import MIN_RANSAC_INLIERS, NO_PARALLAX_SHARE, features

#: Mean confidence of a reconstruction below which its given poses are checked against the images: about 1.3 times
#: the highest a wrong reading reached on the dev splits (docs/design.md).
CHECK_BELOW_CONFIDENCE = 0.25
#: An alternative reading of the poses must agree this many times better with the images to refuse them.
MISMATCH_RATIO = 1.3
#: ... and agree on at least this share of the textured pixels (flat images agree with nothing).
MIN_AGREEMENT = 0.15
#: The refusal names every alternative within this fraction of the best one's agreement.
SAME_AGREEMENT = 0.9
#: Between the photometric margins, an alternative reading refuses the poses when at least this many times as many
#: feature matches support it as the given reading ...
FEATURE_MARGIN = 2.0
#: ... and at least this many (a relative pose's worth: :data:`service.poses.MIN_RANSAC_INLIERS`).
MIN_FEATURE_SUPPORT = MIN_RANSAC_INLIERS
#: Turns (deg) about the cameras' vertical axis read as a misplaced longitude origin: panoramas whose forward axis
#: is not at the image centre (docs/conventions.md, "Frames and pixels").
LONGITUDE_TURNS_DEG = (90, 180, 270)


def readings(c2w_a: np.ndarray, c2w_b: np.ndarray, convention: str = "opencv") -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """B's pose ``(R, t)`` in A's camera frame (``X_a = R X_b + t``) under each reading of two OpenCV c2w: as given,
    with the images swapped (A taken at ``c2w_b``), with both read in the other axis convention, with both inverted
    (world-to-camera matrices, as COLMAP writes them, sent in the request's ``convention``), with the panoramas'
    longitude origin a quarter, half or three quarters of a turn away from the cameras' forward axis (both cameras
    turned about their vertical axis by :data:`LONGITUDE_TURNS_DEG`; the set is the same in either convention),
    with both panoramas mirrored left to right (longitude growing towards the camera's left: each camera's x axis
    reversed), and with one panorama upside down (turned 180 deg in its image plane, as from a camera mounted
    upside down or a wrong orientation tag: that camera turned 180 deg about its forward axis)."""
    def relative(a, b):
        rel = rigid_inverse(a) @ b
        return rel[:3, :3], rel[:3, 3]

    flip = OPENGL_TO_OPENCV  # its own inverse: OpenCV <-> OpenGL camera axes
    sent = flip if convention == "opengl" else np.eye(4)  # the matrices as sent are c2w @ sent

    def inverted(c2w):  # the camera-to-world pose of a world-to-camera matrix sent as c2w, in OpenCV axes
        return sent @ rigid_inverse(c2w) @ sent

    out = {"given": relative(c2w_a, c2w_b), "swapped": relative(c2w_b, c2w_a),
           "other convention": relative(c2w_a @ flip, c2w_b @ flip),
           "world-to-camera": relative(inverted(c2w_a), inverted(c2w_b))}

    def turned(deg):  # a camera frame turned about its y axis by ``deg``
        m = np.eye(4)
        m[:3, :3] = yaw_rotation(np.radians(deg))
        return m

    frames = {**{f"longitude {deg}": turned(deg) for deg in LONGITUDE_TURNS_DEG},
              "mirrored": np.diag([-1.0, 1.0, 1.0, 1.0])}  # x axis reversed: orthogonal, so rigid_inverse inverts it
    out.update((name, relative(c2w_a @ m, c2w_b @ m)) for name, m in frames.items())  # both cameras changed alike
    upside_down = np.diag([-1.0, -1.0, 1.0, 1.0])  # a panorama turned 180 deg in its image plane: lat and lon negated
    out["image_a upside down"] = relative(c2w_a @ upside_down, c2w_b)
    out["image_b upside down"] = relative(c2w_a, c2w_b @ upside_down)
    return out


def matched_bearings(erp_a: np.ndarray, erp_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit bearings ``(a, b)``, (M, 3) each, in A's and B's camera frames, of the two panoramas' putative SIFT matches
    (:func:`service.matching.putative_matches`). erp_a, erp_b: panoramas (RGB or grey, uint8 or [0, 1] float,
    any 2:1 size)."""
    (fa, da), (fb, db) = map_threads(features, (erp_a, erp_b))
    pairs = putative_matches(Distances(da, db))
    return fa[pairs[:, 0]], fb[pairs[:, 1]]


def feature_support(a: np.ndarray, b: np.ndarray, poses: dict[str, tuple[np.ndarray, np.ndarray]]) -> dict[str, int]:
    """For each reading ``name: (R, t)`` (B in A's camera frame), how many matches (bearings ``a``, ``b`` (M, 3) of
    :func:`matched_bearings`) lie within :data:`rasterizer.relative_pose.INLIER_DEG` of their epipolar plane with both
    rays meeting in front of the cameras (positive ranges), their rays at least that far apart (nearer, the matching
    noise decides the ranges' sign). The epipolar test alone does not tell a pose from its swap: reversing the
    baseline keeps every epipolar plane, and it is the ranges' sign that flips."""
    out = {}
    for name, (R, t) in poses.items():
        near = epipolar_error(a, b, R, t) < np.radians(INLIER_DEG)
        apart = np.sum(a * (b @ R.T), axis=1) < np.cos(np.radians(INLIER_DEG))
        range_a, range_b = triangulate(a, b, R, t)
        out[name] = int(np.count_nonzero(near & apart & (range_a > 0) & (range_b > 0)))
    return out


def check_given_poses(erp_a: np.ndarray, erp_b: np.ndarray, c2w_a: np.ndarray, c2w_b: np.ndarray,
                      mean_confidence: float | None, convention: str = "opencv") -> dict | None:
    """Raise 422 ``poses_mismatch`` when the images agree far better with another reading of the given poses
    (:func:`readings`; the two tests of the module's docstring); returns the scores when they were taken (the
    reconstruction's ``mean_confidence`` below :data:`CHECK_BELOW_CONFIDENCE`): ``{"photometric": {reading: share}}``
    and, when the photometric margins did not decide, ``"feature_support": {reading: matches}``; else None.
    erp_a, erp_b: the two panoramas (any 2:1 size); c2w: 4x4 OpenCV; ``convention``: the one the request's
    matrices were sent in (:func:`readings`)."""
    if mean_confidence is None or mean_confidence >= CHECK_BELOW_CONFIDENCE:
        return None
    poses = readings(np.asarray(c2w_a, np.float64), np.asarray(c2w_b, np.float64), convention)
    # a reading that is the given relative pose is no alternative (m3d's cameras, both turned 180 deg about their x
    # axis, have the same relative pose as their inverted matrices): the images cannot tell them apart
    poses = {name: pose for name, pose in poses.items() if name == "given" or not _same_pose(pose, poses["given"])}
    names = tuple(poses)
    scores = dict(zip(names, photometric_scores(erp_a, erp_b, list(poses.values()))))
    out = {"photometric": scores}
    if len(names) == 1:
        return out
    best = max(names[1:], key=scores.get)
    if scores[best] >= MIN_AGREEMENT and scores[best] >= MISMATCH_RATIO * scores["given"]:
        _refuse(scores, best, "photometric", mean_confidence)
    if scores["given"] >= MISMATCH_RATIO * scores[best]:
        return out
    a, b = matched_bearings(erp_a, erp_b)
    static = rotation_only_fraction(a, b)
    if static >= NO_PARALLAX_SHARE:
        raise BadInput(f"poses: {static:.0%} of the images' feature matches move by a turn of the camera alone: the two "
                       f"panoramas were taken from (nearly) one place, or are one picture twice, which carries no depth "
                       f"whatever the poses say (these are {np.linalg.norm(poses['given'][1]):.3g} apart)",
                       code="no_parallax")
    support = feature_support(a, b, poses)
    out["feature_support"] = support
    best = max(names[1:], key=support.get)
    if support[best] >= MIN_FEATURE_SUPPORT and support[best] >= FEATURE_MARGIN * support["given"]:
        _refuse(support, best, "feature", mean_confidence)
    return out


def _same_pose(p: tuple[np.ndarray, np.ndarray], q: tuple[np.ndarray, np.ndarray], tol: float = 1e-6) -> bool:
    """Whether two relative poses ``(R, t)`` are one: the same rotation and travel direction within ``tol``."""
    (R1, t1), (R2, t2) = p, q
    u1, u2 = (t / max(float(np.linalg.norm(t)), 1e-12) for t in (t1, t2))
    return bool(np.allclose(R1, R2, atol=tol) and np.allclose(u1, u2, atol=tol))


def _refuse(scores: dict, best: str, test: str, mean_confidence: float) -> NoReturn:
    """The 422 ``poses_mismatch`` naming every alternative reading within :data:`SAME_AGREEMENT` of the ``best``
    one (for some camera layouts two readings are nearly the same relative pose); ``test``: which scores these are."""
    named = [name for name in scores if name != "given" and scores[name] >= SAME_AGREEMENT * scores[best]]
    if test == "photometric":
        evidence = f"{scores[best]:.0%} of the textured pixels find their match, {scores['given']:.0%} as sent"
    else:
        evidence = f"{scores[best]} feature matches meet in front of both cameras, {scores['given']} as sent"
    turns = dict.fromkeys(_TURN[n] for n in named if n in _TURN)  # the longitude readings, named as one
    texts = [_READING[n] for n in named if n not in _TURN]
    texts += [f"turned {' or '.join(turns)} turn about the cameras' vertical axis"] if turns else []
    fixes = "; ".join(dict.fromkeys(_FIX[n] for n in named))
    raise BadInput(f"poses: the images agree far better with the poses {' or '.join(texts)} ({evidence}; the reconstruction's "
                   f"mean confidence is {mean_confidence:.2f}): {fixes}", code="poses_mismatch")


_READING = {"swapped": "of the two images swapped", "other convention": "read in the other axis convention",
            "world-to-camera": "inverted", "mirrored": "read for panoramas mirrored left to right",
            "image_a upside down": "read for image_a upside down", "image_b upside down": "read for image_b upside down"}
_TURN = {f"longitude {deg}": "a half" if deg == 180 else "a quarter" for deg in LONGITUDE_TURNS_DEG}
_FIX = {"swapped": "check that image_a is the panorama taken at the first pose and image_b the one at the second",
        "other convention": 'check "convention": OpenCV cameras look along +z with +y down, OpenGL ones along -z '
                            "with +y up",
        "world-to-camera": '"c2w" takes camera-to-world matrices, whose last column is the camera\'s position: invert '
                           "world-to-camera ones (such as COLMAP writes)",
        "mirrored": "the panoramas' longitude must grow to the right (column 3W/4 looks along the camera's +x): "
                    "flip both images left to right",
        **{f"image_{v} upside down": f"turn image_{v} the right way up (180 degrees in its plane: the zenith at the top "
                                     "row); a camera mounted upside down, or an orientation tag that does not fit the "
                                     "pixels, gives such a panorama" for v in "ab"}}
_FIX.update({f"longitude {deg}": "check the panoramas' longitude origin: the image centre looks along the camera's "
                                 "forward axis (OpenCV +z, OpenGL -z) and column 3W/4 along its right (+x); turn the poses "
                                 "about their vertical axis, or roll the images, to match" for deg in LONGITUDE_TURNS_DEG})
