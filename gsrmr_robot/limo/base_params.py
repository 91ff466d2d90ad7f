"""The LIMO base node's parameters (:class:`LimoBaseParameters`): names, defaults, descriptors and rules (pure).

:class:`gsrmr_robot.limo.node.LimoBaseNode` declares them, refuses a change :meth:`LimoBaseParameters.change_problem`
gives a reason for and hands an accepted one to the driver; live ones only with ``live_parameter_changes``.
``cmd_vel_writers``: ``docs/security.md``, "cmd_vel".
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from gsrmr_common.node_help import Endpoint, NodeInterface, ParameterGroup
from gsrmr_common.node_params import NodeParameters, ros_parameter
from gsrmr_common.writer_admission import writer_list_problem
from gsrmr_robot.limo import kinematics as kin
from gsrmr_robot.limo.odometry import HEADING_SOURCES

MOTION_MODES = ("auto", "diff", "ackermann", "mecanum")


@dataclass(frozen=True)
class LimoBaseParameters(NodeParameters):
    """Every parameter of the LIMO base node (ROS names; units in the names)."""

    port: str = ros_parameter("/dev/ttyTHS1", "Serial device path or any pyserial URL (e.g. /tmp/limo, "
                              "rfc2217://host:port)", read_only=True)
    baud: int = ros_parameter(460800, "Baud rate (LIMO: 460800, 8N1)", min_value=1200, max_value=4_000_000,
                              read_only=True)
    command_rate_hz: float = ros_parameter(50.0, "0x111 streaming rate [Hz]", min_value=1.0, max_value=200.0,
                                           read_only=True)
    cmd_timeout_s: float = ros_parameter(0.5, "cmd_vel older than this stops the base [s]", min_value=0.05,
                                         max_value=5.0, read_only=True)
    motion_mode: str = ros_parameter("auto", "auto (from 0x211) | diff | ackermann | mecanum",
                                     constraints="one of " + ", ".join(MOTION_MODES))
    heading_source: str = ros_parameter("imu", "Odometry heading: imu (0x323 yaw) | gyro_integration (0x221 wz)",
                                        constraints="one of " + ", ".join(HEADING_SOURCES))
    odom_frame_id: str = ros_parameter("odom", "Odometry parent frame", read_only=True)
    base_frame_id: str = ros_parameter("base_link", "Robot body frame", read_only=True)
    imu_frame_id: str = ros_parameter("imu_link", "IMU frame", read_only=True)
    publish_tf: bool = ros_parameter(False, "Also publish odom → base_link on /tf", read_only=True)
    max_linear_mps: float = ros_parameter(1.0, "Clamp on |linear.x| and |linear.y| [m/s]", min_value=0.0,
                                          max_value=1.0, read_only=True)
    max_angular_radps: float = ros_parameter(kin.DEFAULT_LIMITS.max_angular_radps, "Clamp on |angular.z| [rad/s]",
                                             min_value=0.0, max_value=20.0, read_only=True)
    diagnostics_period_s: float = ros_parameter(1.0, "Diagnostics publishing period [s]", min_value=0.1,
                                                max_value=10.0, read_only=True)
    cmd_vel_writers: tuple[str, ...] = ros_parameter(
        ("*",), "Nodes the base takes cmd_vel from (relative names resolve in its namespace): the planner, or a "
        "twist_mux in front of several; * = any node, as a plain ROS base", read_only=True)
    live_parameter_changes: bool = ros_parameter(
        False, "Allow motion_mode and heading_source to change while the node runs (any participant may call the "
        "parameter service without SROS2; every change is logged)", read_only=True)

    @classmethod
    def rule(cls, name: str, value: Any) -> str | None:
        """``motion_mode`` and ``heading_source`` are one of their names; ``cmd_vel_writers`` names nodes."""
        if name == "motion_mode" and value not in MOTION_MODES:
            return f"motion_mode must be one of {MOTION_MODES}"
        if name == "heading_source" and value not in HEADING_SOURCES:
            return f"heading_source must be one of {HEADING_SOURCES}"
        if name == "cmd_vel_writers":
            return writer_list_problem(name, value)
        return None

    @property
    def limits(self) -> kin.Limits:
        """The command clamps (m/s, rad/s)."""
        return kin.Limits(max_linear_mps=self.max_linear_mps, max_lateral_mps=self.max_linear_mps,
                          max_angular_radps=self.max_angular_radps)


#: What ``gsrmr-limo-base --help`` prints.
INTERFACE = NodeInterface(
    executable="gsrmr-limo-base", node="gsrmr_limo_base",
    summary="The AgileX LIMO base driver: drives the base over its serial link from cmd_vel and publishes wheel "
            "odometry (REP-105 odom → base_link), the IMU and the base's health.",
    subscribes=(Endpoint("cmd_vel", "geometry_msgs/msg/Twist", "base_link, m/s and rad/s"),),
    publishes=(Endpoint("odom", "nav_msgs/msg/Odometry", "odom → base_link"),
               Endpoint("imu", "sensor_msgs/msg/Imu"),
               Endpoint("/tf", "tf2_msgs/msg/TFMessage", "odom → base_link, with publish_tf"),
               Endpoint("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")),
    parameters=(ParameterGroup(LimoBaseParameters),))
