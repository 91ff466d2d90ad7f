"""The scheduler node (``gsrmr-scheduler``): solves P_GS online and publishes the schedule. Topics, services and
parameters: ``gsrmr-scheduler --help``; when it replans and what it takes from the graph: ``docs/scheduling.md`` and
``docs/security.md``. Its logic: :class:`~gsrmr_scheduler.planner.OnlinePlanner`,
:class:`~gsrmr_scheduler.intake.SchedulerIntake`, the replan log and the state store."""

from __future__ import annotations

from dataclasses import replace
import json
import threading
import time

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Vector3Stamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger

from gsrmr_common.interrupts import console_main
from gsrmr_common.pose2d import Pose2D
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
from gsrmr_common.wire import CHANNEL_TOPIC, MR_SLOT_INFO_TOPIC, LossSample
from gsrmr_scheduler.intake import Refusal, SchedulerIntake
from gsrmr_scheduler.loss_map import LossMap
from gsrmr_scheduler.planner import OnlinePlanner, PlanResult, RoutePredictor
from gsrmr_scheduler.planner.cadence import SampleAlignedCadence
from gsrmr_scheduler.replan_log import ReplanLog, ServiceGate, changed_slots, plan_summary, service_answer
from gsrmr_scheduler.scheduler_params import INTERFACE, PLANNING_PARAMETERS, SchedulerParameters
from gsrmr_scheduler.solve import warm_up
from gsrmr_scheduler.state_store import StateStore


