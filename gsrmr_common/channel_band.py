"""How far a measured channel gain may lie from the path-loss prediction (pure math, no numpy): the Rician band.

The link model (:mod:`gsrmr_common.channel`) draws g = ρ0·d^−α·X, X the unit-mean small-scale power of a Rician
channel of K-factor K: ``2(K+1)·X`` is a non-central χ² with 2 degrees of freedom and non-centrality ``2K``, whose
CDF (:func:`rician_power_cdf`, a Poisson mixture of regularised gamma functions, computed from whichever side keeps
its precision) bounds a clean ratio ``g / ḡ(d)`` per sample; the median of the last ``window`` ratios leaves its
quantile band only when ⌈w/2⌉ of w samples fall beyond one quantile (:func:`median_alarm_probability`).
:class:`GainBand` applies both, widened for the robot's odometry position error; the bands and their false-alarm
rates: docs/security.md, "Plausibility, even from the right writer".
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
import math

#: Per-sample false-alarm probability of each tail of the band.
PER_SAMPLE_ALARM = 1e-7
#: Samples in the lasting-bias test and the quantile its median must stay within.
BIAS_WINDOW = 25
BIAS_QUANTILE = 0.05


def _poisson_weights(mean: float, tol: float = 1e-18) -> list[float]:
    """Poisson(mean) probabilities j = 0, 1, … until the rest is below ``tol``."""
    out, w, j = [], math.exp(-mean), 0
    total = 0.0
    while True:
        out.append(w)
        total += w
        if j > mean and 1.0 - total < tol:
            return out
        j += 1
        w *= mean / j


def _gamma_p(m: int, x: float) -> float:
    """Regularised lower incomplete gamma P(m, x) for an integer m ≥ 1 (series from i = m: no cancellation)."""
    if x <= 0:
        return 0.0
    term = math.exp(-x + m * math.log(x) - math.lgamma(m + 1))
    total, i = 0.0, m
    while term > 1e-300:
        total += term
        i += 1
        term *= x / i
        if i > m + 10_000:
            break
    return min(1.0, total)


def _gamma_q(m: int, x: float) -> float:
    """Regularised upper incomplete gamma Q(m, x) = e^−x Σ_{i<m} x^i/i! for an integer m ≥ 1."""
    if x <= 0:
        return 1.0
    term, total = math.exp(-x), 0.0
    for i in range(m):
        total += term
        term *= x / (i + 1)
    return min(1.0, total)


def rician_power_cdf(x: float, k_factor: float, *, upper: bool = False) -> float:
    """P(X ≤ x) (or P(X > x) with ``upper``) for the unit-mean Rician power X of K-factor ``k_factor``."""
    if x <= 0:
        return 0.0 if not upper else 1.0
    y2 = (k_factor + 1.0) * x  # half of the χ'² variable 2(K+1)X
    tail = _gamma_q if upper else _gamma_p
    return min(1.0, sum(w * tail(j + 1, y2) for j, w in enumerate(_poisson_weights(k_factor))))


def rician_power_quantile(p: float, k_factor: float) -> float:
    """x with P(X ≤ x) = p (bisection in log x; p in (0, 1))."""
    if not 0.0 < p < 1.0:
        raise ValueError("quantile: p must be in (0, 1)")
    upper = p > 0.5
    target = 1.0 - p if upper else p
    lo, hi = -60.0, 8.0  # ln x
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        value = rician_power_cdf(math.exp(mid), k_factor, upper=upper)
        if (value > target) != upper:
            hi = mid
        else:
            lo = mid
    return math.exp(0.5 * (lo + hi))


def median_alarm_probability(window: int, quantile: float) -> float:
    """P(the median of ``window`` clean samples lies beyond one ``quantile``): at least ⌈w/2⌉ (the middle one) of
    w independent samples fall in a tail of probability ``quantile`` — a binomial tail."""
    need = window // 2 + 1
    return math.fsum(math.comb(window, i) * quantile ** i * (1 - quantile) ** (window - i)
                     for i in range(need, window + 1))


@dataclass
class GainBand:
    """The band a measured gain must lie in around ḡ(d) (module docstring), and the lasting-bias window."""

    k_factor: float
    pathloss_exponent: float
    per_sample_alarm: float = PER_SAMPLE_ALARM
    position_tolerance_m: float = 1.0
    window: int = BIAS_WINDOW
    window_quantile: float = BIAS_QUANTILE
    low: float = field(init=False)  # per-sample band on X (before the position widening)
    high: float = field(init=False)
    median_low: float = field(init=False)
    median_high: float = field(init=False)
    _ratios: deque = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not (0 < self.per_sample_alarm < 0.5 and 0 < self.window_quantile < 0.5):
            raise ValueError("gain band: alarm probabilities must be in (0, 0.5)")
        if self.window < 1 or self.position_tolerance_m < 0:
            raise ValueError("gain band: window ≥ 1 and position_tolerance_m ≥ 0")
        self.low = rician_power_quantile(self.per_sample_alarm, self.k_factor)
        self.high = rician_power_quantile(1 - self.per_sample_alarm, self.k_factor)
        self.median_low = rician_power_quantile(self.window_quantile, self.k_factor)
        self.median_high = rician_power_quantile(1 - self.window_quantile, self.k_factor)
        self._ratios = deque(maxlen=self.window)

    def widening(self, distance_m: float) -> float:
        """((d + δ)/d)^α: how much a position error δ can move ḡ at distance d (≥ 1)."""
        d = max(distance_m, 1e-3)
        return ((d + self.position_tolerance_m) / d) ** self.pathloss_exponent

    def problem(self, gain: float, mean_gain: float, distance_m: float) -> str | None:
        """Why ``gain`` at predicted mean ``mean_gain`` (distance ``distance_m``) is implausible — ``gain_band``
        (this sample) or ``gain_bias`` (the window's median) — or None. Every sample enters the window."""
        ratio = gain / mean_gain
        self._ratios.append(ratio)
        w = self.widening(distance_m)
        if not self.low / w <= ratio <= self.high * w:
            return "gain_band"
        if len(self._ratios) == self.window:
            median = sorted(self._ratios)[self.window // 2]
            if not self.median_low / w <= median <= self.median_high * w:
                return "gain_bias"
        return None

    def false_alarm_per_sample(self) -> float:
        """Clean-sample alarm probability: both per-sample tails plus the window test's two tails (an upper bound
        for the window: its evaluations overlap and are counted as if independent)."""
        return 2 * self.per_sample_alarm + 2 * median_alarm_probability(self.window, self.window_quantile)
