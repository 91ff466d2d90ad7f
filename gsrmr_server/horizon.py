"""Online planning over a receding horizon (pure): predict poses, losses and gains, then solve P_GS.

The scheduler node calls :meth:`OnlinePlanner.plan` at every replan. The planner

1. predicts the robot's poses for the next ``horizon`` slots by advancing along the scene's route loop
   at the nominal speed from the point nearest to the current pose (:class:`RoutePredictor`);
2. predicts L_t there: with ``loss_model="burst"`` (the node's default) by
   :class:`~gsrmr_server.loss_predictor.LossPredictor` — the seed map of the mapping round × an online
   correction that follows measured bursts and decays back, × a margin learned from its own errors
   (``margin_quantile``); with ``"map"`` by the seed map × a quantile of measured/predicted
   (``calibrate``, ``calibration_quantile``; the earlier model, kept for comparison);
3. takes g_t from the channel's statistics: the expected gain ρ0·d^−α at the predicted robot–server
   distance (:meth:`~gsrmr_common.link_model.LinkBudget.mean_gain`) — what a deployment knows. With
   ``oracle_channel`` it takes the simulator's future realisation instead (the fading of each slot's
   index since the round started, which it learns from the radio's samples): an upper bound for
   comparison, not deployable;
4. sets the loss budget so that the mean loss meets ``L_th·(1 − loss_margin)``: an image slot leaves
   ``image_slot_loss`` J (its JPEG), so Σ x·J + (1 − x)·L ≤ cap becomes the knapsack Σ (1 − x)(L − J) ≤
   cap − n·J. The booked slots (what the robot did — its ledger — at the pose it reported) count with
   their *estimated* loss: J for an image, for a key the burst model's estimate from the measurements
   around it (re-estimated while they arrive; frozen after ``refine_slots``). With ``round_slots`` T the
   budget is the round's: the round starts at the first reported pose > ``round_start_m`` from where the
   robot stood, and cap = L_th·T − Σ booked in the round, split at the round's end (what follows gets a
   fresh budget); without, a running mean over every booked slot: cap = L_th·(n_done + H) − Σ booked;
5. solves with :func:`gsrmr_server.scheduling.solve` and returns the schedule for the wire;
6. with ``in_slot_decision`` (and no oracle), adds per-slot gain thresholds
   (:mod:`gsrmr_server.slot_price`): the robot then sends an image only when the gain it measures in
   the slot is at least the threshold, the price chosen so that the expected loss meets the same budget;
   ``explore_image_fraction`` and ``probe_gap_slots`` lower the threshold (an image in the best fades
   always; after ``probe_gap_slots`` slots without an image, in any fade at or above the median one) so
   that the measurements that find a change keep coming.

It also watches drift: every measured loss is compared with what the planner predicted for that
slot; when the mean absolute error of the last ``drift_window`` samples exceeds ``drift_threshold`` a
replan is due. Why the node's settings: ``docs/scheduling.md`` ("The live loop").
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
import math
import time

import numpy as np

from gsrmr_common.route import LoopPath
from gsrmr_common.wire import ScheduleMsg
from gsrmr_server.loss_map import LossMap
from gsrmr_server.loss_predictor import LossPredictor
from gsrmr_server.slot_price import cap_expected_images, gain_thresholds, rician_power_samples, saving_coefficient_j

# ledger rows the uplink's carrying capacity is judged on (OnlinePlanner.link_image_cap): 5 s of slots
LINK_WINDOW_SLOTS = 50
# images that must have been composed for the uplink to count as delivering them in their slots: the last
# DELIVERY_WINDOW_IMAGES the robot sent, older than DELIVERY_GRACE_SLOTS (the server's loss sample follows its
# slot by ~1 slot); fewer than MIN_DELIVERY_RATIO of them composed → the plan only probes (PROBE_IMAGE_FRACTION)
DELIVERY_WINDOW_IMAGES = 8
DELIVERY_GRACE_SLOTS = 10
MIN_DELIVERY_RATIO = 0.5
PROBE_IMAGE_FRACTION = 3 / LINK_WINDOW_SLOTS
LOSS_MODELS = ("map", "burst")  # L_t predictors: calibrated seed map / burst model (gsrmr_server.loss_predictor)


class RoutePredictor:
    """Future poses along a closed route at a nominal speed."""

    def __init__(self, waypoints: np.ndarray | list, speed_mps: float) -> None:
        if not (speed_mps > 0 and math.isfinite(speed_mps)):
            raise ValueError("route speed must be > 0")
        self.path = LoopPath(waypoints)
        self.speed_mps = float(speed_mps)
        self._dense_s = np.linspace(0.0, self.path.length_m, max(200, int(self.path.length_m / 0.01)),
                                    endpoint=False)
        self._dense_xy = self.path.points_at(self._dense_s)

    def nearest_s(self, a_m: float, b_m: float) -> float:
        """Arc length of the route point nearest to (a, b)."""
        d2 = (self._dense_xy[:, 0] - a_m) ** 2 + (self._dense_xy[:, 1] - b_m) ** 2
        return float(self._dense_s[int(np.argmin(d2))])

    def predict(self, pose: tuple[float, float, float] | None, n_slots: int, slot_s: float) -> np.ndarray:
        """n_slots×3 poses (a_m, b_m, theta_rad) for the next slots (route start if pose is None)."""
        s0 = 0.0 if pose is None else self.nearest_s(pose[0], pose[1])
        s = s0 + self.speed_mps * slot_s * np.arange(1, n_slots + 1)
        xy = self.path.points_at(s)
        theta = np.array([self.path.heading_at(v) for v in s])
        return np.column_stack([xy, theta])


@dataclass
class PlanResult:
    """A solved horizon: the wire schedule plus what the reply of /gsrmr/replan reports."""

    schedule: ScheduleMsg
    method: str
    images: int
    energy_j: float
    mean_predicted_loss: float
    budget: float
    feasible: bool
    solve_time_s: float
    predicted_loss: np.ndarray
    notes: list[str] = field(default_factory=list)


class OnlinePlanner:
    """Receding-horizon GSCLO planner with budget carry-over and drift detection."""

    def __init__(self, predictor: RoutePredictor, loss_map: LossMap, link, *, slot_s: float, image_bits: float,
                 pose_bits: float, loss_threshold: float, horizon: int, method: str = "exact",
                 options: dict | None = None, drift_threshold: float = 0.02, drift_window: int = 5,
                 loss_margin: float = 0.0, oracle_channel: bool = False, in_slot_decision: bool = False,
                 rician_k: float = 1.0, calibrate: bool = False, explore_image_fraction: float = 0.0,
                 calibration_window: int = 30, calibration_quantile: float = 0.75, loss_model: str = "burst",
                 image_slot_loss: float = 0.0, burst_time_constant_slots: float = 25.0,
                 margin_quantile: float = 0.75, refine_slots: int = 300, probe_gap_slots: int = 0,
                 round_slots: int = 0, round_start_m: float = 0.05) -> None:
        if loss_model not in LOSS_MODELS:
            raise ValueError(f"loss_model must be one of {LOSS_MODELS}, got {loss_model!r}")
        if not (image_slot_loss >= 0 and math.isfinite(image_slot_loss)):
            raise ValueError("image_slot_loss must be a finite loss >= 0")
        self.predictor, self.loss_map, self.link = predictor, loss_map, link
        self.loss_model = loss_model
        self.image_slot_loss = float(image_slot_loss)
        # the burst model reads a frozen copy of the seed; self.loss_map keeps learning (saved for later runs)
        self.loss_predictor = LossPredictor(LossMap.from_json(loss_map.to_json()),
                                            burst_time_constant_slots=burst_time_constant_slots,
                                            margin_quantile=margin_quantile, margin_window=calibration_window)
        self.refine_slots = int(refine_slots)
        self.probe_gap_slots = int(probe_gap_slots)
        self.round_slots, self.round_start_m = int(round_slots), float(round_start_m)
        self._round_start: int | None = None  # first slot the reported pose left its start (round mode)
        self._home: tuple[float, float] | None = None
        self._round_frozen, self._round_frozen_n = 0.0, 0
        self._last_image_slot: int | None = None
        self._done: deque[tuple[int, int, tuple[float, float, float] | None]] = deque()  # (slot, x, pose)
        self._frozen_spent = 0.0
        self.oracle_channel = bool(oracle_channel)
        self.round_start_slot: int | None = None  # learnt from the radio's samples (oracle only)
        self.in_slot_decision = bool(in_slot_decision)
        self._fading = rician_power_samples(rician_k)
        self._actual_x: dict[int, int] = {}  # slot → what the robot did (its ledger)
        # (slot, x, held_back, uplink_rate_bps, image_bits) of the last LINK_WINDOW_SLOTS ledger rows
        self._link_window: deque[tuple[int, int, int, float, float]] = deque(maxlen=LINK_WINDOW_SLOTS)
        self.last_image_cap: float | None = None  # the image fraction the last plan was held to (None: no cap)
        self._sent_images: deque[int] = deque(maxlen=4 * DELIVERY_WINDOW_IMAGES)  # slots the robot sent an image in
        self._sampled_slots: deque[int] = deque(maxlen=1000)  # slots the server measured L_t in (image composed)
        self.last_price: float | None = None  # λ of the last plan (J per unit of loss)
        self.calibrate = bool(calibrate)
        self.explore_image_fraction = float(explore_image_fraction)
        self._ratios: deque[float] = deque(maxlen=int(calibration_window))  # measured / map-predicted L
        self.calibration_quantile = float(calibration_quantile)
        self.slot_s, self.image_bits, self.pose_bits = slot_s, image_bits, pose_bits
        self.loss_threshold, self.horizon, self.method = loss_threshold, horizon, method
        self.options = dict(options or {})
        self.drift_threshold, self.drift_window = drift_threshold, drift_window
        self.loss_margin = loss_margin
        self._predicted: dict[int, float] = {}
        self._reported: dict[int, tuple[float, float, float]] = {}  # slot → pose (a_m, b_m, theta_rad) keyed
        self._errors: deque[float] = deque(maxlen=drift_window)
        self.slots_done = 0
        self._accounted_up_to: int | None = None
        self._active: ScheduleMsg | None = None
        self.seq = 0

    def account_until(self, slot: int) -> None:
        """Book the slots of the active schedule that ended before ``slot``: what the robot did (its ledger,
        else the plan) and the pose it reported (else none)."""
        sched = self._active
        if sched is None:
            return
        start = sched.first_slot if self._accounted_up_to is None else self._accounted_up_to + 1
        for k in range(start, slot):
            entry = sched.lookup(k)
            if entry is None:
                continue
            self.slots_done += 1
            self._done.append((k, self._actual_x.pop(k, entry[0]), self._reported.pop(k, None)))
            self._accounted_up_to = k
        while len(self._done) > self.refine_slots:  # old slots: their estimate will not change any more
            done = self._done.popleft()
            loss = self._slot_loss(*done)
            self._frozen_spent += loss
            if self._round_start is not None and done[0] >= self._round_start:
                self._round_frozen += loss
                self._round_frozen_n += 1
        for old in [k for k in self._reported if k < slot - 1000]:
            del self._reported[old]

    def _slot_loss(self, slot: int, x: int, pose: tuple[float, float, float] | None) -> float:
        """Estimated MR loss a booked slot left: ``image_slot_loss`` for an image; for a key, the burst
        model's estimate from the measurements around it (or the calibrated map at the reported pose), the
        plan's prediction without a reported pose."""
        if x:
            return self.image_slot_loss
        if pose is None:
            return self._predicted.get(slot, self.loss_map.prior)
        if self.loss_model == "burst":
            return self.loss_predictor.estimate(slot, pose)
        return self.loss_map.predict(*pose) * self.calibration

    @property
    def loss_spent(self) -> float:
        """Σ estimated MR loss of the booked slots (recent ones re-estimated as measurements arrive)."""
        return self._frozen_spent + math.fsum(self._slot_loss(*d) for d in self._done)

    def record_action(self, slot: int, x: int, held_back: int = 0, uplink_rate_bps: float = math.nan,
                      image_bits: float = math.nan) -> None:
        """What the robot did in ``slot`` (1 = image), from its ledger: key slots are charged by it.
        ``held_back`` = 1: an image was asked for and the robot sent the key, its last image still queued;
        ``uplink_rate_bps``: the robot's estimate of the uplink throughput (from its image acknowledgements);
        ``image_bits``: the size of this slot's frame as a JPEG."""
        self._actual_x[slot] = int(x)
        self._link_window.append((int(slot), int(x), int(held_back), float(uplink_rate_bps), float(image_bits)))
        if x:
            self._sent_images.append(int(slot))
        if x and (self._last_image_slot is None or slot > self._last_image_slot):
            self._last_image_slot = slot
        for old in [k for k in self._actual_x if k < slot - 1000]:
            del self._actual_x[old]

    def link_image_cap(self) -> float | None:
        """The fraction of slots that may plan an image because the uplink carries no more, or None (it carries
        at least one per slot): τ · R / b, with R the median of the robot's throughput estimates and b the median
        JPEG size over its last ``LINK_WINDOW_SLOTS`` ledger rows. R comes from how long each image took to be
        acknowledged (:mod:`gsrmr_robot.uplink_backlog`): it measures the link, not the plan, so a cap does not
        ratchet itself down (a cap from the images the link carried would: fewer planned, fewer carried). When,
        on such a slow link, most recent images were not composed in their slot (:meth:`image_delivery_ratio` <
        ``MIN_DELIVERY_RATIO``: they arrive late), the cap is ``PROBE_IMAGE_FRACTION``: a few images keep
        measuring the link. Images lost to an outage do not count (the link is not slow once it is back)."""
        rates = [r for *_, r, _ in self._link_window if math.isfinite(r) and r > 0]
        sizes = [b for *_, b in self._link_window if math.isfinite(b) and b > 0]
        cap = self.slot_s * float(np.median(rates)) / float(np.median(sizes)) if rates and sizes else 1.0
        delivered = self.image_delivery_ratio()
        # only on a link measurably slower than an image per slot: images lost to an outage (the rate estimate
        # takes no sample from them) say nothing about the link once it is back
        if cap < 1.0 and delivered is not None and delivered < MIN_DELIVERY_RATIO:
            # the images the link carries arrive after their slot was composed (a link this slow takes longer
            # than the server waits): they cost energy and change nothing — only probe until they arrive again
            cap = min(cap, PROBE_IMAGE_FRACTION)
        return cap if cap < 1.0 else None

    def image_delivery_ratio(self) -> float | None:
        """Of the last ``DELIVERY_WINDOW_IMAGES`` images the robot sent (older than ``DELIVERY_GRACE_SLOTS``), the
        fraction the server composed in their slot (its loss sample came); None before the server has sent any
        sample (it may not measure) or with fewer than 2 such images."""
        if not self._sampled_slots or not self._link_window:
            return None
        newest = max(s for s, *_ in self._link_window)
        settled = [s for s in self._sent_images if s <= newest - DELIVERY_GRACE_SLOTS][-DELIVERY_WINDOW_IMAGES:]
        if len(settled) < 2:
            return None
        sampled = set(self._sampled_slots)
        return sum(s in sampled for s in settled) / len(settled)

    def images_held_back(self) -> int:
        """Images the robot held back in its last ``LINK_WINDOW_SLOTS`` ledger rows (its last one still queued)."""
        return sum(h for _, _, h, _, _ in self._link_window)

    def record_pose(self, slot: int, a_m: float, b_m: float, theta_rad: float) -> None:
        """The pose the robot reported for ``slot`` (its pose key): key slots are charged at it."""
        self._reported[slot] = (a_m, b_m, theta_rad)
        if self.round_slots <= 0:
            return
        if self._round_start is not None and slot >= self._round_start + self.round_slots:
            self._round_start, self._home = None, None  # the round is over: the next one starts on motion
        if self._round_start is None:
            if self._home is None:
                self._home = (a_m, b_m)
            elif math.hypot(a_m - self._home[0], b_m - self._home[1]) > self.round_start_m:
                self._round_start, self._round_frozen, self._round_frozen_n = slot, 0.0, 0

    def plan(self, now_slot: int, pose: tuple[float, float, float] | None) -> PlanResult:
        """Solve the horizon starting at ``now_slot + 1``."""
        from gsrmr_server.scheduling import Problem, solve

        self.account_until(now_slot + 1)
        first = now_slot + 1
        poses = self.predictor.predict(pose, self.horizon, self.slot_s)
        slots = np.arange(first, first + self.horizon)
        if self.loss_model == "burst":
            raw = self.loss_predictor.predict(slots, poses)
            losses = raw * self.loss_predictor.margin
        else:
            raw = losses = self.loss_map.predict_many(poses) * self.calibration
        gains = self.gains(first, poses)
        target = self.loss_threshold * (1.0 - self.loss_margin)
        # an image slot leaves image_slot_loss J (its JPEG): Σ x·J + (1−x)·L ≤ cap ⇔ Σ (1−x)(L − J) ≤ cap − n·J
        j = self.image_slot_loss
        key_cost = np.maximum(losses - j, 0.0)
        explore = self._explore(slots)
        blocks = []  # (slice of the horizon, Σ loss allowed over it)
        remaining = self.round_remaining(first)
        if remaining is not None and remaining <= self.horizon:  # the round ends inside the horizon
            n_round, spent_round = self.round_booked()
            blocks.append((slice(0, remaining), target * (n_round + remaining) - spent_round))
            if remaining < self.horizon:  # what follows the round: a fresh budget
                blocks.append((slice(remaining, self.horizon), target * (self.horizon - remaining)))
        elif remaining is not None:
            n_round, spent_round = self.round_booked()
            blocks.append((slice(0, self.horizon), target * (n_round + self.horizon) - spent_round))
        else:
            blocks.append((slice(0, self.horizon), target * (self.slots_done + self.horizon) - self.loss_spent))
        x = np.zeros(self.horizon, np.int8)
        power = np.zeros(self.horizon)
        image_cap = self.link_image_cap()
        self.last_image_cap = image_cap
        thresholds = np.full(self.horizon, np.inf) if self.in_slot_decision and not self.oracle_channel else None
        energy, feasible, solve_time, notes, budget = 0.0, True, 0.0, [], None
        for part, cap in blocks:
            n = part.stop - part.start
            block_budget = max(0.0, (cap - j * n) / n)
            budget = block_budget if budget is None else budget
            problem = Problem(slot_s=self.slot_s, image_bits=self.image_bits, pose_bits=self.pose_bits,
                              bandwidth_hz=self.link.bandwidth_hz, noise_w=self.link.noise_w,
                              channel_gain=gains[part], gs_loss=key_cost[part], loss_threshold=block_budget)
            t0 = time.perf_counter()
            result = solve(problem, self.method, **self.options)
            solve_time += time.perf_counter() - t0
            notes += list(getattr(result, "notes", []) or [])
            x[part] = np.asarray(result.x, dtype=np.int8)
            power[part] = np.nan_to_num(np.asarray(result.power_w, dtype=np.float64), nan=0.0, posinf=0.0)
            energy += float(result.energy_j)
            feasible = feasible and bool(result.feasible)
            if thresholds is not None:
                coeff = saving_coefficient_j(self.image_bits, self.pose_bits, self.slot_s, self.link.bandwidth_hz,
                                             self.link.noise_w)
                thresholds[part], price, _ = gain_thresholds(gains[part], key_cost[part], block_budget * n, coeff,
                                                             self._fading, explore[part])
                if image_cap is not None:  # the link carries fewer images than the budget asks: the best of them
                    thresholds[part], scale = cap_expected_images(thresholds[part], gains[part], self._fading,
                                                                  image_cap * n)
                    price *= scale
                if part.start == 0:
                    self.last_price = price
            elif image_cap is not None and x[part].sum() > image_cap * n:  # keep those saving most loss per joule
                keep = np.argsort(-(key_cost[part] * gains[part] * x[part]))[:int(image_cap * n)]
                capped = np.zeros(n, np.int8)
                capped[keep] = x[part][keep]
                x[part] = capped
                notes.append(f"images capped at {image_cap:.2f} of slots: the uplink carries no more")
        self.seq += 1
        schedule = ScheduleMsg(first, self.slot_s, self.seq, x, power, thresholds)
        for i in range(self.horizon):
            self._predicted[first + i] = float(raw[i])
        for old in [k for k in self._predicted if k < now_slot - 1000]:
            del self._predicted[old]
        self._active = schedule
        self._accounted_up_to = now_slot
        return PlanResult(schedule, self.method, int(x.sum()), energy, float(np.mean(losses * (1 - x) + j * x)),
                          float(budget), feasible, solve_time, losses, notes)

    def _explore(self, slots: np.ndarray) -> np.ndarray:
        """Per-slot exploration fraction of the in-slot rule (see ``probe_gap_slots``)."""
        explore = np.full(slots.shape, self.explore_image_fraction)
        if self.calibrate and self._samples_held() < 3:  # the seed map may be far off: measure first
            explore = np.maximum(explore, 0.5)
        if self.probe_gap_slots > 0:  # no image for a while: accept ever poorer fades, up to the median one
            last = self._last_image_slot if self._last_image_slot is not None else int(slots[0]) - 1
            explore = np.maximum(explore, 0.5 * np.minimum(1.0, (slots - last) / self.probe_gap_slots))
        return explore

    # ------------------------------------------------------------------ rounds
    def round_remaining(self, first: int) -> int | None:
        """Slots of the current round from ``first`` on (None outside a round or without ``round_slots``)."""
        if self.round_slots <= 0 or self._round_start is None:
            return None
        left = self._round_start + self.round_slots - first
        return left if left > 0 else None

    def round_booked(self) -> tuple[int, float]:
        """(slots booked since the round started, their estimated Σ loss)."""
        start = self._round_start if self._round_start is not None else 0
        inside = [d for d in self._done if d[0] >= start]
        return (self._round_frozen_n + len(inside),
                self._round_frozen + math.fsum(self._slot_loss(*d) for d in inside))

    def _samples_held(self) -> int:
        return self.loss_predictor.samples if self.loss_model == "burst" else len(self._ratios)

    def gains(self, first: int, poses: np.ndarray) -> np.ndarray:
        """g_t for slots ``first …`` at the predicted ``poses`` (see the module docstring, step 3)."""
        if not self.oracle_channel or self.round_start_slot is None:
            return np.array([self.link.mean_gain(poses[i, :2]) for i in range(len(poses))])
        out = []
        for i in range(len(poses)):
            k = first + i - self.round_start_slot
            out.append(self.link.gain(k if k >= 0 else first + i, poses[i, :2]))
        return np.array(out)

    @property
    def calibration(self) -> float:
        """Factor on the map's predictions: the ``calibration_quantile`` (0.75) of measured / predicted L over
        the last ``calibration_window`` image slots (1 until 3 samples; clipped to [0.25, 4]). The seed map
        comes from the mapping round, whose frames trained the model: it under-predicts a round with
        changes and odometry error, by a factor the run measures; taking an upper quantile of the ratios
        rather than their median is the safety margin learned from the run's own prediction errors."""
        if not self.calibrate or len(self._ratios) < 3:
            return 1.0
        return float(np.clip(np.quantile(self._ratios, self.calibration_quantile), 0.25, 4.0))

    def observe(self, slot: int, a_m: float, b_m: float, theta_rad: float, loss: float) -> bool:
        """An image slot's measured L_t (the server's loss sample); True when the prediction error says a
        replan is due."""
        self._sampled_slots.append(int(slot))
        predicted = self._predicted.get(slot)
        if self.loss_model == "burst":
            self.loss_predictor.observe(slot, (a_m, b_m, theta_rad), loss, predicted)
        elif self.calibrate and math.isfinite(loss):
            raw = self.loss_map.predict(a_m, b_m, theta_rad)
            if raw > 1e-4:
                self._ratios.append(loss / raw)
        self.loss_map.add(a_m, b_m, theta_rad, loss)
        if predicted is None or not math.isfinite(loss):
            return False
        self._errors.append(abs(loss - predicted))
        return len(self._errors) >= self.drift_window and float(np.mean(self._errors)) > self.drift_threshold

    def clear_drift(self) -> None:
        """Forget past prediction errors (after a replan)."""
        self._errors.clear()

    @property
    def active(self) -> ScheduleMsg | None:
        """The schedule most recently planned."""
        return self._active
