"""What the robot takes from the workstation and its radio, on the graph: schedules, channel gains and map → odom
corrections, each from its admitted writers and checked (:mod:`gsrmr_robot.robot_inputs`,
:mod:`gsrmr_robot.map_source`); refusals are counted in the node's ``implausible``. ROS side of those cores."""

from __future__ import annotations

from collections.abc import Callable
import math
import threading

from rclpy.node import Node
from std_msgs.msg import Float64MultiArray

from gsrmr_common.link_model import LinkBudget
from gsrmr_common.plausibility import Implausible, ScheduleLimits
from gsrmr_common.pose2d import Pose2D
from gsrmr_common.ros_admission import GatedInputs
from gsrmr_common.ros_wire import (
    CAMERA_INFO_QOS,
    SCHEDULE_QOS,
    channel_sample_from_msg,
    map_correction_from_msg,
    schedule_from_msg,
)
from gsrmr_common.slot_clock import SlotClock
from gsrmr_common.wire import CHANNEL_TOPIC, MAP_CORRECTION_TOPIC, MapCorrection
from gsrmr_robot.map_source import CorrectionLimits, MapSource
from gsrmr_robot.robot_inputs import REPEAT, ChannelGains, ScheduleInbox
from gsrmr_robot.robot_params import RobotParameters


class WorkstationInputs:
    """Subscribes the robot's inputs from the workstation and the radio; ``lock`` guards what the slot reads;
    ``position`` gives the robot's latest (x, y) in map (the gain band's centre); ``applied`` is called (holding the
    lock) with each correction put in force."""

    def __init__(self, node: Node, inputs: GatedInputs, params: RobotParameters, link: LinkBudget,
                 clock: SlotClock, lock: threading.Lock, implausible: Implausible,
                 position: Callable[[], tuple[float, float] | None],
                 applied: Callable[[MapCorrection], None] = lambda _c: None) -> None:
        self.node, self.inputs, self.clock, self._lock, self.implausible = node, inputs, clock, lock, implausible
        self.position, self.applied = position, applied
        self.schedules = ScheduleInbox(params.slot_s, ScheduleLimits(max_power_w=params.max_tx_power_w), implausible)
        self.gains = ChannelGains(link, implausible)
        limits = CorrectionLimits(max_step_m=params.max_correction_step_m,
                                  max_step_rad=math.radians(params.max_correction_step_deg))
        self.maps = MapSource(Pose2D.of(params.map_from_odom), limits, implausible)
        inputs.subscribe(Float64MultiArray, CHANNEL_TOPIC, lambda msg, _gid: self._on_channel(msg), 10,
                         params.channel_writers, rate_hz=40.0, burst=40.0)
        # a schedule's and a correction's seq must grow per writer endpoint: their callbacks take the GID
        inputs.subscribe(Float64MultiArray, "gsrmr/schedule", self._on_schedule, SCHEDULE_QOS,
                         params.schedule_writers, rate_hz=20.0, burst=20.0)
        if params.localization == "server":  # latched, as the schedule: a robot started later gets the last one
            inputs.subscribe(Float64MultiArray, MAP_CORRECTION_TOPIC, self._on_correction, CAMERA_INFO_QOS,
                             params.correction_writers, rate_hz=10.0, burst=10.0)

    def _warn(self, text: str) -> None:
        self.node.get_logger().warning(text, throttle_duration_sec=5.0)

    def _on_channel(self, msg: Float64MultiArray) -> None:
        try:
            sample = channel_sample_from_msg(msg)
        except ValueError as err:
            self._warn(f"channel sample refused: {err}")
            return
        with self._lock:
            reason = self.gains.offer(sample, self.position())
        if reason:
            self._warn(f"channel sample refused ({reason}): gain {sample.gain:.3g} for slot {sample.slot}")

    def _on_schedule(self, msg: Float64MultiArray, gid: bytes = b"") -> None:
        """A schedule: refused (counted) when malformed, of another τ, implausible (T, slots, powers) or not newer
        than the last one of the same writer endpoint (seq)."""
        try:
            sched = schedule_from_msg(msg)
        except ValueError as err:
            self.implausible["schedule_malformed"] += 1
            self.node.get_logger().error(f"schedule refused: {err}", throttle_duration_sec=5.0)
            return
        with self._lock:  # the one before stays for the slots the new one starts after (one that began)
            reason = self.schedules.offer(sched, gid, self.clock.slot_at(self.node.get_clock().now().nanoseconds))
        if reason not in (None, REPEAT):
            writer = self.inputs.writer_of("gsrmr/schedule", gid)
            self._warn(f"schedule seq {sched.seq} refused ({reason}) from {writer}")

    def _on_correction(self, msg: Float64MultiArray, gid: bytes = b"") -> None:
        """A map → odom correction: refused (counted, the writer named) when malformed, a replay, or too large."""
        try:
            correction = map_correction_from_msg(msg)
        except ValueError as err:
            self.implausible["correction_malformed"] += 1
            self._warn(f"map correction refused: {err}")
            return
        with self._lock:
            reason = self.maps.offer(correction, gid)
            if reason is None and self.maps.seq == correction.seq:
                self.applied(correction)
        if reason:
            self._warn(f"map correction seq {correction.seq} refused ({reason}) from "
                       f"{self.inputs.writer_of(MAP_CORRECTION_TOPIC, gid)}")
