"""L_t predicted along the route and through the round, corrected online: the burst model (pure; the planner's default).

:class:`LossPredictor` works on the log-ratio ℓ = ln(L_measured / L_seed(pose)) of each measured image slot: a level
μ (their median), a burst that decays back to it, key slots estimated between measurements (a step at a scene change
the robot saw), a learned margin, and a bound on one sample's weight — docs/scheduling.md, "The live loop", items 1
and 2; docs/security.md, "Plausibility, even from the right writer". Losses are MR losses of images in [0, 1]; poses
are (a_m, b_m, theta_rad) in ``map``; slots are absolute slot indices.
"""

from __future__ import annotations

from collections import deque
import math

import numpy as np

from gsrmr_common.pose2d import Pose2D
from gsrmr_scheduler.loss_map import LossMap

_FLOOR = 1e-4  # a seed value below this carries no ratio information
#: A measured log-ratio counts at most this far from the level μ (ln 20: bursts of 3–5× pass unclipped).
MAX_LOG_DEVIATION = math.log(20.0)


class LossPredictor:
    """Seed map × an online, decaying correction, with a learned margin (docs/scheduling.md, "The live loop",
    items 1 and 2)."""

    def __init__(self, seed_map: LossMap, *, burst_time_constant_slots: float = 25.0, margin_quantile: float = 0.75,
                 margin_window: int = 30, history_slots: int = 600) -> None:
        if not burst_time_constant_slots > 0:
            raise ValueError("loss predictor: burst_time_constant_slots must be > 0")
        if not 0.0 <= margin_quantile <= 1.0:
            raise ValueError("loss predictor: margin_quantile must be in [0, 1]")
        self.seed_map = seed_map
        self.tau = float(burst_time_constant_slots)
        self.margin_quantile = float(margin_quantile)
        self._samples: deque[tuple[int, float]] = deque(maxlen=int(history_slots))  # (slot, ℓ) by slot
        self._errors: deque[float] = deque(maxlen=int(margin_window))  # measured / predicted-at-plan-time
        self._changes: deque[int] = deque(maxlen=int(history_slots))  # slots the robot's change test fired in

    # ------------------------------------------------------------------ measurements
    def observe(self, slot: int, pose: Pose2D, loss: float,
                predicted: float | None = None) -> None:
        """An image slot's measured L at ``pose``; ``predicted``: what the plan had predicted for it."""
        if not math.isfinite(loss) or loss < 0:
            return
        seed = self.seed_map.predict(*pose)
        if seed > _FLOOR:
            mu = self.level
            ell = min(max(math.log(max(loss, _FLOOR) / seed), mu - MAX_LOG_DEVIATION), mu + MAX_LOG_DEVIATION)
            samples = self._samples
            if samples and slot < samples[-1][0]:  # late sample: keep the deque ordered by slot
                items = sorted([*samples, (slot, ell)])
                samples.clear()
                samples.extend(items[-samples.maxlen:] if samples.maxlen else items)
            else:
                samples.append((slot, ell))
        if predicted is not None and predicted > _FLOOR:
            self._errors.append(loss / predicted)

    def note_change(self, slot: int) -> None:
        """The robot's scene-change test fired on ``slot``'s frame: key slots between the measurements around it
        are estimated as a step there (:meth:`estimate`)."""
        if slot not in self._changes:
            self._changes.append(int(slot))

    @property
    def level(self) -> float:
        """μ: median measured log-ratio (0 before any sample)."""
        return float(np.median([e for _, e in self._samples])) if self._samples else 0.0

    @property
    def margin(self) -> float:
        """The learned factor on predictions: the ``margin_quantile`` of measured / predicted over the last
        ``margin_window`` ratios (1 with fewer than 3; clipped to [1/4, 4])."""
        if len(self._errors) < 3 or self.margin_quantile <= 0:
            return 1.0
        return float(np.clip(np.quantile(self._errors, self.margin_quantile), 0.25, 4.0))

    @property
    def samples(self) -> int:
        """Measurements held."""
        return len(self._samples)

    # ------------------------------------------------------------------ predictions
    @property
    def burst_factor(self) -> float:
        """M = mean of exp(ℓ − μ) over the samples: the factor a slot far from any measurement carries on
        average — bursts included (≥ 1; 1 before any sample)."""
        if not self._samples:
            return 1.0
        mu = self.level
        return float(np.clip(np.mean([math.exp(min(e - mu, 5.0)) for _, e in self._samples]), 1.0, 10.0))

    def log_ratio(self, slots: np.ndarray) -> np.ndarray:
        """ℓ at absolute ``slots`` between measurements: interpolated (ℓ of the nearest sample outside them)."""
        slots = np.asarray(slots, np.float64)
        if not self._samples:
            return np.full(slots.shape, self.level)
        s = np.array([k for k, _ in self._samples], np.float64)
        e = np.array([v for _, v in self._samples], np.float64)
        return np.interp(slots, s, e)

    def ratio_ahead(self, slots: np.ndarray) -> np.ndarray:
        """Expected L/L_seed at future ``slots``: e^μ·(w·e^(ℓ_last − μ) + (1 − w)·M), w = e^(−Δ/τ), Δ the slots
        since the last measurement — the last burst's level fades into the run's average one."""
        slots = np.asarray(slots, np.float64)
        mu, m = self.level, self.burst_factor
        if not self._samples:
            return np.full(slots.shape, math.exp(mu) * m)
        last_slot, last = self._samples[-1]
        w = np.exp(-np.maximum(slots - last_slot, 0.0) / self.tau)
        return math.exp(mu) * (w * math.exp(min(last - mu, 5.0)) + (1.0 - w) * m)

    def predict(self, slots: np.ndarray, poses: np.ndarray) -> np.ndarray:
        """Expected L_t for future ``slots`` at predicted ``poses`` (N×3); the learned margin not included."""
        return self.seed_map.predict_many(poses) * self.ratio_ahead(slots)

    def estimate(self, slot: int, pose: Pose2D) -> float:
        """Best estimate (no margin) of the L a past key slot left, from the measurements around it: ℓ
        interpolated, or a step at the first change the robot found between them: the slots before the change take
        the earlier measurement's ℓ, the slots from it on the later one's."""
        return float(self.seed_map.predict(*pose) * math.exp(self._stepped_log_ratio(slot)))

    def _stepped_log_ratio(self, slot: int) -> float:
        """ℓ at a past ``slot``: the earlier or the later measurement's when a change lies between them and the
        slot, else interpolated (:meth:`log_ratio`)."""
        samples = self._samples
        if self._changes and len(samples) >= 2 and samples[0][0] < slot < samples[-1][0]:
            after = next(i for i, (k, _) in enumerate(samples) if k >= slot)
            before_slot, after_slot = samples[after - 1][0], samples[after][0]
            if after_slot != slot:
                first_change = min((c for c in self._changes if before_slot < c <= after_slot), default=None)
                if first_change is not None:
                    return samples[after - 1][1] if slot < first_change else samples[after][1]
        return float(self.log_ratio(np.array([slot]))[0])
