"""Dense floor-plane sweep: the floor's distance below camera A in baseline units (numpy only).

Given the relative pose of two panoramas (levelled frames, ``[R | t]`` with unit ``t``, as in
:mod:`rasterizer.relative_pose`), a horizontal plane ``y = d`` below A maps every below-horizon
pixel of A to a pixel of B. The sweep tries many ``d`` and scores each by the photo-consistency of
A's lower band with B warped through that plane (ZNCC of small windows); the same from B's side
with the plane ``d - t_y`` below B. Furniture tops are planes too, but higher (smaller ``d``); the
floor is the lowest plane that explains a large share of the band.
"""

from __future__ import annotations

import numpy as np

from .camera import sample_erp
from .geometry import direction_from_lat_lon, project_to_grid
from .threads import map_threads


def _box_sum(img: np.ndarray, r: int) -> np.ndarray:
    """Sum over (2r+1)^2 windows of (..., H, W); columns wrap (ERP longitude), rows are clipped."""
    p = np.concatenate([img[..., -r:], img, img[..., :r]], axis=-1)
    c = np.cumsum(p, axis=-1)
    c = np.concatenate([np.zeros_like(c[..., :1]), c], axis=-1)
    s = c[..., 2 * r + 1:] - c[..., :-2 * r - 1]
    h = s.shape[-2]
    c = np.cumsum(s, axis=-2)
    c = np.concatenate([np.zeros_like(c[..., :1, :]), c], axis=-2)
    lo = np.clip(np.arange(h) - r, 0, h)
    hi = np.clip(np.arange(h) + r + 1, 0, h)
    return c[..., hi, :] - c[..., lo, :]


