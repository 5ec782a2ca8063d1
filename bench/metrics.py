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
