"""``gsrmr-limo-base``: thin rclpy node around :class:`~gsrmr_robot.limo.driver.LimoDriver`.

Topics and parameters: ``gsrmr-limo-base --help`` (:data:`~gsrmr_robot.limo.base_params.INTERFACE`); what it
publishes and when: ``docs/nodes.md``; the serial protocol: ``docs/limo.md``.
"""

from __future__ import annotations

from collections.abc import Callable
import json
import math
import time
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import Quaternion, TransformStamped, Twist
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.time import Time
from sensor_msgs.msg import Imu

from gsrmr_common.interrupts import console_main
from gsrmr_common.ros_admission import GatedInputs, ParameterAudit
from gsrmr_common.ros_node import declare_parameters, diagnostics_msg, run_node
from gsrmr_common.tf_ros import load_tf2_ros, tf_message_type
from gsrmr_robot.limo import protocol as proto
from gsrmr_robot.limo.base_params import INTERFACE, LimoBaseParameters
from gsrmr_robot.limo.driver import DriverSnapshot, ImuSample, LimoDriver

BATTERY_WARN_V = 10.5  # 3S Li-ion pack, 12 V nominal: warn below 3.5 V/cell


def yaw_pitch_roll_to_quaternion(yaw: float, pitch: float, roll: float) -> Quaternion:
    """ZYX (yaw, then pitch, then roll) Euler angles [rad] → geometry_msgs/Quaternion."""
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    return Quaternion(w=cr * cp * cy + sr * sp * sy, x=sr * cp * cy - cr * sp * sy,
                      y=cr * sp * cy + sr * cp * sy, z=cr * cp * sy - sr * sp * cy)


