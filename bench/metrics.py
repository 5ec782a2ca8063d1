"""Image metrics of conventions section 6: PSNR, SSIM and WS-PSNR, and PSNR above the nadir cap.

Images are float arrays (H, W, 3) in [0, 1]; both are clipped to [0, 1]
for PSNR and WS-PSNR. SSIM is scikit-image's ``structural_similarity`` with
the settings the conventions fix (scikit-image is a bench/test dependency,
imported on first use).
"""

from __future__ import annotations

import numpy as np


def _check_pair(pred: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pred = np.asarray(pred, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    if pred.shape != target.shape:
        raise ValueError(f"image shapes differ: {pred.shape} vs {target.shape}")
    return np.clip(pred, 0.0, 1.0), np.clip(target, 0.0, 1.0)


def _psnr_from_mse(mse: float) -> float:
    return float("inf") if mse <= 0 else float(-10.0 * np.log10(mse))


def psnr(pred: np.ndarray, target: np.ndarray) -> float:
    """PSNR in dB of two images clipped to [0, 1]."""
    pred, target = _check_pair(pred, target)
    return _psnr_from_mse(float(np.mean((pred - target) ** 2)))


#: Degrees around the nadir that :func:`psnr_above_nadir` leaves out. Real 360 captures show the capture
#: rig there, attached to the camera rather than part of the scene: every ZInD panorama of the dev data
#: has a dark tripod disc below about -77 deg latitude (README, "The capture rig"). 15 deg is 8.3% of
#: an ERP image's rows.
NADIR_CAP_DEG = 15.0


def psnr_above_nadir(pred: np.ndarray, target: np.ndarray, cap_deg: float = NADIR_CAP_DEG) -> float:
    """PSNR of two ERP images over the rows whose pixel-centre latitude lies above -(90 - cap_deg) degrees.

    A diagnostic beside :func:`psnr`, not a replacement: a novel view cannot predict the camera-attached
    rig that the target's own capture shows at its nadir, while copying a reference gets it for free.
    """
    if not 0.0 <= cap_deg < 90.0:
        raise ValueError(f"cap_deg must be in [0, 90), got {cap_deg}")
    pred, target = _check_pair(pred, target)
    h = pred.shape[0]
    keep = (np.arange(h) + 0.5) / h * 180.0 < 180.0 - cap_deg
    return _psnr_from_mse(float(np.mean((pred[keep] - target[keep]) ** 2)))


def ws_psnr(pred: np.ndarray, target: np.ndarray) -> float:
    """WS-PSNR of two ERP images: MSE weighted by cos(latitude) of each row."""
    pred, target = _check_pair(pred, target)
    h = pred.shape[0]
    lat = np.pi / 2 - (np.arange(h) + 0.5) / h * np.pi
    w = np.cos(lat).reshape((h,) + (1,) * (pred.ndim - 1))
    err = (pred - target) ** 2 * w
    return _psnr_from_mse(float(err.sum() / (np.broadcast_to(w, err.shape).sum())))


def ssim(pred: np.ndarray, target: np.ndarray) -> float:
    """SSIM as scikit-image computes it with the conventions' settings."""
    from skimage.metrics import structural_similarity

    pred = np.asarray(pred, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    if pred.shape != target.shape:
        raise ValueError(f"image shapes differ: {pred.shape} vs {target.shape}")
    return float(
        structural_similarity(
            pred, target, data_range=1.0, gaussian_weights=True, sigma=1.5, win_size=11,
            channel_axis=-1 if pred.ndim == 3 else None,
        )
    )


#: Luma weights of conventions section 6 (sharpness, GMSD).
LUMA = (0.299, 0.587, 0.114)
#: GMSD's stability constant for images in [0, 1] (Xue et al. 2014: 170 for [0, 255] -> 170 / 255^2).
GMSD_C = 0.0026


def luma(image: np.ndarray) -> np.ndarray:
    """(H, W) luma of an (H, W, 3) image clipped to [0, 1]."""
    return np.clip(np.asarray(image, dtype=np.float64), 0.0, 1.0) @ np.asarray(LUMA)


def above_nadir_rows(height: int, cap_deg: float = NADIR_CAP_DEG) -> np.ndarray:
    """(H,) bool: ERP rows whose pixel-centre latitude lies above -(90 - cap_deg) degrees."""
    return (np.arange(height) + 0.5) / height * 180.0 < 180.0 - cap_deg


def box5_erp(y: np.ndarray) -> np.ndarray:
    """5x5 box mean of an (H, W) ERP map, wrapping in longitude and clamped (edge rows repeated) in latitude."""
    p = np.pad(y, ((2, 2), (0, 0)), mode="edge")
    p = np.pad(p, ((0, 0), (2, 2)), mode="wrap")
    c = np.cumsum(np.cumsum(np.pad(p, ((1, 0), (1, 0))), 0), 1)
    h, w = y.shape
    return (c[5:5 + h, 5:5 + w] - c[:h, 5:5 + w] - c[5:5 + h, :w] + c[:h, :w]) / 25.0


def detail(image: np.ndarray, rows: np.ndarray | None = None) -> float:
    """Mean |Y - box5(Y)| of an ERP image over ``rows`` (default all): its high-frequency energy."""
    y = luma(image)
    d = np.abs(y - box5_erp(y))
    return float(d[rows].mean() if rows is not None else d.mean())


def sharpness(pred: np.ndarray, target: np.ndarray, cap_deg: float = NADIR_CAP_DEG) -> float:
    """detail(pred) / detail(target) over the rows above the nadir cap: 1 = as sharp as the target,
    blur and ghosts fall towards 0 (conventions section 6)."""
    pred, target = _check_pair(pred, target)
    rows = above_nadir_rows(pred.shape[0], cap_deg)
    return detail(pred, rows) / max(detail(target, rows), 1e-12)


def _prewitt(y: np.ndarray) -> np.ndarray:
    """Gradient magnitude of an (H, W) map with 3x3 Prewitt kernels (/3), edges replicated."""
    p = np.pad(y, 1, mode="edge")
    gx = (p[:-2, 2:] + p[1:-1, 2:] + p[2:, 2:] - p[:-2, :-2] - p[1:-1, :-2] - p[2:, :-2]) / 3.0
    gy = (p[2:, :-2] + p[2:, 1:-1] + p[2:, 2:] - p[:-2, :-2] - p[:-2, 1:-1] - p[:-2, 2:]) / 3.0
    return np.sqrt(gx * gx + gy * gy)


def gmsd(pred: np.ndarray, target: np.ndarray, cap_deg: float = NADIR_CAP_DEG) -> float:
    """Gradient magnitude similarity deviation (Xue et al., IEEE TIP 2014) over the rows above the nadir cap.

    Luma, 2x2 average pooling, Prewitt 3x3 gradient magnitudes m_r, m_t; GMS = (2 m_r m_t + c) /
    (m_r^2 + m_t^2 + c) with c = ``GMSD_C``; GMSD = the standard deviation of GMS. 0 = identical structure.
    """
    pred, target = _check_pair(pred, target)
    rows = above_nadir_rows(pred.shape[0], cap_deg)

    def pooled(img):
        y = luma(img)
        h, w = (y.shape[0] // 2) * 2, (y.shape[1] // 2) * 2
        return y[:h, :w].reshape(h // 2, 2, w // 2, 2).mean(axis=(1, 3))

    mp, mt = _prewitt(pooled(pred)), _prewitt(pooled(target))
    gms = (2.0 * mp * mt + GMSD_C) / (mp * mp + mt * mt + GMSD_C)
    keep = rows[: 2 * gms.shape[0]].reshape(-1, 2).all(axis=1)  # pooled rows wholly above the cap
    return float(gms[keep].std())


def real_capture_scores(pred: np.ndarray, target: np.ndarray) -> dict:
    """The per-target figures of conventions section 6 for real captures: PSNR above the nadir cap (the
    headline), full PSNR, WS-PSNR, sharpness and GMSD."""
    return {"psnr_above_nadir": psnr_above_nadir(pred, target), "psnr": psnr(pred, target),
            "ws_psnr": ws_psnr(pred, target), "sharpness": sharpness(pred, target), "gmsd": gmsd(pred, target)}
