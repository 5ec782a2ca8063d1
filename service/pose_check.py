"""Given poses against their images: a swapped pair or the other axis convention is refused, not built.

A scene built on poses that do not belong to its images comes out as nonsense without a word: two uploads in
the wrong order, or poses written in OpenGL's axes (y up, z backwards) sent as OpenCV's. Matching cannot confirm
such poses, so the reconstruction's mean confidence is low. Below :data:`CHECK_BELOW_CONFIDENCE` the two images'
photometric agreement (:func:`service.poses.photometric_score`: the share of textured pixels of A that find their
window in B along the epipolar curve) is scored under the poses as given, with image_a and image_b swapped, and with
both cameras read in the other convention; an alternative that agrees :data:`MISMATCH_RATIO` times better is a 422
``poses_mismatch`` that names it. Pairs far apart, whose readings agree nearly as well, are let through. The
thresholds' margins on the dev scenes: docs/design.md, "Given poses are checked against their images".
"""

from __future__ import annotations

import numpy as np

from rasterizer.geometry import OPENGL_TO_OPENCV, rigid_inverse
from rasterizer.threads import map_threads

from .errors import BadInput
from .poses import photometric_score

#: Mean confidence of a reconstruction below which its given poses are checked against the images.
CHECK_BELOW_CONFIDENCE = 0.15
#: An alternative reading of the poses must agree this many times better with the images to refuse them.
MISMATCH_RATIO = 1.3
#: ... and agree on at least this share of the textured pixels (flat images agree with nothing).
MIN_AGREEMENT = 0.15
#: The refusal names every alternative within this fraction of the best one's agreement.
SAME_AGREEMENT = 0.9

def readings(c2w_a: np.ndarray, c2w_b: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """B's pose ``(R, t)`` in A's camera frame (``X_a = R X_b + t``) under each reading of two OpenCV c2w:
    as given, with the images swapped (A taken at ``c2w_b``), and with both read in the other axis convention."""
    def relative(a, b):
        rel = rigid_inverse(a) @ b
        return rel[:3, :3], rel[:3, 3]

    flip = OPENGL_TO_OPENCV  # its own inverse: OpenCV <-> OpenGL camera axes
    return {"given": relative(c2w_a, c2w_b), "swapped": relative(c2w_b, c2w_a),
            "other convention": relative(c2w_a @ flip, c2w_b @ flip)}


def check_given_poses(erp_a: np.ndarray, erp_b: np.ndarray, c2w_a: np.ndarray, c2w_b: np.ndarray,
                      mean_confidence: float | None) -> dict | None:
    """Raise 422 ``poses_mismatch`` when the images agree far better with another reading of the given poses
    (:func:`readings`); returns the scores when they were taken (the reconstruction's ``mean_confidence`` below
    :data:`CHECK_BELOW_CONFIDENCE`), else None. erp_a, erp_b: the two panoramas (any 2:1 size); c2w: 4x4 OpenCV."""
    if mean_confidence is None or mean_confidence >= CHECK_BELOW_CONFIDENCE:
        return None
    names, poses = zip(*readings(np.asarray(c2w_a, np.float64), np.asarray(c2w_b, np.float64)).items())
    scores = dict(zip(names, map_threads(lambda pose: photometric_score(erp_a, erp_b, *pose), poses)))
    best = max(names[1:], key=scores.get)
    if scores[best] < MIN_AGREEMENT or scores[best] < MISMATCH_RATIO * scores["given"]:
        return scores
    # both alternatives as good: for some camera layouts the two readings are nearly the same relative pose
    named = [name for name in names[1:] if scores[name] >= SAME_AGREEMENT * scores[best]]
    raise BadInput(f"poses: the images agree far better with the poses {' or '.join(_READING[n] for n in named)} "
                   f"({scores[best]:.0%} of the textured pixels find their match, {scores['given']:.0%} as sent; the "
                   f"reconstruction's mean confidence is {mean_confidence:.2f}): "
                   f"{'; '.join(_FIX[n] for n in named)}", code="poses_mismatch")


_READING = {"swapped": "of the two images swapped", "other convention": "read in the other axis convention"}
_FIX = {"swapped": "check that image_a is the panorama taken at the first pose and image_b the one at the second",
        "other convention": 'check "convention": OpenCV cameras look along +z with +y down, OpenGL ones along -z '
                            "with +y up"}