class LimoBaseNode(Node):
    """cmd_vel → LIMO; odom, imu, diagnostics ← LIMO."""

    def __init__(self) -> None:
        super().__init__("gsrmr_limo_base")
        self.params: LimoBaseParameters = declare_parameters(self, LimoBaseParameters)
        p = self.params
        self.odom_frame, self.base_frame, self.imu_frame = p.odom_frame_id, p.base_frame_id, p.imu_frame_id
        self.publish_tf = p.publish_tf
        self.audit = ParameterAudit(self, p.live_parameter_changes)
        self.add_on_set_parameters_callback(self._validate)
        self.add_post_set_parameters_callback(self._after_set)

        self._odom_pub = self.create_publisher(Odometry, "odom", 10)
        self._imu_pub = self.create_publisher(Imu, "imu", 10)
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._send_tf: Callable[[TransformStamped], None] | None = None
        if self.publish_tf:
            self._send_tf = self._tf_sender()
        self.inputs = GatedInputs(self)
        self.inputs.subscribe(Twist, "cmd_vel", self._on_cmd_vel, 10, p.cmd_vel_writers, rate_hz=200.0, burst=100.0)

        self.driver = LimoDriver(p.port, p.baud, command_rate_hz=p.command_rate_hz, cmd_timeout_s=p.cmd_timeout_s,
                                 motion_mode=p.motion_mode, heading_source=p.heading_source, limits=p.limits,
                                 on_event=self._on_event)
        self.driver.on_odometry = self._publish_odom
        self.driver.on_imu = self._publish_imu
        self._alive = True
        self.create_timer(p.diagnostics_period_s, self._publish_diagnostics)
        self.driver.start()
        self.get_logger().info(f"LIMO base on {p.port} @ {p.baud} Bd, mode {p.motion_mode}, heading "
                               f"{p.heading_source}, commands {p.command_rate_hz:g} Hz, timeout {p.cmd_timeout_s:g} s")

    def _tf_sender(self) -> Callable[[TransformStamped], None] | None:
        """Where odom → base_link goes: tf2_ros's broadcaster, else a raw /tf publisher, else nowhere."""
        tf2_ros, why = load_tf2_ros()
        if tf2_ros is not None:
            return tf2_ros.TransformBroadcaster(self).sendTransform
        TFMessage, why_msgs = tf_message_type()
        if TFMessage is None:
            self.get_logger().warning(f"publish_tf is true but {why} and {why_msgs}: no TF published")
            return None
        pub = self.create_publisher(TFMessage, "/tf", 100)  # what TransformBroadcaster does
        return lambda tf: pub.publish(TFMessage(transforms=[tf]))

    # ---------------------------------------------------------------- parameters
    def _validate(self, params: list) -> SetParametersResult:
        """On-set: refuse a change :class:`LimoBaseParameters` gives a reason for (read-only, type, range, an
        unknown mode or heading source); change nothing."""
        reason = self.audit.problem(LimoBaseParameters, params)
        return SetParametersResult(successful=reason is None, reason=reason or "")

    def _after_set(self, params: list) -> None:
        """Post-set: take the accepted values and hand a new motion mode or heading source to the driver."""
        old = self.params
        self.params = self.audit.applied(old, params)
        if not hasattr(self, "driver"):  # start-up overrides: the driver is built from self.params
            return
        if self.params.motion_mode != old.motion_mode:
            self.driver.set_motion_mode(self.params.motion_mode)
        if self.params.heading_source != old.heading_source:
            self.driver.set_heading_source(self.params.heading_source)

    # ---------------------------------------------------------------- callbacks
    def _on_cmd_vel(self, msg: Twist, _gid: bytes = b"") -> None:
        self.driver.set_command(msg.linear.x, msg.angular.z, msg.linear.y)

    def _on_event(self, level: str, text: str) -> None:
        # one call site per severity: rclpy refuses a severity change at the same call site
        log = self.get_logger()
        if level == "info":
            log.info(text)
        elif level == "warn":
            log.warning(text)
        else:
            log.error(text)

    def _stamp(self, t_mono_s: float, now_mono_s: float):
        """ROS time of a host-monotonic instant (receive time of a frame)."""
        now = self.get_clock().now()
        return Time(nanoseconds=now.nanoseconds - int((now_mono_s - t_mono_s) * 1e9)).to_msg()

    def _publish_odom(self, snap: DriverSnapshot) -> None:
        if not self._alive:
            return
        msg = Odometry()
        t_rx = snap.link.last_rx_t_s if snap.link.last_rx_t_s is not None else snap.t_s
        msg.header.stamp = self._stamp(t_rx, snap.t_s)
        msg.header.frame_id = self.odom_frame
        msg.child_frame_id = self.base_frame
        msg.pose.pose.position.x = snap.pose.x_m
        msg.pose.pose.position.y = snap.pose.y_m
        msg.pose.pose.orientation = yaw_pitch_roll_to_quaternion(snap.pose.theta_rad, 0.0, 0.0)
        msg.pose.covariance = snap.pose_covariance
        msg.twist.twist.linear.x = snap.velocity.vx_mps
        msg.twist.twist.linear.y = snap.velocity.vy_mps
        msg.twist.twist.angular.z = snap.velocity.wz_radps
        msg.twist.covariance = snap.twist_covariance
        self._publish(self._odom_pub, msg)
        if self._send_tf is not None:
            tf = TransformStamped()
            tf.header = msg.header
            tf.child_frame_id = self.base_frame
            tf.transform.translation.x = snap.pose.x_m
            tf.transform.translation.y = snap.pose.y_m
            tf.transform.rotation = msg.pose.pose.orientation
            self._guarded(self._send_tf, tf)

    def _publish(self, pub, msg) -> None:
        """Publish from the driver's io thread; silent once the context is shutting down (SIGINT)."""
        self._guarded(pub.publish, msg)

    def _guarded(self, send: Callable[[Any], None], msg: Any) -> None:
        """``send(msg)`` unless the node or its context is shutting down (a publish then may raise)."""
        if not self._alive or not self.context.ok():
            return
        try:
            send(msg)
        except Exception:
            if self.context.ok():
                raise

    def _publish_imu(self, sample: ImuSample) -> None:
        if not self._alive:
            return
        msg = Imu()
        msg.header.stamp = self._stamp(sample.t_s, time.monotonic())
        msg.header.frame_id = self.imu_frame
        e = sample.euler
        msg.orientation = yaw_pitch_roll_to_quaternion(e.yaw_rad, e.pitch_rad, e.roll_rad)
        msg.orientation_covariance = _diag3(math.radians(1.0) ** 2)
        if sample.gyro is not None:
            g = sample.gyro
            msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z = g.x_radps, g.y_radps, g.z_radps
            msg.angular_velocity_covariance = _diag3(math.radians(0.5) ** 2)
        else:
            msg.angular_velocity_covariance = [-1.0] + [0.0] * 8
        if sample.accel is not None:
            a = sample.accel
            msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z = (
                a.x_mps2, a.y_mps2, a.z_mps2)
            msg.linear_acceleration_covariance = _diag3(0.1 ** 2)
        else:
            msg.linear_acceleration_covariance = [-1.0] + [0.0] * 8
        self._publish(self._imu_pub, msg)

    def _publish_diagnostics(self) -> None:
        snap = self.driver.snapshot()
        level, problems = diagnose(snap)
        refused = self.inputs.problems()
        if refused:  # a stranger's cmd_vel ignored: a warning, however well the base runs
            level, problems = max(level, DiagnosticStatus.WARN), problems + refused
        values = dict(diagnostic_values(snap))
        values.update({k: json.dumps(v) if isinstance(v, dict) else str(v) for k, v in
                       {**self.inputs.diagnostic_values(), **self.audit.diagnostic_values()}.items()})
        self._diag_pub.publish(diagnostics_msg(self, name="gsrmr_limo_base: LIMO base", hardware_id=snap.link.port,
                                               values=values, level=level,
                                               message="; ".join(problems) if problems else "OK"))

    def on_shutdown(self) -> None:
        """Stop the base and the driver threads (called by run_node before destroy_node); log the refused cmd_vel."""
        self._alive = False
        self.driver.close()
        self.inputs.log_summary()


