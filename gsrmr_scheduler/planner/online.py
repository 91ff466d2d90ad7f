"""The receding-horizon planner (pure): :class:`OnlinePlanner` composes the steps of one replan
(:meth:`OnlinePlanner.plan`). Design, and why the node's settings: docs/scheduling.md, "The live loop".
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
import time

import numpy as np

from gsrmr_common.link_model import LinkBudget
from gsrmr_common.pose2d import Pose2D
from gsrmr_common.wire import ScheduleMsg
from gsrmr_scheduler.loss_map import LossMap
from gsrmr_scheduler.planner.budget import LossBudget
from gsrmr_scheduler.planner.config import PlannerConfig
from gsrmr_scheduler.planner.drift import DriftMonitor
from gsrmr_scheduler.planner.fix_age import FixAge
from gsrmr_scheduler.planner.forecast import LossForecast, SlotLossModel
from gsrmr_scheduler.planner.link_cap import LinkCap, cap_planned_images
from gsrmr_scheduler.planner.pricing import InSlotPricing
from gsrmr_scheduler.planner.route import RoutePredictor
from gsrmr_scheduler.problem import Problem
from gsrmr_scheduler.slot_price import saving_coefficient_j
from gsrmr_scheduler.solve import solve


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


@dataclass
class _Blocks:
    """The per-block solutions of one plan, assembled over the horizon."""

    x: np.ndarray
    power_w: np.ndarray
    thresholds: np.ndarray | None
    energy_j: float = 0.0
    feasible: bool = True
    solve_time_s: float = 0.0
    notes: list[str] = field(default_factory=list)


class OnlinePlanner:
    """Receding-horizon GSCLO planner: plans the next ``horizon_slots`` slots from what a deployment knows.

    One :class:`~gsrmr_scheduler.planner.config.PlannerConfig` and the objects that own one concept each (route,
    L_t forecast, loss budget, link cap, in-slot pricing, drift test: docs/scheduling.md, "The planner's code").
    Between plans it takes in what happened: the robot's ledger (:meth:`record_action`), its pose keys
    (:meth:`record_pose`), what the server composed each slot from (:meth:`record_composed`) and the server's loss
    samples (:meth:`observe`, which also says when the prediction drifted enough for a replan).

    Args:
        config: every knob (losses are MR losses, the scale of ``loss_threshold``; slots of τ = ``config.slot_s``
            seconds; payloads in bits).
        route: predicts the robot's poses (a_m, b_m, theta_rad) in ``map`` along the route.
        loss_map: the seed loss map; it keeps learning from the measured samples (:attr:`loss_map`).
        link: the uplink's budget: bandwidth (Hz), noise σ² (W), path loss and Rician K; its gains g_t are
            dimensionless power gains ``|h|²``.
        loss_model: replaces the burst model (a study's hindsight bound,
            :class:`gsrmr_sim.replay.TruthLossPredictor`); None: the burst model.

    Raises:
        ValueError: ``loss_model`` given with ``config.trust_loss_map``.

    Example:
        A planner on a square route, planning the first 100 slots from the route's start::

            from gsrmr_common.link_model import LinkBudget
            from gsrmr_scheduler.loss_map import LossMap
            from gsrmr_scheduler.planner import OnlinePlanner, PlannerConfig, RoutePredictor

            route = RoutePredictor([(0, 0), (2, 0), (2, 2), (0, 2)], speed_mps=0.2)
            config = PlannerConfig(loss_threshold=0.03, horizon_slots=100)
            planner = OnlinePlanner(config, route, LossMap(), LinkBudget())
            result = planner.plan(now_slot=0, pose=(0.0, 0.0, 0.0))
    """

    def __init__(self, config: PlannerConfig, route: RoutePredictor, loss_map: LossMap, link: LinkBudget,
                 *, loss_model: SlotLossModel | None = None) -> None:
        self.config = config
        self.route, self.link = route, link
        self.forecast = LossForecast(loss_map, trust_loss_map=config.trust_loss_map,
                                     sample_offset=config.loss_sample_offset,
                                     burst_time_constant_slots=config.burst_time_constant_slots,
                                     margin_quantile=config.margin_quantile,
                                     margin_window_samples=config.margin_window_samples, model=loss_model)
        self.budget = LossBudget(self.forecast.key_loss, image_slot_loss=config.image_slot_loss,
                                 round_slots=config.round_slots, round_start_m=config.round_start_m,
                                 refine_slots=config.refine_slots,
                                 level_extra_loss=(0.0, config.half_level_extra_loss,
                                                   config.quarter_level_extra_loss))
        self.link_cap = LinkCap(config.slot_s)
        self.pricing = InSlotPricing(link.rician_k, explore_image_fraction=config.explore_image_fraction,
                                     probe_gap_slots=config.probe_gap_slots,
                                     startup_explore_samples=config.startup_explore_samples)
        self.drift = DriftMonitor(config.drift_threshold, config.drift_window_samples)
        self.fix_age = FixAge(config.stale_fix_m)
        self.last_image_cap: float | None = None  # the image fraction the last plan was held to (None: no cap)
        self.last_price: float | None = None  # λ of the last plan's in-slot rule (J per unit of loss)
        self.seq = 0  # of the last schedule
        self._active: ScheduleMsg | None = None
        self._round_start_slot: int | None = None  # the simulator's round start (oracle only)

    @property
    def loss_map(self) -> LossMap:
        """The live loss map (the seed, updated by every measured sample): what the scheduler saves."""
        return self.forecast.loss_map

    def reseed(self, loss_map: LossMap) -> None:
        """A new seed loss map (the scheduler's ``loss_map_file`` set at run time, after a model swap): the
        forecast predicts from it from the next plan on (:meth:`LossForecast.reseed`); the loss the booked slots left
        stays as estimated before it (:meth:`LossBudget.freeze_all`: they were served by the old model)."""
        self.budget.freeze_all()
        self.forecast.reseed(loss_map)

    @property
    def active(self) -> ScheduleMsg | None:
        """The schedule most recently planned (or resumed)."""
        return self._active

    @property
    def round_start_slot(self) -> int | None:
        """The slot the simulator's round (and its fading index) started in, once learnt (oracle only)."""
        return self._round_start_slot

    # ------------------------------------------------------------------ configuration and state
    def reconfigure(self, config: PlannerConfig) -> None:
        """Plan with ``config`` from the next plan on (a live parameter change). Only
        :data:`~gsrmr_scheduler.planner.config.LIVE_FIELDS` may differ; ValueError names any other."""
        reason = self.config.live_change_problem(config)
        if reason:
            raise ValueError(f"planner: {reason}")
        self.config = config
        self.drift.reconfigure(config.drift_threshold, config.drift_window_samples)

    def resume(self, schedule: ScheduleMsg) -> None:
        """Continue from a saved ``schedule`` (a restarted scheduler): it is the active one, and the next plan
        follows its sequence number."""
        self._active = schedule
        self.seq = schedule.seq

    def learn_round_start(self, slot: int) -> None:
        """Oracle only: the simulator's round started in ``slot`` (its fading index counts from there)."""
        self._round_start_slot = int(slot)

    # ------------------------------------------------------------------ what happened
    def record_action(self, slot: int, x: int, held_back: int = 0, uplink_rate_bps: float = math.nan,
                      image_bits: float = math.nan, scene_change: int = 0, correction_seq: int = 0) -> None:
        """What the robot did in ``slot`` (1 = image), from its ledger: key slots are charged by it.
        ``held_back`` = 1: an image was asked for and the robot sent the key, its last image still queued;
        ``uplink_rate_bps``: the robot's estimate of the uplink throughput (from its image acknowledgements);
        ``image_bits``: the size of this slot's frame as a JPEG; ``scene_change`` = 1: the robot's scene-change
        test fired on this slot's frame (the key slots around it are estimated as a step there);
        ``correction_seq``: the ``map → odom`` correction the slot's key was made with (:class:`~.fix_age.FixAge`)."""
        self.budget.record_action(slot, x)
        self.fix_age.ledger(slot, x, correction_seq)
        if scene_change:
            self.forecast.note_change(slot)
        self.link_cap.record(slot, x, held_back, uplink_rate_bps, image_bits)
        if x:
            self.pricing.record_image(slot)

    def record_composed(self, slot: int, source: str, level: int = 0) -> None:
        """What the server composed ``slot`` from (its ``mr/slot_info`` source: ``image``, ``render``, ``fallback``,
        ``none``): an image it did not have in time is charged as the render it used instead
        (:meth:`~.budget.LossBudget.record_composed`)."""
        self.budget.record_composed(slot, source, level)

    def record_pose(self, slot: int, a_m: float, b_m: float, theta_rad: float) -> None:
        """The pose the robot reported for ``slot`` (its pose key): key slots are charged at it."""
        self.budget.record_pose(slot, (a_m, b_m, theta_rad))
        self.fix_age.key(slot, Pose2D(a_m, b_m, theta_rad))

    def observe(self, slot: int, a_m: float, b_m: float, theta_rad: float, loss: float) -> bool:
        """An image slot's measured L_t (the server's loss sample, corrected by ``loss_sample_offset``: the loss
        against the frame); True when the prediction error says a replan is due."""
        self.link_cap.record_sample(slot)
        loss = self.forecast.corrected(loss)
        predicted = self.forecast.observe(slot, (a_m, b_m, theta_rad), loss)
        if predicted is None or not math.isfinite(loss):
            return False
        return self.drift.add(abs(loss - predicted))

    def clear_drift(self) -> None:
        """Forget past prediction errors (after a replan)."""
        self.drift.clear()

    # ------------------------------------------------------------------ planning
    def gains(self, first: int, poses: np.ndarray) -> np.ndarray:
        """g_t (dimensionless ``|h|²``) for slots ``first …`` at the predicted ``poses`` (:meth:`plan`, step 3)."""
        if not self.config.oracle_channel or self._round_start_slot is None:
            return np.array([self.link.mean_gain(poses[i, :2]) for i in range(len(poses))])
        out = []
        for i in range(len(poses)):
            k = first + i - self._round_start_slot
            out.append(self.link.gain(k if k >= 0 else first + i, poses[i, :2]))
        return np.array(out)

    def plan(self, now_slot: int, pose: Pose2D | None) -> PlanResult:
        """Plan the ``horizon_slots`` slots from ``now_slot``, the slot in which the schedule is expected to reach
        the robot.

        The node passes the slot in which it expects the plan to be done (now + the p90 of its plan times). The plan
        covers that slot too: the robot replaces its schedule with each new one, a schedule published before the
        slot starts decides it, and a slot its schedule has no entry for uploads the image whatever the fade. A
        plan done within ``now_slot`` covers a slot the robot has already decided; the next plan books that slot by
        its ledger row. The steps:

        1. the robot's poses along the route (:class:`~.route.RoutePredictor`);
        2. L_t there (:class:`~.forecast.LossForecast`: the burst model with its learned margin, or the loss map as
           it stands with ``trust_loss_map``);
        3. g_t from the channel's statistics: the expected gain ρ0·d^−α at the predicted robot–server distance
           (:meth:`~gsrmr_common.link_model.LinkBudget.mean_gain`), what a deployment knows; with
           ``oracle_channel`` the simulator's future fading (:meth:`learn_round_start`: an upper bound, not
           deployable);
        4. the loss budget of each block, the round's rest and what follows it (:meth:`~.budget.LossBudget.caps`);
           an image slot leaves the loss J = ``image_slot_loss``, so Σ x·J + (1 − x)·L ≤ cap becomes the knapsack
           Σ (1 − x)(L − J) ≤ cap − n·J;
        5. each block solved with :func:`gsrmr_scheduler.solve.solve` (``method``, ``solver_options``);
        6. with ``in_slot_decision`` (and no oracle) per-slot gain thresholds (:class:`~.pricing.InSlotPricing`),
           taking ever poorer fades where the robot's pose fix grows stale (:class:`~.fix_age.FixAge`);
           without, the solved images held to what the uplink carries (:class:`~.link_cap.LinkCap`).

        Args:
            now_slot: the absolute slot index (slots of τ = ``config.slot_s`` s) the plan starts at.
            pose: the robot's last reported pose (a_m, b_m, theta_rad) in ``map``; None: the route's start.

        Returns:
            :class:`PlanResult`: the wire schedule (per slot x, power in W and, with the in-slot rule, the gain
            thresholds as dimensionless ``|h|²``), the images planned, the plan's energy (J), the mean predicted
            loss, the first block's loss budget per slot, whether every block was feasible, the solve time (s) and
            the predicted L_t (margin included).

        Raises:
            ValueError: an option in ``config.solver_options`` the method does not take.

        Example:
            After the planner of the class example has taken in a few slots::

                planner.observe(3, 0.06, 0.0, 0.0, loss=0.08)  # an image slot's loss sample
                result = planner.plan(now_slot=5, pose=(0.1, 0.0, 0.0))
                result.schedule.first_slot, result.images, result.energy_j
        """
        cfg = self.config
        self.budget.account_until(now_slot, self._active)
        first, h = now_slot, cfg.horizon_slots
        poses = self.route.predict(pose, h, cfg.slot_s)
        slots = np.arange(first, first + h)
        raw, losses = self.forecast.predict(slots, poses)
        losses = losses + self.budget.level_loss_now(first)  # a server short of CPU renders its keys coarser
        gains = self.gains(first, poses)
        j = cfg.image_slot_loss
        key_cost = np.maximum(losses - j, 0.0)  # Σ x·J + (1−x)·L ≤ cap ⇔ Σ (1−x)(L − J) ≤ cap − n·J
        self.last_image_cap = image_cap = self.link_cap.image_cap()
        priced = cfg.in_slot_decision and not cfg.oracle_channel
        explore = self.pricing.explore(slots, self.forecast.samples) if priced else None
        stale = self.fix_age.explore(poses, pose) if priced else None
        if stale is not None:  # the robot's pose fix grows stale: buy an image the server can fix it from
            explore = np.maximum(explore, stale)
        out = _Blocks(np.zeros(h, np.int8), np.zeros(h), np.full(h, np.inf) if priced else None)
        mean_budget = None  # the first block's mean loss budget per slot (the reply reports it)
        for part, cap in self.budget.caps(first, h, cfg.loss_target):
            n = part.stop - part.start
            block_budget = max(0.0, (cap - j * n) / n)
            mean_budget = block_budget if mean_budget is None else mean_budget
            self._solve_block(out, part, gains[part], key_cost[part], block_budget)
            max_images = None if image_cap is None else image_cap * n
            if explore is not None:
                out.thresholds[part], price = self.pricing.thresholds(
                    gains[part], key_cost[part], block_budget * n, explore[part], self._saving_coefficient_j(),
                    max_images)
                if part.start == 0:
                    self.last_price = price
            elif max_images is not None:  # keep the images saving most loss per joule
                capped = cap_planned_images(out.x[part], key_cost[part], gains[part], max_images)
                if capped is not None:
                    out.x[part] = capped
                    out.notes.append(f"images capped at {image_cap:.2f} of slots: the uplink carries no more")
        self.seq += 1
        schedule = ScheduleMsg(first, cfg.slot_s, self.seq, out.x, out.power_w, out.thresholds)
        self.forecast.remember(first, raw, now_slot)
        self._active = schedule
        self.budget.planned_from(first - 1)
        return PlanResult(schedule, cfg.method, int(out.x.sum()), out.energy_j,
                          float(np.mean(losses * (1 - out.x) + j * out.x)), float(mean_budget), out.feasible,
                          out.solve_time_s, losses, out.notes)

    def _solve_block(self, out: _Blocks, part: slice, gains: np.ndarray, key_cost: np.ndarray,
                     loss_threshold: float) -> None:
        """Solve P_GS over one block of the horizon into ``out``."""
        cfg = self.config
        problem = Problem(slot_s=cfg.slot_s, image_bits=cfg.image_bits, pose_bits=cfg.pose_bits,
                          bandwidth_hz=self.link.bandwidth_hz, noise_w=self.link.noise_w, channel_gain=gains,
                          gs_loss=key_cost, loss_threshold=loss_threshold)
        t0 = time.perf_counter()
        result = solve(problem, cfg.method, **cfg.solver_options)
        out.solve_time_s += time.perf_counter() - t0
        out.notes += list(getattr(result, "notes", []) or [])
        out.x[part] = np.asarray(result.x, dtype=np.int8)
        out.power_w[part] = np.nan_to_num(np.asarray(result.power_w, dtype=np.float64), nan=0.0, posinf=0.0)
        out.energy_j += float(result.energy_j)
        out.feasible = out.feasible and bool(result.feasible)

    def _saving_coefficient_j(self) -> float:
        """c of the in-slot rule: an image minus a key costs c/g joules at gain g."""
        cfg = self.config
        return saving_coefficient_j(cfg.image_bits, cfg.pose_bits, cfg.slot_s, self.link.bandwidth_hz,
                                    self.link.noise_w)
