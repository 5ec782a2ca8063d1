"""Image metrics of conventions section 6: PSNR, SSIM and WS-PSNR.

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
