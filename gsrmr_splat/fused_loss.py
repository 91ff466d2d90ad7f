"""The fused engine's loss (:class:`FusedLoss`): 0.8·L1 + 0.2·(1 − SSIM) of a render against its target and its gradient
with respect to the render, in three parallel numba passes over image rows; the SSIM is
:func:`~gsrmr_splat.losses.ssim_torch`'s. The gradient and the passes: docs/splatting.md, "The fused loss".
"""

from __future__ import annotations

import numba as nb
import numpy as np

from gsrmr_common.metrics import SSIM_C1, SSIM_C2, gaussian_window_1d

RADIUS = 5  # half the 11-tap window
_R = np.uint64(RADIUS)
_TAPS = np.uint64(2 * RADIUS + 1)
_F0, _F2 = np.float32(0.0), np.float32(2.0)
N_STATS = 15  # x, y, x², y², x·y per channel
N_DERIV = 9  # ∂m/∂μx, ∂m/∂E[x²], ∂m/∂E[xy] per channel


@nb.njit(inline="always", fastmath=True, cache=True)
def _hblur(src, s0, dst, d0, width, w):
    """dst[d0 + u] = Σ_k w[k]·src[s0 + u + k], u < width (src padded by RADIUS zeros at each end)."""
    w0 = w[0]
    for u in range(width):
        dst[d0 + u] = w0 * src[s0 + u]
    for k in range(np.uint64(1), _TAPS):
        wk = w[k]
        for u in range(width):
            dst[d0 + u] += wk * src[s0 + u + k]


@nb.njit(inline="always", fastmath=True, cache=True)
def _vblur(src, plane, v, rows_padded, width, w, dst, d0):
    """dst[d0 + u] = Σ_k w[k]·src[plane, v + k, u] for a buffer of ``rows_padded`` = H + 10 rows per plane."""
    base = (plane * rows_padded + v) * width
    w0 = w[0]
    for u in range(width):
        dst[d0 + u] = w0 * src[base + u]
    for k in range(np.uint64(1), _TAPS):
        wk = w[k]
        b = base + k * width
        for u in range(width):
            dst[d0 + u] += wk * src[b + u]


@nb.njit(parallel=True, fastmath=True, cache=True)
def _pass_stats(pred, target, w, hb):
    """Pass 1: the statistics of each row, blurred along the row, into rows v + RADIUS of ``hb``."""
    h, wd = pred.shape[0], pred.shape[1]
    uw = np.uint64(wd)
    rows_p = np.uint64(h + 2 * RADIUS)
    padded = uw + np.uint64(2) * _R
    for v in nb.prange(h):
        row = np.zeros(N_STATS * (wd + 2 * RADIUS), np.float32)
        for c in range(3):
            uc = np.uint64(c)
            for u in range(wd):
                x = np.float32(pred[v, u, c])
                y = np.float32(target[v, u, c])
                i = _R + np.uint64(u)
                row[uc * padded + i] = x
                row[(np.uint64(3) + uc) * padded + i] = y
                row[(np.uint64(6) + uc) * padded + i] = x * x
                row[(np.uint64(9) + uc) * padded + i] = y * y
                row[(np.uint64(12) + uc) * padded + i] = x * y
        uv = np.uint64(v) + _R
        for q in range(np.uint64(N_STATS)):
            _hblur(row, q * padded, hb, (q * rows_p + uv) * uw, uw, w)


@nb.njit(parallel=True, fastmath=True, cache=True)
def _pass_maps(hb, w, c1, c2, hd, row_sums):
    """Pass 2: column blur → μ, E[x²], E[xy] …; the SSIM map (its row sums) and its derivatives, blurred along
    the row, into rows v + RADIUS of ``hd``."""
    n_planes = hb.shape[0]
    rows_p = hb.shape[1]
    wd = hb.shape[2]
    h = rows_p - 2 * RADIUS
    uw = np.uint64(wd)
    urp = np.uint64(rows_p)
    padded = uw + np.uint64(2) * _R
    flat = hb.reshape(-1)
    out = hd.reshape(-1)
    for v in nb.prange(h):
        col = np.empty(N_STATS * wd, np.float32)
        der = np.zeros(N_DERIV * (wd + 2 * RADIUS), np.float32)
        for q in range(np.uint64(n_planes)):
            _vblur(flat, q, np.uint64(v), urp, uw, w, col, q * uw)
        s = 0.0
        for c in range(3):
            uc = np.uint64(c)
            for u in range(uw):
                mx = col[uc * uw + u]
                my = col[(np.uint64(3) + uc) * uw + u]
                sxx = col[(np.uint64(6) + uc) * uw + u] - mx * mx
                syy = col[(np.uint64(9) + uc) * uw + u] - my * my
                sxy = col[(np.uint64(12) + uc) * uw + u] - mx * my
                a1 = _F2 * mx * my + c1
                a2 = _F2 * sxy + c2
                b1 = mx * mx + my * my + c1
                b2 = sxx + syy + c2
                inv = np.float32(1.0) / (b1 * b2)
                m = a1 * a2 * inv
                s += m
                d_mu = _F2 * my * a2 * inv - m * _F2 * mx / b1
                d_sxx = -m / b2
                d_sxy = _F2 * a1 * inv
                i = _R + u
                # as a function of (μx, E[x²], E[xy]): σxx = E[x²] − μx², σxy = E[xy] − μx·μy
                der[(np.uint64(3) * uc) * padded + i] = d_mu - _F2 * mx * d_sxx - my * d_sxy
                der[(np.uint64(3) * uc + np.uint64(1)) * padded + i] = d_sxx
                der[(np.uint64(3) * uc + np.uint64(2)) * padded + i] = d_sxy
        row_sums[v] = s
        uv = np.uint64(v) + _R
        for q in range(np.uint64(N_DERIV)):
            _hblur(der, q * padded, out, (q * urp + uv) * uw, uw, w)


