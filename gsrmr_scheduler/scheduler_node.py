"""The scheduler node (``gsrmr-scheduler``): solves P_GS online and publishes the schedule.

Replans (see :class:`~gsrmr_scheduler.planner.OnlinePlanner`) every ``replan_period_s``, on
``/gsrmr/replan`` (``std_srvs/Trigger``, relative name ``gsrmr/replan``), after any accepted parameter
change, and by itself when measured losses drift from the prediction by more than ``drift_threshold``. With
``replan_on_loss_sample`` the periodic replan waits for the next loss sample (a period at most) and runs right after
it, as a drift replan does (:class:`~gsrmr_scheduler.planner.cadence.SampleAlignedCadence`).

Subscribes: ``uplink/pose_key`` (geometry_msgs/Vector3Stamped: the robot's pose in ``map``),
``gsrmr/loss_sample`` (std_msgs/Float64MultiArray ``[slot, a_m, b_m, theta_rad, loss]`` from the server),
``gsrmr/ledger`` (the robot's ledger rows) and ``mr/slot_info`` (the server's :class:`~gsrmr_common.wire.MRSlotInfo`:
what it composed each slot from — an image that did not reach it in time is charged as the render it used).
Publishes: ``gsrmr/schedule`` (std_msgs/Float64MultiArray, layout in :mod:`gsrmr_common.wire`;
reliable, transient local, depth 1), ``/diagnostics``.
The last schedule and the loss map are saved in ``state_dir`` (when set) after every plan, and loaded
at start, so a restarted scheduler resumes from its last schedule.

Nothing on the graph is taken blindly (``docs/security.md``, "Application checks"): every input is admitted by its
writer (:class:`gsrmr_common.ros_admission.GatedInputs`: ``robot_writers`` for the pose keys and the ledger,
``loss_writers`` for the loss samples and the slot info, ``channel_writers`` for the oracle; each writer endpoint
rate-limited); pose keys must move within ``max_speed_mps``; a ledger row must name a slot near now, once; a loss
sample must lie in the metric's range, come once per slot, for a slot the ledger says carried an image, at the pose
the robot reported for it
(:class:`gsrmr_common.plausibility.LossSampleCheck`; a sample that comes before its slot's ledger row waits for it,
20 slots at most; one for a slot before the first ledger row heard is not used, counted ``loss_samples_unverified``).
``gsrmr/replan`` answers at most once per ``replan_min_interval_s``. Refusals are counted by writer and by reason on
``/diagnostics``.

Parameters: :class:`~gsrmr_scheduler.scheduler_params.SchedulerParameters` (``self.params``); a change is
checked in the on-set callback (read-only ones, values out of range or of the wrong type, an unknown
``method``, ``solver_options`` that are no JSON object, values the planner's configuration refuses — e.g.
``image_bits`` ≤ ``pose_bits`` — are refused with the reason) and applied in the post-set callback: a planning
parameter builds a new :class:`~gsrmr_scheduler.planner.PlannerConfig` (:meth:`SchedulerParameters.planner_config`)
that the planner takes with :meth:`~gsrmr_scheduler.planner.OnlinePlanner.reconfigure` — live changes only with
``live_parameter_changes``.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import replace
import json
import math
from pathlib import Path
import threading
import time

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Vector3Stamped
import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger

from gsrmr_common.interrupts import console_main
from gsrmr_common.plausibility import (
    REDELIVERED,
    Implausible,
    LossSampleCheck,
    PoseTrack,
    ledger_image_sent,
    ledger_problem,
)
from gsrmr_common.ros_admission import GatedInputs, ParameterAudit
from gsrmr_common.ros_node import declare_link_budget, declare_parameters, diagnostics_msg, run_node
from gsrmr_common.ros_wire import (
    LOSS_SAMPLE_QOS,
    SCHEDULE_QOS,
    UPLINK_QOS,
    channel_sample_from_msg,
    ledger_from_msg,
    loss_sample_from_msg,
    mr_slot_info_from_msg,
    pose_key_from_msg,
    schedule_to_msg,
)
from gsrmr_common.slot_clock import SlotClock
from gsrmr_common.wire import CHANNEL_TOPIC, MR_SLOT_INFO_TOPIC, LossSample, ScheduleMsg
from gsrmr_scheduler import exact
from gsrmr_scheduler.loss_map import LossMap
from gsrmr_scheduler.planner import OnlinePlanner, PlanResult, RoutePredictor
from gsrmr_scheduler.planner.cadence import SampleAlignedCadence
from gsrmr_scheduler.problem import Problem
from gsrmr_scheduler.scheduler_params import PLANNING_PARAMETERS, SchedulerParameters
from gsrmr_scheduler.solve import solve

#: Slots whose ledger rows and pose keys the loss-sample check remembers.
_MEMORY_SLOTS = 2000
_SLOT_INFO_SKEW_SLOTS = 50  # an mr/slot_info names a slot within this many of now (as a ledger row does)
#: A loss sample waits this many slots for its slot's ledger row, then it is refused (``loss_unledgered``).
_LOSS_WAIT_SLOTS = 20


class SchedulerNode(Node):
    """Online GSCLO scheduler."""

    def __init__(self, **node_kwargs) -> None:
        super().__init__("gsrmr_scheduler", **node_kwargs)
        self.params: SchedulerParameters = replace(declare_parameters(self, SchedulerParameters),
                                                   link=declare_link_budget(self))
        p = self.params
        self.clock = SlotClock(p.slot_s)
        # Load the compiled knapsack kernel now (1–2 s from the numba cache, ~8 s cold) rather than in the
        # first replan, so the first schedule follows start-up at once.
        self.get_logger().info(f"knapsack kernel ready in {exact.warm_up():.2f} s")
        if p.method != "exact":  # the method's own first call too (APO imports CVXPY: ~1 s)
            t0 = time.perf_counter()
            solve(Problem(channel_gain=np.array([1e-6, 2e-6, 3e-6, 4e-6]), gs_loss=np.array([0.04, 0.01, 0.03, 0.02]),
                          loss_threshold=0.012), p.method, **p.options)
            self.get_logger().info(f"method {p.method} ready in {time.perf_counter() - t0:.2f} s")
        loss_map = LossMap(prior=p.loss_prior)
        for candidate in (Path(p.state_dir, "loss_map.json") if p.state_dir else None,
                          Path(p.loss_map_file) if p.loss_map_file else None):
            if candidate is not None and candidate.exists():
                loss_map = LossMap.load(candidate)
                self.get_logger().info(f"loss map loaded from {candidate} ({len(loss_map.cells)} cells)")
                break
        self.planner = OnlinePlanner(p.planner_config(loss_map), RoutePredictor(p.waypoints, p.route_speed_mps),
                                     loss_map, p.link)
        self._lock = threading.RLock()
        self._pose: tuple[float, float, float] | None = None
        self._replan_reason: str | None = "start"
        self._new_loss_map: LossMap | None = None  # a loss_map_file read by the on-set check, for the post-set
        self.last: PlanResult | None = None
        self.replans: dict[str, int] = {}
        self.solve_times_s: list[float] = []
        self.plan_times_s: list[float] = []  # wall time of the whole plan (predictor, solver, thresholds)
        self.plan_slack_s: list[float] = []  # end of the first covered slot − schedule ready [s]
        self._logged_cap: float | None = None  # the uplink image cap last logged
        self._pub = self.create_publisher(Float64MultiArray, "gsrmr/schedule", SCHEDULE_QOS)
        self._pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        # what is taken from the graph, and from whom (docs/security.md, "Application checks")
        self.audit = ParameterAudit(self, p.live_parameter_changes)
        self.implausible = Implausible()
        self.poses = PoseTrack(p.max_speed_mps, p.slot_s)
        self.loss_check = LossSampleCheck(_MEMORY_SLOTS)
        self._ledger_x: OrderedDict[int, int] = OrderedDict()  # slot → what the robot's ledger row says it did
        self._key_poses: OrderedDict[int, tuple[float, float, float]] = OrderedDict()  # slot → its accepted key
        self._waiting_loss: dict[int, LossSample] = {}  # samples whose slot's ledger row has not come yet
        self._first_ledger_slot: int | None = None  # the earliest slot of an accepted ledger row
        # loss samples of slots before the first ledger row heard (start-up: discovery may match the server's loss
        # writer before the robot's ledger writer, whose rows are not latched): not used, and not implausible either
        self.loss_samples_unverified = 0
        self.loss_samples_redelivered = 0  # samples taken already, sent again from the server's history: dropped
        self._service_replan_s: float | None = None  # monotonic time of the last replan the service ran
        self.replans_refused = 0
        self.inputs = GatedInputs(self)
        self.inputs.subscribe(Vector3Stamped, "uplink/pose_key", self._on_key, UPLINK_QOS, p.robot_writers,
                              rate_hz=40.0, burst=60.0)
        self.inputs.subscribe(Float64MultiArray, "gsrmr/loss_sample", self._on_loss, LOSS_SAMPLE_QOS, p.loss_writers,
                              rate_hz=40.0, burst=60.0)
        if p.oracle_channel:
            self.inputs.subscribe(Float64MultiArray, CHANNEL_TOPIC, self._on_channel, 10, p.channel_writers,
                                  rate_hz=40.0, burst=40.0)
        self.inputs.subscribe(Float64MultiArray, "gsrmr/ledger", self._on_ledger, UPLINK_QOS, p.robot_writers,
                              rate_hz=40.0, burst=60.0)
        self.inputs.subscribe(Float64MultiArray, MR_SLOT_INFO_TOPIC, self._on_slot_info, UPLINK_QOS, p.loss_writers,
                              rate_hz=40.0, burst=60.0)
        self.create_service(Trigger, "gsrmr/replan", self._on_replan)
        self.add_on_set_parameters_callback(self._validate)
        self.add_post_set_parameters_callback(self._apply)
        self._restore()
        self.cadence = SampleAlignedCadence(p.replan_on_loss_sample)
        self._replan_timer = self.create_timer(p.replan_period_s, self._on_period)
        self.create_timer(0.02, self._tick)
        self.create_timer(1.0, self._publish_diagnostics)

    def _on_ledger(self, msg: Float64MultiArray, _gid: bytes = b"") -> None:
        """What the robot did in a slot (an in-slot decision may differ from the plan's x): one plausible row per slot;
        a loss sample that waited for it is judged now."""
        try:
            row = ledger_from_msg(msg)
        except ValueError:
            self.implausible["ledger_malformed"] += 1
            return
        now_slot = self.clock.slot_at(self.get_clock().now().nanoseconds)
        reason = ledger_problem(row, now_slot)
        if reason is None and row.slot in self._ledger_x:
            reason = "ledger_repeat"  # one row per slot: the first stands
        if reason:
            self.implausible[reason] += 1
            return
        x = ledger_image_sent(row)  # what left, not what was asked for
        _remember(self._ledger_x, row.slot, x)
        first = self._first_ledger_slot
        self._first_ledger_slot = row.slot if first is None else min(row.slot, first)
        with self._lock:
            self.planner.record_action(row.slot, x, row.held_back, row.uplink_rate_bps, row.upload_all_bits,
                                       row.scene_change)
        waiting = self._waiting_loss.pop(row.slot, None)
        if waiting is not None:
            self._take_loss(waiting)

    def _on_channel(self, msg: Float64MultiArray, _gid: bytes = b"") -> None:
        """Oracle only: learn when the simulator's round (and its fading index) started."""
        try:
            sample = channel_sample_from_msg(msg)
        except ValueError:
            return
        if sample.round_slot >= 0 and self.planner.round_start_slot is None:
            with self._lock:
                self.planner.learn_round_start(sample.slot - sample.round_slot)
            self._request("channel round start")

    # ---------------------------------------------------------------- parameters
    def _validate(self, params: list[Parameter]) -> SetParametersResult:
        """On-set: refuse a change :class:`SchedulerParameters` gives a reason for (type, range, read-only,
        method, solver_options) or the planner's configuration refuses (image_bits ≤ pose_bits), or any change while
        live changes are off; change nothing."""
        for param in params:
            reason = SchedulerParameters.change_problem(param.name, param.value)
            if reason:
                return SetParametersResult(successful=False, reason=reason)
        refusal = self.audit.refusal(param.name for param in params)
        if refusal:
            return SetParametersResult(successful=False, reason=refusal)
        if any(param.name in PLANNING_PARAMETERS for param in params):
            try:
                self.params.with_values({param.name: param.value for param in params}).planner_config(
                    self.planner.loss_map)
            except ValueError as err:
                return SetParametersResult(successful=False, reason=str(err))
        for param in params:
            if param.name == "loss_map_file":
                try:  # a small JSON: read it here, so that a bad file is refused, not applied
                    self._new_loss_map = LossMap.load(Path(str(param.value)))
                except (OSError, ValueError, KeyError, TypeError, AttributeError) as err:
                    return SetParametersResult(successful=False, reason=f"loss_map_file {param.value!r} is no loss "
                                               f"map: {type(err).__name__}: {err}")
        return SetParametersResult(successful=True)

    def _apply(self, params: list[Parameter]) -> None:
        """Post-set: take the accepted values into ``self.params``; a planning one gives the planner a new
        configuration and requests a replan; ``replan_period_s`` re-times the replan timer."""
        names = {param.name for param in params}
        changed = [param.name for param in params if param.name in PLANNING_PARAMETERS]
        with self._lock:
            old = self.params
            self.params = self.params.with_values({param.name: param.value for param in params})
            self.audit.record({param.name: (getattr(old, param.name, None), getattr(self.params, param.name, None))
                               for param in params})
            if changed:
                self.planner.reconfigure(self.params.planner_config(self.planner.loss_map))
            if "loss_map_file" in names and self._new_loss_map is not None:
                self.planner.reseed(self._new_loss_map)
                self.get_logger().info(f"loss map re-seeded from {self.params.loss_map_file} "
                                       f"({len(self._new_loss_map.cells)} cells)")
                self._new_loss_map = None
                changed.append("loss_map_file")
        if "replan_period_s" in names:
            self._replan_timer.timer_period_ns = round(self.params.replan_period_s * 1e9)
        if changed:
            self._request("parameters: " + ", ".join(changed))

    # ---------------------------------------------------------------- inputs
    def _on_key(self, msg: Vector3Stamped, _gid: bytes = b"") -> None:
        try:
            key = pose_key_from_msg(msg, self.clock)
        except ValueError as err:  # wrong frame or invalid stamp: ignore, never raise out of the callback
            self.implausible["key_malformed"] += 1
            self.get_logger().warning(f"pose key refused: {err}", throttle_duration_sec=5.0)
            return
        if not key.is_valid():
            return
        if not self.poses.offer(key.slot, key.a_m, key.b_m):
            self.implausible["pose_jump"] += 1  # faster than the robot drives: no relocalisation (yet)
            return
        self._pose = (key.a_m, key.b_m, key.theta_rad)
        _remember(self._key_poses, key.slot, self._pose)
        with self._lock:
            self.planner.record_pose(key.slot, *self._pose)

    def _on_slot_info(self, msg: Float64MultiArray, _gid: bytes = b"") -> None:
        """What the server composed a slot from: the budget charges the slot by it (an image it did not have in time
        left a render's loss, not the JPEG's). One per slot near now."""
        try:
            info = mr_slot_info_from_msg(msg)
        except ValueError:
            self.implausible["slot_info_malformed"] += 1
            return
        now_slot = self.clock.slot_at(self.get_clock().now().nanoseconds)
        if abs(info.slot - now_slot) > _SLOT_INFO_SKEW_SLOTS:
            self.implausible["slot_info_slot"] += 1
            return
        with self._lock:
            self.planner.record_composed(info.slot, str(info.source))

    def _on_loss(self, msg: Float64MultiArray, _gid: bytes = b"") -> None:
        try:
            sample = loss_sample_from_msg(msg)
        except ValueError:
            self.implausible["loss_malformed"] += 1
            return
        self._take_loss(sample)

    def _take_loss(self, sample: LossSample) -> None:
        """Observe a plausible loss sample; one whose slot has no ledger row yet waits for it (a few at most)."""
        x = self._ledger_x.get(sample.slot)
        reason = self.loss_check.problem(sample, None if x is None else bool(x), self._key_poses.get(sample.slot))
        if reason == REDELIVERED:  # the server's latched history, read again after this reader resubscribed
            self.loss_samples_redelivered += 1
            return
        if reason == "loss_unledgered" and len(self._waiting_loss) < 16 and sample.slot not in self._waiting_loss:
            self._waiting_loss[sample.slot] = sample
            return
        if reason:
            self._refuse_loss(sample, reason)
            return
        with self._lock:
            drift = self.planner.observe(sample.slot, sample.a_m, sample.b_m, sample.theta_rad, sample.loss)
            period = self.cadence.sample_taken()
        if drift or period:
            self._request("drift" if drift else "period")
            if self.cadence.aligned:  # now, not at the next tick: the plan should reach the robot for the next slot
                self._tick()

    def _on_period(self) -> None:
        """The replan timer: a replan now, or right after the next loss sample (:class:`SampleAlignedCadence`)."""
        with self._lock:
            due = self.cadence.timer_fired()
        if due:
            self._request("period")

    def _expire_waiting_loss(self) -> None:
        """Loss samples whose ledger row did not come within ``_LOSS_WAIT_SLOTS`` are refused."""
        if not self._waiting_loss:
            return
        now_slot = self.clock.slot_at(self.get_clock().now().nanoseconds)
        for slot in [k for k in self._waiting_loss if k < now_slot - _LOSS_WAIT_SLOTS]:
            self._refuse_loss(self._waiting_loss.pop(slot), "loss_unledgered")

    def _refuse_loss(self, sample: LossSample, reason: str) -> None:
        """Count a refused loss sample: implausible, or — without a ledger row for a slot before the first one heard —
        unverified."""
        if reason == "loss_unledgered" and (self._first_ledger_slot is None or sample.slot < self._first_ledger_slot):
            self.loss_samples_unverified += 1
            return
        self.implausible[reason] += 1
        self.get_logger().warning(f"loss sample refused ({reason}): slot {sample.slot}, loss {sample.loss:.4g}",
                                  throttle_duration_sec=5.0)

    def _request(self, reason: str) -> None:
        with self._lock:
            if self._replan_reason is None or reason != "period":
                self._replan_reason = reason

    def _tick(self) -> None:
        self._expire_waiting_loss()
        reason = self._replan_reason
        if reason is not None:
            self.replan(reason)

    # ---------------------------------------------------------------- planning
    def replan(self, reason: str) -> tuple[PlanResult, int]:
        """Plan from the slot in which the plan is expected to be done (the p90 of the last 20 plan times from
        now: this slot for a 1-ms plan, later for a slow solver) and publish — a schedule that reaches the robot
        before that slot starts covers it too (:mod:`gsrmr_scheduler.planner.online`); returns the result and how many
        slots changed x."""
        with self._lock:
            self._replan_reason = None
            self.cadence.replanned()
            recent = sorted(self.plan_times_s[-20:])
            expected_ns = int(1e9 * recent[int(0.9 * (len(recent) - 1))]) if recent else 0
            now_slot = self.clock.slot_at(self.get_clock().now().nanoseconds + expected_ns)
            previous = self.planner.active
            t0 = time.perf_counter()
            result = self.planner.plan(now_slot, self._pose)
            self.plan_times_s.append(time.perf_counter() - t0)
            del self.plan_times_s[:-100]
            # > 0: the schedule was ready by the end of the slot it was expected to be done in (now_slot, the first
            # it covers); < 0: later than expected (bench/demo.py's replans_late)
            self.plan_slack_s.append(round((self.clock.start_ns(now_slot + 1)
                                            - self.get_clock().now().nanoseconds) / 1e9, 4))
            del self.plan_slack_s[:-10_000]
            changed = 0
            if previous is not None:
                for i, x in enumerate(result.schedule.x):
                    old = previous.lookup(result.schedule.first_slot + i)
                    changed += int(old is not None and old[0] != int(x))
            self.last = result
            self.solve_times_s.append(round(result.solve_time_s, 6))
            del self.solve_times_s[:-10_000]
            self.replans[reason.split(":")[0]] = self.replans.get(reason.split(":")[0], 0) + 1
            self.planner.clear_drift()
        self._pub.publish(schedule_to_msg(result.schedule))
        self._save(result.schedule)
        cap = self.planner.last_image_cap
        if (cap is None) != (self._logged_cap is None) or (cap is not None and abs(cap - self._logged_cap) >= 0.05):
            self._logged_cap = cap
            link_cap = self.planner.link_cap
            self.get_logger().info(
                "uplink image cap: image_cap=none (the link carries an image per slot)" if cap is None else
                f"uplink image cap: image_cap={cap:.3f} ({link_cap.images_held_back()} held back in the last "
                f"slots, {_ratio(link_cap.delivery_ratio())} of the last images composed in their slot; "
                "the plan keeps the images saving the most loss per joule)")
        if reason != "period":
            self.get_logger().info(f"replan ({reason}): {self._summary(result, changed)}")
        return result, changed

    @staticmethod
    def _summary(result: PlanResult, changed: int) -> str:
        return (f"method={result.method} T={len(result.schedule.x)} images={result.images} "
                f"energy_j={result.energy_j:.6g} predicted_mean_loss={result.mean_predicted_loss:.4f} "
                f"budget={result.budget:.4f} feasible={result.feasible} solve_time_s={result.solve_time_s:.4f} "
                f"changed_slots={changed}")

    def _on_replan(self, _request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        now = time.monotonic()
        interval = self.params.replan_min_interval_s
        if self._service_replan_s is not None and now - self._service_replan_s < interval:
            self.replans_refused += 1
            response.success = False
            response.message = (f"rate-limited: one replan per {interval:g} s on this service (the last "
                                f"{now - self._service_replan_s:.2f} s ago); the schedule is replanned every "
                                f"{self.params.replan_period_s:g} s anyway")
            return response
        self._service_replan_s = now
        previous = self.last
        result, changed = self.replan("service")
        what = f"{changed} slot(s) switched image/key against the previous schedule"
        if previous is not None and not changed:
            what = "no slot changed image/key (same inputs give the same optimum)"
        response.success = bool(result.feasible)
        response.message = self._summary(result, changed) + "; " + what
        return response

    # ---------------------------------------------------------------- state
    def _save(self, schedule: ScheduleMsg) -> None:
        if not self.params.state_dir:
            return
        state = Path(self.params.state_dir)
        state.mkdir(parents=True, exist_ok=True)
        tmp = state / "schedule.json.tmp"
        tmp.write_text(json.dumps({"data": schedule.to_data()}))
        tmp.replace(state / "schedule.json")
        self.planner.loss_map.save(state / "loss_map.json")
        stats = state / "plan_stats.json.tmp"  # every replan's solve time (bench/demo.py reads it)
        stats.write_text(json.dumps({"method": self.planner.config.method, "solve_time_s": self.solve_times_s,
                                     "slack_s": self.plan_slack_s}))
        stats.replace(state / "plan_stats.json")

    def _restore(self) -> None:
        state_dir = self.params.state_dir
        if not state_dir or not Path(state_dir, "schedule.json").exists():
            return
        try:
            sched = ScheduleMsg.from_data(json.loads(Path(state_dir, "schedule.json").read_text())["data"])
        except (ValueError, KeyError, json.JSONDecodeError) as err:
            self.get_logger().warning(f"saved schedule ignored: {err}")
            return
        now_slot = self.clock.slot_at(self.get_clock().now().nanoseconds)
        if sched.lookup(now_slot + 1) is not None:
            self.planner.resume(sched)
            self._pub.publish(schedule_to_msg(sched))
            self.get_logger().info(f"resumed schedule seq {sched.seq} from {state_dir}")

    def on_shutdown(self) -> None:
        """Log what the input checks refused and the replans the service refused (called by run_node on exit)."""
        self.inputs.log_summary(self.implausible, replans_refused=self.replans_refused,
                                relocalisations=self.poses.relocalisations,
                                loss_samples_unverified=self.loss_samples_unverified,
                                loss_samples_redelivered=self.loss_samples_redelivered)

    def _publish_diagnostics(self) -> None:
        r = self.last
        p = self.planner
        cfg, budget, lp = p.config, p.budget, p.forecast.model
        values = {"replans": json.dumps(self.replans), "loss_map_cells": len(p.loss_map.cells),
                  "loss_spent": round(budget.loss_spent, 6), "slots_accounted": budget.slots_done,
                  # what L_t is predicted by: the burst model, or the loss map as it is (the oracle's survey)
                  "loss_model": "map" if lp is None else "burst", "image_slot_loss": round(cfg.image_slot_loss, 6),
                  "loss_sample_offset": round(cfg.loss_sample_offset, 6),
                  # the image fraction the last plan was held to because the robot held images back (-1: none)
                  "link_image_cap": -1 if p.last_image_cap is None else round(p.last_image_cap, 4),
                  "images_held_back": p.link_cap.images_held_back(),
                  "image_delivery_ratio": _ratio(p.link_cap.delivery_ratio())}
        if lp is not None:
            values.update({"loss_level_ratio": round(math.exp(lp.level), 4), "loss_margin_factor": round(lp.margin, 4),
                           "loss_burst_factor": round(lp.burst_factor, 4)})
        if cfg.round_slots:
            remaining = budget.round_remaining(self.clock.slot_at(self.get_clock().now().nanoseconds) + 1)
            values["round_slots_remaining"] = -1 if remaining is None else remaining
        if r is not None:
            values.update({"method": r.method, "horizon": len(r.schedule.x), "images": r.images,
                           "energy_j": r.energy_j, "feasible": r.feasible, "solve_time_s": round(r.solve_time_s, 5),
                           "seq": r.schedule.seq})
        values.update({k: json.dumps(v) if isinstance(v, dict) else v for k, v in {
            **self.inputs.diagnostic_values(), "implausible": self.implausible.values_for_diagnostics(),
            "relocalisations": self.poses.relocalisations, "replans_refused": self.replans_refused,
            "loss_samples_unverified": self.loss_samples_unverified,
            "loss_samples_redelivered": self.loss_samples_redelivered,
            **self.audit.diagnostic_values()}.items()})
        problems = [] if r is None or r.feasible else ["plan infeasible"]
        problems += self.inputs.problems()
        if self.implausible:
            problems.append("implausible inputs refused: " + ", ".join(
                f"{k} {n}" for k, n in sorted(self.implausible.items())))
        if self.replans_refused:
            problems.append(f"gsrmr/replan calls refused (rate limit): {self.replans_refused}")
        self._pub_diag.publish(diagnostics_msg(
            self, name=f"{self.get_name()}: schedule", hardware_id="gsrmr_server", values=values,
            problems=problems))


def _remember(book: OrderedDict, slot: int, value: object) -> None:
    """``book[slot] = value``, the oldest slots forgotten past ``_MEMORY_SLOTS``."""
    book[slot] = value
    while len(book) > _MEMORY_SLOTS:
        book.popitem(last=False)


def _ratio(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.0%}"


@console_main
def main(args: list[str] | None = None) -> int:
    """Console script ``gsrmr-scheduler``."""
    return run_node(SchedulerNode, args)


