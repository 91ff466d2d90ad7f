"""L_t predicted along the route and through the round, corrected online (pure; used by the scheduler).

What a deployment knows before round 2 is the **mapping round**: the seed :class:`~gsrmr_scheduler.loss_map.LossMap`
holds the model's MR loss L at the route's poses in the world as it was mapped. Round 2 differs from it in
two ways the seed cannot see, and the sandbox demo shows both (``gsrmr-planner-replay``):

* a steady offset — the reported pose carries odometry error and the model renders a view it was not
  trained on — that makes the measured L about 1.2× the seed's everywhere;
* **bursts**: changes in the world (a light switched, a crate moved, a bag dropped) raise L 3–5× for the
  20–60 slots in which they are in view.

So the predictor works on the log-ratio ℓ = ln(L_measured / L_seed(pose)) that each image slot measures,
and models it as a level μ plus a burst that decays back to it (an Ornstein–Uhlenbeck process in time):

* μ is the median of the measured log-ratios so far (robust to the bursts; 0 before the first sample);
* a future slot t predicts ℓ̂(t) = μ + (ℓ_last − μ)·exp(−(t − t_last)/τ) from the last measurement
  (``burst_time_constant_slots`` τ: how long a change stays in view);
* a past *key* slot (no measurement of its own) is estimated by interpolating ℓ linearly between the
  measurements before and after it — the run's loss spent so far is re-estimated as measurements arrive —
  unless the robot's scene-change test fired in between (:meth:`LossPredictor.note_change`, the ledger's
  ``scene_change``): then the world changed *at* that slot, not gradually, and the slots before it take the
  earlier measurement's ℓ, the slots from it on the later one's (a **step**). Interpolated across a light switched
  off, the slots still lit were charged as half dark, and across one switched on the dark slots as half lit:
  over the 123 recorded runs of ``gsrmr-key-estimates`` the step cuts the spread of the round's booked mean loss
  by a quarter (sd 0.00084 → 0.00063)
  (``docs/scheduling.md``, "Change slots, missed uploads and a 1 % back-off: measured");
* the **safety margin is learned**, conformal style: every measurement is compared with what the planner
  had predicted for that slot when it planned it, and predictions are multiplied by the
  ``margin_quantile`` (0.75) of those measured/predicted ratios over the last ``margin_window`` (30) samples
  (1 until 3 samples; clipped to [1/4, 4]). Instead of a fixed ``loss_margin`` the margin is what the run's
  own errors say it must be: P(measured ≤ margin × predicted) ≈ the quantile on recent slots.

Robust to one writer's outliers: a measured ℓ enters clipped to μ ± ``ln 20`` (:data:`MAX_LOG_DEVIATION`: the
bursts seen are 3–5×, so they pass whole) around the level so far — one sample of 0 or of the metric's maximum
moves the burst prediction by at most 20× for τ slots and the level (a median) hardly at all —, while a lasting
change moves the median within half the history. The scheduler takes one sample per slot, after its plausibility
checks (:class:`gsrmr_common.plausibility.LossSampleCheck`).

Loss values are the MR loss ``(1 − λ)·L1 + λ·(1 − SSIM)`` (λ = 0.2) of images in [0, 1]; poses are
(a_m, b_m, theta_rad) in ``map``; slots are absolute slot indices.
"""

from __future__ import annotations

from collections import deque
import math

import numpy as np

from gsrmr_scheduler.loss_map import LossMap

_FLOOR = 1e-4  # a seed value below this carries no ratio information
#: A measured log-ratio counts at most this far from the level μ (ln 20: bursts of 3–5× pass unclipped).
MAX_LOG_DEVIATION = math.log(20.0)


class LossPredictor:
    """Seed map × an online, decaying correction, with a learned margin (see the module docstring)."""

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
    def observe(self, slot: int, pose: tuple[float, float, float], loss: float,
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
        are estimated as a step there (module docstring)."""
        if slot not in self._changes:
            self._changes.append(int(slot))

    @property
    def level(self) -> float:
        """μ: median measured log-ratio (0 before any sample)."""
        return float(np.median([e for _, e in self._samples])) if self._samples else 0.0

    @property
    def margin(self) -> float:
        """The learned factor on predictions (the ``margin_quantile`` of measured/predicted)."""
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

    def estimate(self, slot: int, pose: tuple[float, float, float]) -> float:
        """Best estimate (no margin) of the L a past key slot left, from the measurements around it: ℓ
        interpolated, or a step at the first change the robot found between them (module docstring)."""
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
