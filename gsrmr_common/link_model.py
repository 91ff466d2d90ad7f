"""The uplink link model (pure numpy, no rclpy): rate, required power and energy, and the link budget.

One module for the robot (its energy ledger), the scheduler (its plan) and the experiments. :class:`LinkBudget`
holds the parameters in SI units (``config/link.yaml``'s names: :class:`gsrmr_common.link_params.LinkParameters`);
the fading draws are :mod:`gsrmr_common.channel`'s. The closed forms and why they are computed in the log domain:
docs/scheduling.md, "P_GS is a 0-1 knapsack once x is binary" and "Log domain and overflow".
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

from gsrmr_common.channel import PATHLOSS_DB_AT_1M, PATHLOSS_EXPONENT, RICIAN_K, ChannelModel
from gsrmr_common.wire import POSE_KEY_BITS

# The paper's link (Section V), in SI units: the defaults of the robot's ledger (LinkBudget), the
# scheduler's plan (its parameters) and every scheduling problem (gsrmr_scheduler.Problem).
SLOT_S = 0.1  # τ
IMAGE_BITS = 67_200.0  # I: the image size the plan assumes (8.4 kB)
KEY_BITS = float(POSE_KEY_BITS)  # S: the pose key, 3 × float64
BANDWIDTH_HZ = 1e6  # B
NOISE_W = 1e-9  # σ² = −60 dBm

LN2 = math.log(2.0)
#: ln of the largest float64 kept as a finite power/energy (leaves headroom for sums and products).
LOG_FLOAT_MAX = math.log(1e300)

ArrayLike = float | np.ndarray


def snr_exponent(bits: ArrayLike, slot_s: float, bandwidth_hz: float) -> ArrayLike:
    """Natural-log exponent ``a = D·ln2/(τB)`` such that ``1 + SNR = e^a`` carries ``bits`` in one slot."""
    return np.asarray(bits, dtype=np.float64) * LN2 / (slot_s * bandwidth_hz) if np.ndim(bits) else (
        float(bits) * LN2 / (slot_s * bandwidth_hz))


def log_expm1(a: ArrayLike) -> ArrayLike:
    """``ln(e^a − 1)`` for ``a ≥ 0`` without overflow (``−inf`` at ``a = 0``)."""
    arr = np.asarray(a, dtype=np.float64)
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
        big = arr + np.log1p(-np.exp(-np.maximum(arr, 1.0)))
        small = np.log(np.expm1(np.minimum(arr, 1.0)))
    out = np.where(arr > 1.0, big, small)
    return out if np.ndim(a) else float(out)


def log_required_power_w(bits: ArrayLike, gain: ArrayLike, slot_s: float, bandwidth_hz: float,
                         noise_w: float) -> ArrayLike:
    """``ln`` of the minimum power (W) carrying ``bits`` in one slot: ``ln σ² − ln g + ln expm1(a)``.

    ``+inf`` where the gain is 0 (and bits > 0), ``−inf`` where bits = 0 (no power needed).
    """
    a = np.asarray(snr_exponent(bits, slot_s, bandwidth_hz), dtype=np.float64)
    g = np.asarray(gain, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        log_g = np.log(g)
        out = math.log(noise_w) - log_g + log_expm1(a)
    # 0 bits need no power even on a dead channel (−inf − (−inf) would be NaN).
    out = np.where(a == 0.0, -np.inf, np.where(g == 0.0, np.inf, out))
    return out if (np.ndim(bits) or np.ndim(gain)) else float(out)


def required_power_w(bits: ArrayLike, gain: ArrayLike, slot_s: float, bandwidth_hz: float,
                     noise_w: float) -> ArrayLike:
    """Minimum transmit power (W) so that ``slot_s·R(p) ≥ bits``: ``(σ²/g)·(2^{bits/(τB)} − 1)``.

    Args:
        bits: payload of the slot (bits), scalar or array.
        gain: channel power gain ``|h|²`` (dimensionless, ≥ 0), scalar or array.
        slot_s: slot length τ (s). bandwidth_hz: B (Hz). noise_w: σ² (W).

    Returns:
        Power in watts (float or float64 array); ``inf`` where not representable (> 1e300 W) or
        gain 0 — the slot cannot carry ``bits``. Never NaN for valid (non-negative, finite) inputs.
    """
    log_p = np.asarray(log_required_power_w(bits, gain, slot_s, bandwidth_hz, noise_w))
    with np.errstate(over="ignore"):
        out = np.where(log_p > LOG_FLOAT_MAX, np.inf, np.exp(np.minimum(log_p, LOG_FLOAT_MAX)))
    return out if (np.ndim(bits) or np.ndim(gain)) else float(out)


def energy_j(power_w: ArrayLike, slot_s: float) -> float:
    """Energy (J) of transmitting ``power_w`` (W, scalar or per-slot array) for one slot ``slot_s`` each."""
    return float(slot_s * math.fsum(np.atleast_1d(np.asarray(power_w, dtype=np.float64)).tolist()))


def rate_bps(power_w: ArrayLike, gain: ArrayLike, bandwidth_hz: float, noise_w: float) -> ArrayLike:
    """Shannon rate ``B·log2(1 + g·p/σ²)`` in bits/s (``log1p`` for accuracy at low SNR)."""
    p = np.asarray(power_w, dtype=np.float64)
    g = np.asarray(gain, dtype=np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        snr = g * p / noise_w
        out = bandwidth_hz * np.log1p(np.where(np.isfinite(snr), snr, np.finfo(np.float64).max)) / LN2
    out = np.where((g == 0.0) | (p == 0.0), 0.0, out)
    return out if (np.ndim(power_w) or np.ndim(gain)) else float(out)


def slot_bits(power_w: ArrayLike, gain: ArrayLike, slot_s: float, bandwidth_hz: float,
              noise_w: float) -> ArrayLike:
    """Bits carried in one slot: ``τ·R(p)``."""
    r = rate_bps(power_w, gain, bandwidth_hz, noise_w)
    return slot_s * np.asarray(r) if np.ndim(r) else slot_s * float(r)


@dataclass(frozen=True)
class LinkBudget:
    """Uplink parameters in SI units (distances in metres in ``map``)."""

    bandwidth_hz: float = BANDWIDTH_HZ
    noise_w: float = NOISE_W
    pathloss_db_at_1m: float = PATHLOSS_DB_AT_1M
    pathloss_exponent: float = PATHLOSS_EXPONENT
    rician_k: float = RICIAN_K
    server_position_m: tuple[float, float] = (10.0, 0.0)
    channel_seed: int = 7
    min_distance_m: float = 1.0

    def distance_m(self, position_xy: np.ndarray | tuple[float, float] | None) -> float:
        """Robot–server distance (≥ ``min_distance_m``; the server position itself if unknown)."""
        if position_xy is None:
            return max(self.min_distance_m, math.hypot(*self.server_position_m))
        dx = float(position_xy[0]) - self.server_position_m[0]
        dy = float(position_xy[1]) - self.server_position_m[1]
        return max(self.min_distance_m, math.hypot(dx, dy))

    def mean_gain(self, position_xy: np.ndarray | tuple[float, float] | None) -> float:
        """Expected gain E|h|² = ρ0·d^−α at ``position_xy`` (the Rician small-scale power has mean 1)."""
        model = ChannelModel(self.pathloss_db_at_1m, self.pathloss_exponent, self.rician_k, seed=None)
        return float(model.pathloss(np.array([self.distance_m(position_xy)]))[0])

    def gain(self, slot: int, position_xy: np.ndarray | tuple[float, float] | None) -> float:
        """Channel power gain g = |h|² of slot index ``slot`` (≥ 0) at ``position_xy`` (robot x, y in map).

        The fading draw is seeded by (``channel_seed``, ``slot``): the simulator passes the index since
        the round started, so every run with one seed sees the same small-scale fading.
        """
        model = ChannelModel(self.pathloss_db_at_1m, self.pathloss_exponent, self.rician_k,
                             seed=[self.channel_seed, int(slot)])  # type: ignore[arg-type]
        return float(model.gains(np.array([self.distance_m(position_xy)]))[0])

    def required_power_w(self, bits: float, gain: float, slot_s: float, bandwidth_hz: float,
                         noise_w: float) -> float:
        """Minimum power to carry ``bits`` in one slot (:func:`required_power_w`)."""
        return float(required_power_w(bits, gain, slot_s, bandwidth_hz, noise_w))
