"""The in-slot image/key rule (pure): a price λ on the loss budget (J per unit of loss), turned into per-slot gain
thresholds: the robot sends an image in slot t iff the gain its radio measures (a dimensionless ``|h|²``) reaches
``g*_t = c/(λ·L_t)``, c in J (:func:`saving_coefficient_j`). The derivation and the expected-loss condition that
sets λ: docs/scheduling.md, "The in-slot rule: the price and the gain thresholds".
"""

from __future__ import annotations

import math

import numpy as np

from gsrmr_common import link_model as link
from gsrmr_common.channel import rician_power_samples  # noqa: F401 (re-exported: the fades the rule prices)

DEEP_FADE_FRACTION = 0.02  # slots in the worst 2 % of fades never send an image


def saving_coefficient_j(image_bits: float, key_bits: float, slot_s: float, bandwidth_hz: float,
                         noise_w: float) -> float:
    """c such that an image minus a key costs c/g joules at gain g."""
    a_i = link.snr_exponent(image_bits, slot_s, bandwidth_hz)
    a_s = link.snr_exponent(key_bits, slot_s, bandwidth_hz)
    return float(slot_s * noise_w * (math.expm1(a_i) - math.expm1(a_s)))


def gain_thresholds(mean_gain: np.ndarray, loss: np.ndarray, loss_cap: float, coeff_j: float,
                    samples: np.ndarray, min_image_prob: float | np.ndarray = 0.0) -> tuple[np.ndarray, float, float]:
    """(g*_t per slot, λ, expected loss of the rule) for a horizon with loss budget ``loss_cap`` (Σ, not
    mean). ``samples``: :func:`rician_power_samples`. All keys when the whole predicted loss fits
    (λ = 0, g* = +inf); images in all but the deepest fades when nothing fits (λ = +inf).

    Slots whose fade is among the deepest ``DEEP_FADE_FRACTION`` never send an image (the threshold is at
    least that quantile of ``m_t·|h|²``), even when nothing fits (λ = +inf).

    ``min_image_prob`` (exploration): every slot with L_t > 0 sends an image at least when its fade is in
    the best ``min_image_prob`` fraction (g*_t capped at that quantile of ``m_t·|h|²``) — cheap images that
    keep measuring L_t where the predictions may be wrong (a scalar, or one fraction per slot). The
    expected loss returned includes it."""
    thresholds, lam, _ = _price(mean_gain, loss, loss_cap, coeff_j, samples)
    m = np.asarray(mean_gain, np.float64)
    L = np.maximum(np.asarray(loss, np.float64), 0.0)
    # never an image in the deepest fades (bottom DEEP_FADE_FRACTION): with K = 1 one such image can cost
    # more than the rest of a run together (seen live: λ = ∞ after an overspend, an image at 0.2 % of the
    # mean gain, 90 % of the run's energy); the key it sends instead costs L_t once
    floor = float(np.quantile(samples, DEEP_FADE_FRACTION)) * m
    thresholds = np.where(L > 0, np.maximum(thresholds, floor), thresholds)
    prob = np.broadcast_to(np.clip(np.asarray(min_image_prob, np.float64), 0.0, 1.0), thresholds.shape)
    if not np.any(prob > 0):
        p_key = np.searchsorted(samples, np.where(np.isinf(thresholds), np.inf, thresholds / m)) / samples.size
        return thresholds, lam, float(np.sum(L * p_key))
    q = np.where(prob > 0, np.quantile(samples, 1.0 - prob), np.inf)
    capped = np.where(L > 0, np.maximum(np.minimum(thresholds, q * m), floor), thresholds)
    p_key = np.searchsorted(samples, np.where(np.isinf(capped), np.inf, capped / m)) / samples.size
    return capped, lam, float(np.sum(L * p_key))


def _price(mean_gain: np.ndarray, loss: np.ndarray, loss_cap: float, coeff_j: float,
           samples: np.ndarray) -> tuple[np.ndarray, float, float]:
    m = np.asarray(mean_gain, np.float64)
    L = np.maximum(np.asarray(loss, np.float64), 0.0)
    pos = L > 0
    inf = np.full(L.shape, np.inf)
    if math.fsum(L.tolist()) <= loss_cap:
        return inf, 0.0, math.fsum(L.tolist())
    if loss_cap <= 0:
        out = np.where(pos, 0.0, np.inf)
        return out, math.inf, 0.0
    n = samples.size

    def expected(lam: float) -> float:
        q = coeff_j / (lam * L[pos] * m[pos])  # threshold in units of the mean gain
        return float(np.sum(L[pos] * np.searchsorted(samples, q) / n))

    ref = coeff_j / (L[pos] * m[pos])
    lo, hi = math.log(float(ref.min()) / samples[-1] / 10), math.log(float(ref.max()) / samples[0] * 10)
    for _ in range(80):  # expected() decreases in λ: bisection on ln λ
        mid = 0.5 * (lo + hi)
        if expected(math.exp(mid)) > loss_cap:
            lo = mid
        else:
            hi = mid
    lam = math.exp(hi)
    thresholds = np.where(pos, coeff_j / (lam * np.where(pos, L, 1.0)), np.inf)
    return thresholds, lam, expected(lam)


def cap_expected_images(thresholds: np.ndarray, mean_gain: np.ndarray, samples: np.ndarray,
                        max_images: float) -> tuple[np.ndarray, float]:
    """Raise the gain thresholds by one common factor until the rule's expected number of images,
    ``Σ P(m_t·|h|² ≥ g*_t)``, is at most ``max_images`` (a link that carries fewer images than the loss budget
    asks for); returns (thresholds, factor ≥ 1). Scaling every g*_t = c/(λ·L_t) by s is raising the price λ by
    s: the images kept are still the ones that save the most loss per joule. Thresholds of 0 (image always)
    are first set to the lowest fade drawn, so that they can rise too; +inf (never) stays."""
    m = np.asarray(mean_gain, np.float64)
    t = np.asarray(thresholds, np.float64)
    finite = np.isfinite(t)
    base = np.where(finite, np.maximum(t / m, samples[0]), np.inf)  # in units of the mean gain

    def expected(scale: float) -> float:
        q = base[finite] * scale
        return float(np.sum(1.0 - np.searchsorted(samples, q) / samples.size))

    if max_images < 0 or expected(1.0) <= max_images:
        return t.copy(), 1.0
    lo, hi = 0.0, math.log(float(samples[-1]) / float(base[finite].min())) + 1.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if expected(math.exp(mid)) > max_images:
            lo = mid
        else:
            hi = mid
    scale = math.exp(hi)
    return np.where(finite, base * scale * m, np.inf), scale
