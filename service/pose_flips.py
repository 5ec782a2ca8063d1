"""Is one panorama of a pair flipped as a whole (mirrored left-right, upside down, flipped top-bottom)?

A mirrored panorama is no view of the other's room, yet fits a relative pose exactly: reflected across the vertical
plane normal to the baseline, every bearing stays in its epipolar plane. An upside-down one can seed an upright
pose with a few agreeing matches. On the dev scenes and a synthetic room either gave a confident pose 170-180 deg
wrong (hundreds of guided inliers). Flipping B's features back costs no new features: SIFT is invariant to the
180-deg turn, and a mirror permutes its descriptor's bins (:data:`MIRROR_BINS`); the bearings change sign per
axis (:data:`FLIPS`). :func:`flip_supports` compares the seed support of B as it is with B flipped each way.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from rasterizer.relative_pose import upright_ransac

#: A seed pose agreeing with fewer than this share of its putative matches (or seeded at the second ratio) is
#: checked: a mirrored or upside-down B leaves 0-30% of them agreeing, a true pair of the dev scenes 37-99%.
FLIP_CHECK_SHARE = 0.5
#: B flipped wins when its seed support is at least this many times B's as it is (and a pose's worth).
FLIP_MARGIN = 2.0
#: At most this many putative matches seed each RANSAC of the check (a random subset, fixed seed).
FLIP_CHECK_MATCHES = 400
_I, _J, _O = np.meshgrid(np.arange(4), np.arange(4), np.arange(8), indexing="ij")
#: SIFT's descriptor of the left-right mirror of a patch: the 4 x 4 x 8 bins (row i, column j, orientation o) go
#: to (3 - i, j, -o) (the keypoint's frame keeps x along its orientation, so the mirror flips its y).
MIRROR_BINS = ((3 - _I) * 32 + _J * 8 + (8 - _O) % 8).ravel()
#: (name, the sign per axis of B's levelled bearings, descriptors mirrored). A left-right mirror negates x, upside
#: down (turned 180 deg in the image plane) x and y, top-bottom flipped y. A flipped panorama's levelling is the
#: flipped levelling (the lines' down is taken along +y either way), so the signs apply to levelled bearings too.
FLIPS = (("mirrored left-right", np.array([-1.0, 1.0, 1.0]), True),
         ("upside down", np.array([-1.0, -1.0, 1.0]), False),
         ("flipped top-bottom", np.array([1.0, -1.0, 1.0]), True))


def seed_support(fa: np.ndarray, fb: np.ndarray, pairs: np.ndarray, min_pairs: int, seed: int = 0) -> int:
    """Matches of ``pairs`` (M, 2) of bearings ``fa``, ``fb`` agreeing with upright RANSAC's best pose (on at most
    :data:`FLIP_CHECK_MATCHES` of them); 0 when they are fewer than ``min_pairs``."""
    if len(pairs) < min_pairs:
        return 0
    if len(pairs) > FLIP_CHECK_MATCHES:
        pairs = pairs[np.sort(np.random.default_rng(seed).choice(len(pairs), FLIP_CHECK_MATCHES, replace=False))]
    try:
        return upright_ransac(fa[pairs[:, 0]], fb[pairs[:, 1]]).best.num_inliers
    except ValueError:
        return 0


def flip_supports(fa: np.ndarray, fb: np.ndarray, plain: np.ndarray, mirrored: np.ndarray,
                  min_pairs: int) -> tuple[int, str, int]:
    """(support of B as it is, the best flip's name, its support): ``plain`` and ``mirrored`` (M, 2) are the putative
    matches of A's descriptors with B's and with B's through :data:`MIRROR_BINS`."""
    as_is = seed_support(fa, fb, plain, min_pairs)
    name, best = max(((n, seed_support(fa, fb * sign, mirrored if mirror else plain, min_pairs))
                      for n, sign, mirror in FLIPS), key=lambda x: x[1])
    return as_is, name, best


def flipped(fa: np.ndarray, da: np.ndarray, fb: np.ndarray, db: np.ndarray, min_pairs: int, min_support: int, *,
            match: Callable[[np.ndarray], np.ndarray], plain: np.ndarray | None = None) -> str | None:
    """A refusal's message when B (bearings ``fb``, descriptors ``db``) matches A far better flipped than as it is:
    the best flip's seed support at least ``min_support`` and :data:`FLIP_MARGIN` times B's as sent; else None.
    ``match(descriptors)``: the putative matches (M, 2) of A's descriptors with those; ``plain``: ``match(db)`` when
    the caller has it already."""
    if min(len(da), len(db)) < min_pairs:  # too few features for a pose either way
        return None
    plain = match(db) if plain is None else plain
    mirrored = match(db[:, MIRROR_BINS])
    as_is, name, best = flip_supports(fa, fb, plain, mirrored, min_pairs)
    if best < min_support or best < FLIP_MARGIN * as_is:
        return None
    return (f"poses: image_b matches image_a far better {name} ({best} feature matches agree on a pose, {as_is} as "
            f"sent): one of the two panoramas is {name}; send both as the camera wrote them, or give poses")