class SchedulerNode(Node):
    """Online GSCLO scheduler."""

    def __init__(self, **node_kwargs) -> None:
        super().__init__("gsrmr_scheduler", **node_kwargs)
        self.params: SchedulerParameters = replace(declare_parameters(self, SchedulerParameters),
                                                   link=declare_link_budget(self))
        p = self.params
        self.clock = SlotClock(p.slot_s)
        self.store = StateStore(p.state_dir)
        # the solver's first call now, not in the first replan: the first schedule follows start-up at once
        kernel_s, method_s = warm_up(p.method, **p.options)
        self.get_logger().info(f"knapsack kernel ready in {kernel_s:.2f} s" + (
            "" if method_s is None else f"; method {p.method} ready in {method_s:.2f} s"))
        loss_map, source = self.store.initial_loss_map(p.loss_map_file, p.loss_prior)
        if source is not None:
            self.get_logger().info(f"loss map loaded from {source} ({len(loss_map.cells)} cells)")
        self.planner = OnlinePlanner(p.planner_config(loss_map), RoutePredictor(p.waypoints, p.route_speed_mps),
                                     loss_map, p.link)
        self._lock = threading.RLock()
        self._pose: Pose2D | None = None
        self._replan_reason: str | None = "start"
        self._new_loss_map: LossMap | None = None  # a loss_map_file read by the on-set check, for the post-set
        self.log = ReplanLog()
        self._pub = self.create_publisher(Float64MultiArray, "gsrmr/schedule", SCHEDULE_QOS)
        self._pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        # what is taken from the graph, and from whom (docs/security.md, "Application checks")
        self.audit = ParameterAudit(self, p.live_parameter_changes)
        self.intake = SchedulerIntake(p.max_speed_mps, p.slot_s)
        self.service_gate = ServiceGate()
        self.inputs = GatedInputs(self)
        for kind, topic, callback, qos, writers in (
                (Vector3Stamped, "uplink/pose_key", self._on_key, UPLINK_QOS, p.robot_writers),
                (Float64MultiArray, "gsrmr/loss_sample", self._on_loss, LOSS_SAMPLE_QOS, p.loss_writers),
                *([(Float64MultiArray, CHANNEL_TOPIC, self._on_channel, 10, p.channel_writers)]
                  if p.oracle_channel else []),
                (Float64MultiArray, "gsrmr/ledger", self._on_ledger, UPLINK_QOS, p.robot_writers),
                (Float64MultiArray, MR_SLOT_INFO_TOPIC, self._on_slot_info, UPLINK_QOS, p.loss_writers)):
            self.inputs.subscribe(kind, topic, callback, qos, writers, rate_hz=40.0,
                                  burst=40.0 if topic == CHANNEL_TOPIC else 60.0)
        self.create_service(Trigger, "gsrmr/replan", self._on_replan)
        self.add_on_set_parameters_callback(self._validate)
        self.add_post_set_parameters_callback(self._apply)
        self._restore()
        self.cadence = SampleAlignedCadence(p.replan_on_loss_sample)
        self._replan_timer = self.create_timer(p.replan_period_s, self._on_period)
        self.create_timer(0.02, self._tick)
        self.create_timer(1.0, self._publish_diagnostics)

    def _now_slot(self) -> int:
        return self.clock.slot_at(self.get_clock().now().nanoseconds)

    # ---------------------------------------------------------------- parameters
    def _validate(self, params: list[Parameter]) -> SetParametersResult:
        """On-set: refuse what :class:`SchedulerParameters` refuses (alone, or together: the planner's configuration,
        a loss_map_file that is no loss map), or any change while live changes are off."""
        reason = self.audit.problem(SchedulerParameters, params)
        if reason is None:
            reason, self._new_loss_map = self.params.live_change_problem({q.name: q.value for q in params},
                                                                         self.planner.loss_map)
        return SetParametersResult(successful=reason is None, reason=reason or "")

    def _apply(self, params: list[Parameter]) -> None:
        """Post-set: take the accepted values into ``self.params``; a planning one gives the planner a new
        configuration and requests a replan; ``replan_period_s`` re-times the replan timer."""
        names = {param.name for param in params}
        changed = [param.name for param in params if param.name in PLANNING_PARAMETERS]
        with self._lock:
            self.params = self.audit.applied(self.params, params)
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
    def _on_ledger(self, msg: Float64MultiArray, _gid: bytes = b"") -> None:
        """What the robot did in a slot (an in-slot decision may differ from the plan's x); a loss sample that
        waited for the row is judged now."""
        try:
            row = ledger_from_msg(msg)
        except ValueError:
            self.intake.implausible["ledger_malformed"] += 1
            return
        x, waiting = self.intake.ledger(row, self._now_slot())
        if x is None:
            return
        with self._lock:
            self.planner.record_action(row.slot, x, row.held_back, row.uplink_rate_bps, row.upload_all_bits,
                                       row.scene_change, row.correction_seq)
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

    def _on_key(self, msg: Vector3Stamped, _gid: bytes = b"") -> None:
        try:
            key = pose_key_from_msg(msg, self.clock)
        except ValueError as err:  # wrong frame or invalid stamp: ignore, never raise out of the callback
            self.intake.implausible["key_malformed"] += 1
            self.get_logger().warning(f"pose key refused: {err}", throttle_duration_sec=5.0)
            return
        if not key.is_valid() or not self.intake.key(key.slot, (key.a_m, key.b_m, key.theta_rad)):
            return
        self._pose = (key.a_m, key.b_m, key.theta_rad)
        with self._lock:
            self.planner.record_pose(key.slot, *self._pose)

    def _on_slot_info(self, msg: Float64MultiArray, _gid: bytes = b"") -> None:
        """What the server composed a slot from: the budget charges the slot by it (an image it did not have in time
        left a render's loss, not the JPEG's)."""
        try:
            info = mr_slot_info_from_msg(msg)
        except ValueError:
            self.intake.implausible["slot_info_malformed"] += 1
            return
        if self.intake.slot_info(info, self._now_slot()):
            with self._lock:
                self.planner.record_composed(info.slot, str(info.source), info.level)

    def _on_loss(self, msg: Float64MultiArray, _gid: bytes = b"") -> None:
        try:
            sample = loss_sample_from_msg(msg)
        except ValueError:
            self.intake.implausible["loss_malformed"] += 1
            return
        self._take_loss(sample)

    def _take_loss(self, sample: LossSample) -> None:
        """Observe a loss sample the intake takes; replan on drift or when the periodic replan waited for it."""
        verdict = self.intake.loss(sample)
        if isinstance(verdict, Refusal):
            self._log_refusal(verdict)
        if verdict is not True:
            return
        with self._lock:
            drift = self.planner.observe(sample.slot, sample.a_m, sample.b_m, sample.theta_rad, sample.loss)
            period = self.cadence.sample_taken()
        if drift or period:
            self._request("drift" if drift else "period")
            if self.cadence.aligned:  # now, not at the next tick: the plan should reach the robot for the next slot
                self._tick()

    def _log_refusal(self, refusal: Refusal) -> None:
        s = refusal.sample
        self.get_logger().warning(f"loss sample refused ({refusal.reason}): slot {s.slot}, loss {s.loss:.4g}",
                                  throttle_duration_sec=5.0)

    def _on_period(self) -> None:
        """The replan timer: a replan now, or right after the next loss sample (:class:`SampleAlignedCadence`)."""
        with self._lock:
            due = self.cadence.timer_fired()
        if due:
            self._request("period")

    def _request(self, reason: str) -> None:
        with self._lock:
            if self._replan_reason is None or reason != "period":
                self._replan_reason = reason

    def _tick(self) -> None:
        for refusal in self.intake.expire(self._now_slot()):
            self._log_refusal(refusal)
        reason = self._replan_reason
        if reason is not None:
            self.replan(reason)

    # ---------------------------------------------------------------- planning
    def replan(self, reason: str) -> tuple[PlanResult, int]:
        """Plan from the slot in which the plan is expected to be done (the p90 of the recent plan times from now:
        this slot for a 1-ms plan, later for a slow solver) and publish — a schedule that reaches the robot before
        that slot starts covers it too; returns the result and how many slots changed x."""
        with self._lock:
            self._replan_reason = None
            self.cadence.replanned()
            now_slot = self.clock.slot_at(self.get_clock().now().nanoseconds + self.log.expected_plan_ns())
            previous = self.planner.active
            t0 = time.perf_counter()
            result = self.planner.plan(now_slot, self._pose)
            self.log.record(reason, result, time.perf_counter() - t0,
                            (self.clock.start_ns(now_slot + 1) - self.get_clock().now().nanoseconds) / 1e9)
            changed = changed_slots(previous, result.schedule)
            self.planner.clear_drift()
        self._pub.publish(schedule_to_msg(result.schedule))
        self.store.save(result.schedule, self.planner.loss_map, self.planner.config.method, self.log.solve_times_s,
                        self.log.plan_slack_s)
        for line in (self.log.image_cap_news(self.planner),
                     f"replan ({reason}): {plan_summary(result, changed)}" if reason != "period" else None):
            if line:
                self.get_logger().info(line)
        return result, changed

    def _on_replan(self, _request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        refusal = self.service_gate.refusal(time.monotonic(), self.params.replan_min_interval_s,
                                            self.params.replan_period_s)
        if refusal:
            response.success, response.message = False, refusal
        else:
            previous = self.log.last
            response.success, response.message = service_answer(previous, *self.replan("service"))
        return response

    def _restore(self) -> None:
        """Resume the saved schedule when it still covers the next slot."""
        try:
            sched = self.store.load_schedule()
        except ValueError as err:
            self.get_logger().warning(f"saved schedule ignored: {err}")
            return
        if sched is not None and sched.lookup(self._now_slot() + 1) is not None:
            self.planner.resume(sched)
            self._pub.publish(schedule_to_msg(sched))
            self.get_logger().info(f"resumed schedule seq {sched.seq} from {self.params.state_dir}")

    # ---------------------------------------------------------------- health
    def on_shutdown(self) -> None:
        """Log what the input checks refused and the replans the service refused (called by run_node on exit)."""
        self.inputs.log_summary(self.intake.implausible, replans_refused=self.service_gate.refused,
                                **self.intake.counters())

    def _publish_diagnostics(self) -> None:
        values = self.log.diagnostic_values(self.planner, self._now_slot() + 1)
        values.update({k: json.dumps(v) if isinstance(v, dict) else v for k, v in {
            **self.inputs.diagnostic_values(), "implausible": self.intake.implausible.values_for_diagnostics(),
            **self.intake.counters(), "replans_refused": self.service_gate.refused,
            **self.audit.diagnostic_values()}.items()})
        problems = self.log.problems() + self.inputs.problems() + self.intake.problems() + self.service_gate.problems()
        self._pub_diag.publish(diagnostics_msg(self, name=f"{self.get_name()}: schedule", hardware_id="gsrmr_server",
                                               values=values, problems=problems))


@console_main
def main(args: list[str] | None = None) -> int:
    """Console script ``gsrmr-scheduler``."""
    return run_node(SchedulerNode, args, interface=INTERFACE)
