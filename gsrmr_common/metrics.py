"""Image metrics used everywhere a loss is computed: PSNR, SSIM and the paper's MR loss.

Images are float arrays in [0, 1], H×W×C (or H×W). SSIM follows the 3DGS implementation (``utils/loss_utils.py``):
a Gaussian window (:data:`SSIM_WINDOW`, :data:`SSIM_SIGMA`), per channel, zero padding ("same" size), averaged over
every pixel and channel. The MR loss is L = (1 − λ)·mean|m − m̂| + λ·(1 − SSIM(m, m̂)), λ = 0.2; the paper prints its
DSSIM term as 1/(1 − SSIM), a typo: 1 − SSIM is the 3DGS convention.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2
MR_LOSS_LAMBDA = 0.2
PSNR_CAP_DB = 100.0  # PSNR of identical images (finite so averages and plots stay finite)


def gaussian_window_1d(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> np.ndarray:
    """Normalised 1-D Gaussian (float64); the SSIM window is its outer product with itself."""
    x = np.arange(size, dtype=np.float64) - size // 2
    g = np.exp(-(x**2) / (2.0 * sigma**2))
    return g / g.sum()


def _as_image(img: np.ndarray, name: str) -> np.ndarray:
    arr = np.asarray(img)
    if arr.dtype == np.uint8:
        arr = arr.astype(np.float32) / 255.0
    arr = arr.astype(np.float32, copy=False)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    if arr.ndim != 3:
        raise ValueError(f"{name}: expected H×W or H×W×C, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: contains NaN or inf")
    return arr


def _pair(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x, y = _as_image(a, "first image"), _as_image(b, "second image")
    if x.shape != y.shape:
        raise ValueError(f"image shapes differ: {x.shape} vs {y.shape}")
    return x, y


def _blur(img: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    return cv2.sepFilter2D(img, cv2.CV_32F, kernel, kernel, borderType=cv2.BORDER_CONSTANT)


def ssim_map(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-pixel, per-channel SSIM map (H×W×C, float32)."""
    x, y = _pair(a, b)
    kernel = gaussian_window_1d().astype(np.float32)
    out = np.empty_like(x)
    for c in range(x.shape[2]):
        xc = np.ascontiguousarray(x[:, :, c])
        yc = np.ascontiguousarray(y[:, :, c])
        mu_x, mu_y = _blur(xc, kernel), _blur(yc, kernel)
        sxx = _blur(xc * xc, kernel) - mu_x * mu_x
        syy = _blur(yc * yc, kernel) - mu_y * mu_y
        sxy = _blur(xc * yc, kernel) - mu_x * mu_y
        num = (2 * mu_x * mu_y + SSIM_C1) * (2 * sxy + SSIM_C2)
        den = (mu_x * mu_x + mu_y * mu_y + SSIM_C1) * (sxx + syy + SSIM_C2)
        out[:, :, c] = num / den
    return out


def ssim(a: np.ndarray, b: np.ndarray) -> float:
    """Mean SSIM of two images in [0, 1] (1.0 for identical images)."""
    return float(np.mean(ssim_map(a, b), dtype=np.float64))


def l1(a: np.ndarray, b: np.ndarray) -> float:
    """Mean absolute difference."""
    x, y = _pair(a, b)
    return float(np.mean(np.abs(x - y), dtype=np.float64))


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR in dB for images in [0, 1]; identical images give :data:`PSNR_CAP_DB`."""
    x, y = _pair(a, b)
    mse = float(np.mean((x - y) ** 2, dtype=np.float64))
    if mse <= 10.0 ** (-PSNR_CAP_DB / 10.0):
        return PSNR_CAP_DB
    return -10.0 * math.log10(mse)


def pooled_psnr_db(psnr_values_db) -> float:
    """PSNR of a set of images taken together (``psnr_db`` in every report): the PSNR of their mean MSE,
    −10·log10(mean_t 10^(−PSNR_t/10)) for images in [0, 1] of one size. A few bad slots pull it down far
    more than the mean of the per-slot PSNRs (``psnr_slot_mean_db``), which is also reported; NaN for none."""
    values = np.asarray([v for v in np.ravel(psnr_values_db) if math.isfinite(v)], np.float64)
    if values.size == 0:
        return math.nan
    return float(-10.0 * np.log10(np.mean(10.0 ** (-values / 10.0))))


def mr_loss(m: np.ndarray, m_hat: np.ndarray, lam: float = MR_LOSS_LAMBDA) -> float:
    """The paper's MR loss (1 − λ)·mean|m − m̂| + λ·(1 − SSIM(m, m̂)); 0 for identical images."""
    if not 0.0 <= lam <= 1.0:
        raise ValueError(f"lambda must be in [0, 1], got {lam}")
    return (1.0 - lam) * l1(m, m_hat) + lam * (1.0 - ssim(m, m_hat))


def image_quality(reference: np.ndarray, test: np.ndarray) -> dict[str, float]:
    """All metrics at once: ``{"loss", "psnr_db", "ssim", "l1"}``."""
    s = ssim(reference, test)
    d = l1(reference, test)
    return {"loss": (1 - MR_LOSS_LAMBDA) * d + MR_LOSS_LAMBDA * (1 - s), "psnr_db": psnr(reference, test),
            "ssim": s, "l1": d}
