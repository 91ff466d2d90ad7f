"""Training losses of the 3DGS recipe (torch): SSIM with the 11-tap Gaussian window and
``(1 − λ)·L1 + λ·(1 − SSIM)``, λ = 0.2.
"""

from __future__ import annotations

import torch

from gsrmr_common.metrics import SSIM_C1, SSIM_C2, gaussian_window_1d


def ssim_torch(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of two H×W×C images, identical to :func:`gsrmr_common.metrics.ssim` (differentiable)."""
    g = torch.as_tensor(gaussian_window_1d(), dtype=a.dtype)
    win = (g[:, None] * g[None, :])[None, None]
    c = a.shape[2]
    x = a.permute(2, 0, 1)[None]
    y = b.permute(2, 0, 1)[None]
    w = win.expand(c, 1, -1, -1)
    pad = win.shape[-1] // 2

    def blur(t: torch.Tensor) -> torch.Tensor:
        return torch.nn.functional.conv2d(t, w, padding=pad, groups=c)

    mu_x, mu_y = blur(x), blur(y)
    sxx = blur(x * x) - mu_x * mu_x
    syy = blur(y * y) - mu_y * mu_y
    sxy = blur(x * y) - mu_x * mu_y
    num = (2 * mu_x * mu_y + SSIM_C1) * (2 * sxy + SSIM_C2)
    den = (mu_x * mu_x + mu_y * mu_y + SSIM_C1) * (sxx + syy + SSIM_C2)
    return (num / den).mean()


def train_loss(pred: torch.Tensor, target: torch.Tensor, lam: float = 0.2) -> torch.Tensor:
    """(1 − λ)·L1 + λ·(1 − SSIM), λ = 0.2 (the 3DGS loss and the paper's MR loss)."""
    return (1.0 - lam) * (pred - target).abs().mean() + lam * (1.0 - ssim_torch(pred, target))