@nb.njit(parallel=True, fastmath=True, cache=True)
def _pass_grad(pred, target, hd, w, l1_weight, ssim_weight, g_out, row_abs, row_sq):
    """Pass 3: column blur of the derivatives; g_out = l1_weight·sign(x − y) − ssim_weight·(G∗a + 2x·G∗b + y·G∗c);
    per row Σ|x − y| and Σ(clip(x, 0, 1) − y)² (float64)."""
    h, wd = pred.shape[0], pred.shape[1]
    uw = np.uint64(wd)
    urp = np.uint64(h + 2 * RADIUS)
    flat = hd.reshape(-1)
    lw = np.float32(l1_weight)
    sw = np.float32(ssim_weight)
    for v in nb.prange(h):
        back = np.empty(N_DERIV * wd, np.float32)
        for q in range(np.uint64(N_DERIV)):
            _vblur(flat, q, np.uint64(v), urp, uw, w, back, q * uw)
        sa = 0.0
        sq = 0.0
        for c in range(3):
            uc = np.uint64(c)
            for u in range(wd):
                uu = np.uint64(u)
                x = np.float32(pred[v, u, c])
                y = np.float32(target[v, u, c])
                d = x - y
                sa += abs(d)
                e = min(max(x, _F0), np.float32(1.0)) - y
                sq += e * e
                sgn = np.float32(1.0) if d > _F0 else (np.float32(-1.0) if d < _F0 else _F0)
                ds = (back[np.uint64(3) * uc * uw + uu] + _F2 * x * back[(np.uint64(3) * uc + np.uint64(1)) * uw + uu]
                      + y * back[(np.uint64(3) * uc + np.uint64(2)) * uw + uu])
                g_out[v, u, c] = lw * sgn - sw * ds
        row_abs[v] = sa
        row_sq[v] = sq


class FusedLoss:
    """0.8·L1 + 0.2·(1 − SSIM) and its gradient (docs/splatting.md, "The fused loss"); keeps its row buffers
    between calls."""

    def __init__(self, lam: float = 0.2) -> None:
        self.lam = lam
        self.window = gaussian_window_1d().astype(np.float32)
        self._shape: tuple[int, int] | None = None

    def _buffers(self, h: int, w: int) -> None:
        if self._shape != (h, w):  # the pad rows stay zero: the passes write rows RADIUS .. h + RADIUS − 1 only
            self._hb = np.zeros((N_STATS, h + 2 * RADIUS, w), np.float32)
            self._hd = np.zeros((N_DERIV, h + 2 * RADIUS, w), np.float32)
            self._shape = (h, w)

    def __call__(self, pred: np.ndarray, target: np.ndarray, g_out: np.ndarray) -> tuple[float, float, float]:
        """Loss of H×W×3 ``pred`` against ``target``, its gradient into ``g_out`` (H×W×3); returns
        (loss, SSIM, MSE of clip(pred, 0, 1))."""
        h, w = pred.shape[0], pred.shape[1]
        self._buffers(h, w)
        n = float(h * w * 3)
        row_sums, row_abs, row_sq = np.empty(h), np.empty(h), np.empty(h)
        _pass_stats(pred, target, self.window, self._hb.reshape(-1))
        _pass_maps(self._hb, self.window, np.float32(SSIM_C1), np.float32(SSIM_C2), self._hd, row_sums)
        _pass_grad(pred, target, self._hd, self.window, (1.0 - self.lam) / n, self.lam / n, g_out, row_abs, row_sq)
        ssim_val = float(row_sums.sum()) / n
        l1 = float(row_abs.sum()) / n
        return (1.0 - self.lam) * l1 + self.lam * (1.0 - ssim_val), ssim_val, float(row_sq.sum()) / n