def _window_stats(img: np.ndarray, r: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean and variance over (2r+1)^2 windows of (..., H, W)."""
    n = (2 * r + 1) ** 2
    mean = _box_sum(img, r) / n
    return mean, np.maximum(_box_sum(img * img, r) / n - mean * mean, 0.0)


def _zncc(a: np.ndarray, a_stats: tuple[np.ndarray, np.ndarray], b: np.ndarray, r: int, eps: float) -> np.ndarray:
    """Windowed ZNCC of ``a`` (H, W), with its :func:`_window_stats`, against each of ``b`` (K, H, W)."""
    ma, va = a_stats
    mb, vb = _window_stats(b, r)
    cov = _box_sum(a[None] * b, r) / (2 * r + 1) ** 2 - ma[None] * mb
    return cov / np.sqrt((va[None] + eps) * (vb + eps))


#: A pixel lies in a uniform area when some (2 r + 1)-pixel square around it, r this, holds one grey value: a black
#: nadir cap, a grey fill, a logo. No window of the dev scenes' floor bands is that flat at this size (their few
#: such areas, blown-out lamps and windows, lie near or above the horizon), while a cap's edge is the same curve in
#: both views under any plane far enough below, and its windows voted for such planes.
UNIFORM_RADIUS = 3


def near_uniform(img: np.ndarray, r: int) -> np.ndarray | None:
    """Pixels (H, W) bool of ``img`` within ``r`` of a uniform area (:data:`UNIFORM_RADIUS`) below the horizon
    (where the band and the planes' points below the cameras lie), None when it has none: windows of radius ``r``
    there are not compared."""
    g = np.asarray(img, np.float64)
    n = (2 * UNIFORM_RADIUS + 1) ** 2
    mean = _box_sum(g, UNIFORM_RADIUS) / n
    flat = _box_sum(g * g, UNIFORM_RADIUS) / n - mean * mean < 1e-8  # one step of 1/255 is 3e-7
    flat[:g.shape[0] // 2] = False
    if not flat.any():
        return None
    return _box_sum(flat.astype(np.float64), UNIFORM_RADIUS + r) > 0.5


#: The band below a camera that the sweep compares: this far from its nadir (deg); the nadir cap hides the
#: photographer or the tripod.
BAND_DEG = (20.0, 80.0)


def band_directions(height: int, band_deg: tuple[float, float]) -> np.ndarray:
    """Levelled-frame directions (h, w, 3) of :func:`plane_zncc`'s band grid for ERPs ``height`` rows high."""
    lat = np.pi / 2 - (np.arange(height) + 0.5) / height * np.pi
    lon = (np.arange(height) + 0.5) / height * 2 * np.pi - np.pi
    lo, hi = np.radians(band_deg)
    rows = (lat >= lo - np.pi / 2 - 0.05) & (lat <= hi - np.pi / 2 + 0.05)
    return direction_from_lat_lon(lat[rows, None], lon[None, :])


def plane_zncc(ref: np.ndarray, other: np.ndarray, level_ref: np.ndarray, level_other: np.ndarray, R: np.ndarray,
               t: np.ndarray, normal: np.ndarray, offsets: np.ndarray, *, band_deg: tuple[float, float] = BAND_DEG,
               nadir_deg: float = 20.0, radius: int = 2, min_std: float = 0.02, chunk: int = 16) -> np.ndarray:
    """Windowed ZNCC (K, h, w) of ``ref``'s lower band with ``other`` warped through each plane
    ``normal . X = offsets[k]`` of ref's levelled frame; NaN where not scored.

    ref, other: grey ERPs (H, 2H), values in [0, 1], in their camera frames; level_*: (3, 3)
    levelled-from-camera turns; ``[R | t]``: other's pose in ref's levelled frame (``X_ref = R X_other + t``,
    both levelled). The band is a grid of h rows (ref's row spacing) by w = H columns (twice the row
    spacing in longitude, about the row spacing on the sphere 60 deg below the horizon), its pixels
    ``band_deg`` from ``normal`` (the nadir cap hides the photographer or the tripod). Not scored: flat
    windows (std below ``min_std``), points within ``nadir_deg`` of other's nadir, and windows of either view that
    reach a uniform area (:func:`near_uniform`)."""
    height = ref.shape[0]
    lo, hi = np.radians(band_deg)
    dirs = band_directions(height, band_deg)
    cos_n = dirs @ np.asarray(normal, np.float64)
    ang = np.arccos(np.clip(cos_n, -1.0, 1.0))
    in_ref = project_to_grid("erp", dirs @ level_ref, height, 2 * height)  # the band's pixels in ref
    a = sample_erp(ref.astype(np.float32)[..., None], *in_ref)[..., 0]
    stats = _window_stats(a, radius)
    keep = (ang >= lo) & (ang <= hi) & (stats[1] >= min_std ** 2)
    ref_uniform, other_uniform = near_uniform(ref, radius), near_uniform(other, radius)
    if ref_uniform is not None:
        keep &= sample_erp(ref_uniform.astype(np.float32)[..., None], *in_ref)[..., 0] == 0
    out = np.full((len(offsets),) + a.shape, np.nan, np.float32)
    cos_nadir = np.cos(np.radians(nadir_deg))
    ray = (dirs / np.maximum(cos_n, 1e-3)[..., None]).astype(np.float32)  # meets the plane at offset 1
    other = np.asarray(other, np.float32)[..., None]
    if other_uniform is not None:  # sampled with the image, as a second channel
        other = np.concatenate([other, other_uniform.astype(np.float32)[..., None]], axis=-1)
    t32, R32 = np.asarray(t, np.float32), np.asarray(R, np.float32)
    for s in range(0, len(offsets), chunk):
        off = np.asarray(offsets[s:s + chunk], np.float32)
        xo = (ray[None] * off[:, None, None, None] - t32) @ R32  # R^T (X - t): other's levelled frame
        warped = sample_erp(other, *project_to_grid("erp", xo @ level_other.astype(np.float32), height, 2 * height))
        z = _zncc(a, stats, warped[..., 0], radius, 1e-4)
        ok = keep[None] & (xo[..., 1] < cos_nadir * np.linalg.norm(xo, axis=-1)) & (off[:, None, None] > 0)
        if other_uniform is not None:
            ok &= _box_sum(warped[..., 1], radius) == 0
        out[s:s + chunk] = np.where(ok, z, np.nan)
    return out


#: The floor is trusted where it is seen near the cameras: within this angle (deg) of a camera's nadir a room
#: shows its floor or furniture tops, never a plane below the floor, while far content near the horizon can pile
#: votes on a deeper plane. With that part hidden (a black nadir cap of 60 deg, half a panorama grey) the deepest
#: plane left was a bed top or such a pile: a baseline 1.7 times or a fifth of the true one.
NEAR_FLOOR_DEG = 50.0
#: One view's band within NEAR_FLOOR_DEG of its nadir is scored (textured, not near a uniform area) on at least
#: this share of its pixels (the dev scenes' panoramas: 18-98% on the better view; behind a 45-deg black cap 3-10%).
MIN_NEAR_SCORED = 0.14
#: The floor's peak holds at least this share of one view's scored pixels within NEAR_FLOOR_DEG (the dev scenes'
#: floors: 6-56%; a pile of far votes 3%).
MIN_NEAR_SUPPORT = 0.045


class FloorHidden(ValueError):
    """The images do not show the floor near the cameras well enough to trust a plane as the floor."""


#: A window that also matches through a plane this many times deeper than the deepest candidate (no parallax left)
#: tells no height: content far away, or fixed to two cameras turned alike (a logo stamped on both nadirs of level
#: panoramas, whose rings of latitude stay in place under any yaw).
PARALLAX_FREE_FACTOR = 1000.0
#: A refusal for a floor not seen near the cameras names the parallax-free windows when they are at least this share
#: of a view's scored pixels there; it changes the message only (dev pairs up to 0.19, zind pairs with a 35-deg logo 0.81-0.83).
PARALLAX_FREE_NAMED = 0.5


#: Candidate floor distances below A, in baselines: 80 log-spaced values (5.4% apart), a baseline of
#: 1/16 to 4 camera heights.
FLOOR_RATIOS = np.exp(np.linspace(np.log(0.25), np.log(16.0), 80))


def floor_ratio(grey_a: np.ndarray, grey_b: np.ndarray, level_a: np.ndarray, level_b: np.ndarray, R: np.ndarray,
                t: np.ndarray, *, ratios: np.ndarray = FLOOR_RATIOS, min_zncc: float = 0.7, min_peak: float = 0.3,
                min_share: float = 0.01, width: int = 2, near_deg: float | None = NEAR_FLOOR_DEG,
                parallax_free_votes: bool = False) -> tuple[float, dict]:
    """Distance of the floor below A in baselines (``t`` is unit) from a dense plane sweep of both views.

    grey_*: grey ERPs (H, 2H) in [0, 1]; level_*: levelled-from-camera (3, 3); ``[R | t]``: B in A's
    levelled frame. Every band pixel of A (and of B, with the plane ``d - t_y`` below B) votes for the candidate
    ``ratios`` whose plane matches it best (:func:`plane_zncc`), when that ZNCC exceeds ``min_zncc`` and its ZNCC
    through a plane :data:`PARALLAX_FREE_FACTOR` times deeper than any candidate does not (a window that matches
    with no parallax tells no height; ``parallax_free_votes`` lets it vote, for a share that compares two poses).
    The floor is the deepest peak of the votes holding ``min_peak`` of the highest peak above the median (a bed or
    a table top is a plane too, higher: a smaller ratio; a floor is the lowest plane, nothing is seen below it)
    and ``min_share`` of the scored pixels within ``width`` bins. A peak at either end of ``ratios`` is not a
    plane: its voters' best plane lies at or beyond it (far content, with little parallax, piles on the deepest
    candidate).
    With ``near_deg`` (:data:`NEAR_FLOOR_DEG`), the floor must be seen near a camera: :class:`FloorHidden` when
    neither view's band within ``near_deg`` of its nadir is scored on :data:`MIN_NEAR_SCORED` of its pixels, or
    when no strong peak holds :data:`MIN_NEAR_SUPPORT` of one view's scored pixels there (the deepest that does is
    the floor). The ratio is refined by a parabola through the summed ZNCC of the floor's voters. Raises
    ``ValueError`` when no peak qualifies. Info: pixel counts, the floor's ``floor_share`` and every strong
    peak's ratio and share (``planes``)."""
    t = np.asarray(t, np.float64)
    normals = (np.array([0.0, 1.0, 0.0]), R[1])  # the floor's normal in A's and in B's levelled frame
    far = [] if parallax_free_votes else [float(np.max(ratios)) * PARALLAX_FREE_FACTOR]  # the last plane, if any
    sides = map_threads(plane_zncc, (grey_a, grey_b), (grey_b, grey_a), (level_a, level_b), (level_b, level_a), (R, R.T),
                        (t, -R.T @ t), normals, (np.append(ratios, far), np.append(ratios - t[1], far)))
    votes = np.zeros(len(ratios))
    winners, scored, near = [], 0, []
    dirs = band_directions(grey_a.shape[0], BAND_DEG) if near_deg is not None else None
    for zf, normal in zip(sides, normals, strict=True):
        z = zf[:len(ratios)]
        filled = np.where(np.isnan(z), -2.0, z)
        arg, best = filled.argmax(0), filled.max(0)
        no_parallax = np.zeros(best.shape, bool) if parallax_free_votes else zf[-1] > min_zncc
        good = (best > min_zncc) & ~no_parallax
        scored += int(np.count_nonzero(~np.isnan(z).all(0)))
        votes += np.bincount(arg[good], minlength=len(ratios))
        winners.append((z, arg, good))
        if dirs is not None:  # (votes, scored, band and parallax-free pixels) within near_deg of this view's nadir
            ang = np.degrees(np.arccos(np.clip(dirs @ normal, -1.0, 1.0)))
            m = (ang >= BAND_DEG[0]) & (ang < near_deg)
            near.append((np.bincount(arg[good & m], minlength=len(ratios)), int(np.count_nonzero(m & ~np.isnan(z).all(0))),
                         int(np.count_nonzero(m)), int(np.count_nonzero(m & no_parallax))))
    smooth = np.convolve(votes, [0.25, 0.5, 0.25], mode="same")
    padded = np.concatenate([[-1.0], smooth, [-1.0]])
    peaks = np.nonzero((padded[1:-1] > padded[:-2]) & (padded[1:-1] >= padded[2:]))[0]
    base = float(np.median(smooth))
    # a peak at either end of the candidates is censored, not a plane (docstring)
    peaks = peaks[(peaks > 0) & (peaks < len(ratios) - 1)]
    strong = peaks[smooth[peaks] - base >= min_peak * (smooth.max() - base)] if smooth.max() > base else peaks[:0]
    info = {"scored_pixels": scored, "voters": int(votes.sum())}
    if not len(strong):
        raise ValueError("the images agree on no horizontal plane below the camera: the floor is not seen in both views")

    def share_at(i):  # share of the scored pixels voting within ``width`` bins of candidate i
        return float(votes[max(i - width, 0):i + width + 1].sum() / max(scored, 1))

    k = int(strong.max())
    if near:
        seen = max(n / max(total, 1) for _, n, total, _ in near)
        fixed = max(f / max(n, 1) for _, n, _, f in near)
        info.update(near_floor_scored=seen, near_parallax_free=fixed)
        why = (f"; {fixed:.0%} of a view's pixels there line up with no parallax, as far content or what "
               "moves with the cameras does, such as a logo over the nadirs") if fixed >= PARALLAX_FREE_NAMED else ""
        if seen < MIN_NEAR_SCORED:
            raise FloorHidden(f"the floor within {near_deg:.0f} deg of straight down is textured on {seen:.0%} of the "
                              f"better view (need {MIN_NEAR_SCORED:.0%}): the floor is not seen well enough")
        support = [max(v[max(p - width, 0):p + width + 1].sum() / max(n, 1) for v, n, _, _ in near) for p in strong]
        near_peaks = strong[np.asarray(support) >= MIN_NEAR_SUPPORT]
        if not len(near_peaks):
            raise FloorHidden(f"no plane the images agree on is seen within {near_deg:.0f} deg of straight down "
                              f"(at most {max(support):.1%} of a view's pixels there, need {MIN_NEAR_SUPPORT:.1%}"
                              f"{why}): the floor is not seen well enough")
        k = int(near_peaks.max())
    lo_, hi_ = max(k - width, 0), min(k + width + 1, len(ratios))
    share = share_at(k)
    if share < min_share:
        raise ValueError(f"the lowest plane the images agree on holds {share:.1%} of the pixels below the camera "
                         f"(need {min_share:.0%}): the floor is not seen in both views")
    curve = sum(np.nansum(np.where((good & (np.abs(arg - k) <= width))[None], z, 0.0), axis=(1, 2))
                for z, arg, good in winners)
    j = int(np.clip(lo_ + np.argmax(curve[lo_:hi_]), 1, len(ratios) - 2))
    y0, y1, y2 = curve[j - 1:j + 2]
    step = np.clip(0.5 * (y0 - y2) / min(y0 - 2 * y1 + y2, -1e-9), -0.5, 0.5)
    log_r = np.log(ratios)
    d = float(np.exp(log_r[j] + step * (log_r[j + 1] - log_r[j])))
    return d, {**info, "floor_ratio": d, "floor_share": share,
               "planes": [{"ratio": float(ratios[p]), "share": share_at(p)} for p in strong]}