def _diag3(var: float) -> list[float]:
    return [var, 0.0, 0.0, 0.0, var, 0.0, 0.0, 0.0, var]


def diagnose(snap: DriverSnapshot, stale_after_s: float = 0.5) -> tuple[bytes, list[str]]:
    """(DiagnosticStatus level, problem texts) for a driver snapshot."""
    problems: list[str] = []
    level = DiagnosticStatus.OK
    def worse(new: bytes) -> None:
        nonlocal level
        level = max(level, new)
    if not snap.link.connected:
        worse(DiagnosticStatus.ERROR)
        problems.append(f"serial link down ({snap.link.last_error})")
    elif snap.link.last_rx_t_s is None or snap.t_s - snap.link.last_rx_t_s > stale_after_s:
        worse(DiagnosticStatus.ERROR)
        problems.append("no data from the base")
    s = snap.system_state
    if s is None:
        worse(DiagnosticStatus.WARN)
        problems.append("no 0x211 system state yet")
    else:
        if s.vehicle_state != proto.VehicleState.NORMAL:
            worse(DiagnosticStatus.ERROR)
            problems.append(f"vehicle state {_enum_name(proto.VehicleState, s.vehicle_state)}")
        if s.control_mode != proto.ControlMode.COMMANDED:
            worse(DiagnosticStatus.WARN)
            problems.append(f"control mode {_enum_name(proto.ControlMode, s.control_mode)} (not commanded)")
        errors = s.errors
        if errors:
            fatal = s.error_code & ~0x0002
            worse(DiagnosticStatus.ERROR if fatal else DiagnosticStatus.WARN)
            problems.append("errors: " + ", ".join(errors))
        if s.battery_voltage_v < BATTERY_WARN_V:
            worse(DiagnosticStatus.WARN)
            problems.append(f"battery {s.battery_voltage_v:.1f} V")
    if snap.motion_mode == proto.MotionMode.UNKNOWN:
        worse(DiagnosticStatus.WARN)
        problems.append("motion mode unknown: commands held at zero")
    return level, problems


def _enum_name(enum_cls, value: int) -> str:
    try:
        return enum_cls(value).name.lower()
    except ValueError:
        return f"0x{value:02x}"


def diagnostic_values(snap: DriverSnapshot) -> list[tuple[str, str]]:
    """Key/value pairs published in /diagnostics."""
    s = snap.system_state
    vals = [("link_connected", str(snap.link.connected)), ("port", snap.link.port),
            ("connects", str(snap.link.connects)), ("reconnects", str(max(0, snap.link.connects - 1))),
            ("disconnects", str(snap.link.disconnects)), ("failed_opens", str(snap.link.failed_opens)),
            ("last_link_error", snap.link.last_error),
            ("motion_mode", _enum_name(proto.MotionMode, snap.motion_mode)),
            ("motion_mode_param", snap.motion_mode_param),
            ("heading_source", "imu" if snap.heading_from_imu else "gyro_integration"),
            ("command_active", str(snap.command_active)), ("commands_sent", str(snap.commands_sent)),
            ("enables_sent", str(snap.enables_sent)), ("implausible_frames", str(snap.implausible_frames)),
            ("write_timeouts", str(snap.write_timeouts))]
    if s is not None:
        vals += [("battery_voltage_v", f"{s.battery_voltage_v:.1f}"),
                 ("vehicle_state", _enum_name(proto.VehicleState, s.vehicle_state)),
                 ("control_mode", _enum_name(proto.ControlMode, s.control_mode)),
                 ("base_motion_mode", _enum_name(proto.MotionMode, s.motion_mode)),
                 ("error_code", f"0x{s.error_code:04x}"), ("errors", ",".join(s.errors) or "none")]
    vals += [(f"parser_{k}", str(v)) for k, v in snap.parser.items()]
    vals += [("unknown_ids", ",".join(f"0x{k:03x}:{v}" for k, v in sorted(snap.unknown_ids.items())) or "none")]
    vals += [(f"frames_0x{k:03x}", str(v)) for k, v in sorted(snap.frames_by_id.items())]
    return vals


@console_main
def main(args: list[str] | None = None) -> int:
    """Console script ``gsrmr-limo-base``."""
    return run_node(LimoBaseNode, args, interface=INTERFACE)
