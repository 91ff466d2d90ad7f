"""``gsrmr-route-follower``: drive the scene's route loop by publishing cmd_vel (pure pursuit).

Topics and ``wait_for_server``: docs/world.md, "Nodes"; parameters: :class:`RouteFollowerParameters`.
``cmd_vel`` is a geometry_msgs/Twist in the robot frame: linear.x in m/s, angular.z in rad/s.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass

from geometry_msgs.msg import Twist
from nav_msgs.msg import Odometry
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from std_msgs.msg import Float64MultiArray, Int32

from gsrmr_common.interrupts import console_main
from gsrmr_common.node_help import Endpoint, NodeInterface, ParameterGroup
from gsrmr_common.node_params import NodeParameters, ros_parameter
from gsrmr_common.pose2d import Pose2D, yaw_from_quaternion
from gsrmr_common.ros_node import declare_parameters, run_node
from gsrmr_common.ros_wire import UPLINK_QOS
from gsrmr_common.route import LoopPath, PurePursuit, laps_completed
from gsrmr_common.wire import MR_SLOT_INFO_TOPIC
from gsrmr_sim.world.scene import load_scene


@dataclass(frozen=True)
class RouteFollowerParameters(NodeParameters):
    """The route follower's parameters."""

    scene: str = ros_parameter("sandbox", "Scene name (config/scenes) or YAML path: its route", read_only=True)
    odom_topic: str = ros_parameter("odom", "Pose feedback (nav_msgs/Odometry)", read_only=True)
    laps: int = ros_parameter(2, "Stop after this many laps (0 = never)", min_value=0, read_only=True)
    rate_hz: float = ros_parameter(20.0, "Control rate [Hz]", min_value=1.0, max_value=200.0, read_only=True)
    speed_mps: float = ros_parameter(0.0, "Nominal speed [m/s] (0 = the route's)", min_value=0.0, max_value=2.0,
                                     read_only=True)
    wait_for_server: bool = ros_parameter(False, f"Hold still until the server composes its first slot "
                                          f"({MR_SLOT_INFO_TOPIC})", read_only=True)


#: What ``gsrmr-route-follower --help`` prints.
INTERFACE = NodeInterface(
    executable="gsrmr-route-follower", node="gsrmr_route_follower",
    summary="Drives the scene's route loop by pure pursuit, counting laps.",
    subscribes=(Endpoint("odom", "nav_msgs/msg/Odometry", "odom_topic"),
                Endpoint(MR_SLOT_INFO_TOPIC, "std_msgs/msg/Float64MultiArray", "with wait_for_server")),
    publishes=(Endpoint("cmd_vel", "geometry_msgs/msg/Twist", "base_link, m/s and rad/s"),
               Endpoint("sim/route/lap", "std_msgs/msg/Int32", "laps completed")),
    parameters=(ParameterGroup(RouteFollowerParameters),))


class RouteFollower(Node):
    """Pure pursuit around the scene's route; counts laps and stops after ``laps``."""

    def __init__(self) -> None:
        super().__init__("gsrmr_route_follower")
        p = declare_parameters(self, RouteFollowerParameters)
        scene = load_scene(p.scene)
        odom_topic, self.max_laps, rate, wait_for_server = p.odom_topic, p.laps, p.rate_hz, p.wait_for_server
        speed = p.speed_mps or scene.route.speed_mps
        self.path = LoopPath(scene.route.waypoints)
        self.ctrl = PurePursuit(speed, scene.route.lookahead_m, scene.route.max_omega_rps)
        self.pub = self.create_publisher(Twist, "cmd_vel", 10)
        self.pub_lap = self.create_publisher(Int32, "sim/route/lap", 10)
        self.create_subscription(Odometry, odom_topic, self._on_odom, qos_profile_sensor_data)
        self.server_composing = not wait_for_server
        self._server_sub = None
        if wait_for_server:
            self._server_sub = self.create_subscription(Float64MultiArray, MR_SLOT_INFO_TOPIC, self._on_slot_info,
                                                        UPLINK_QOS)
        self.pose: Pose2D | None = None
        self.s0: float | None = None
        self.s = 0.0
        self.laps = 0
        self.done = False
        self.create_timer(1.0 / rate, self._tick)
        self.get_logger().info(f"route follower: {self.path.length_m:.2f} m loop of scene {scene.name}, "
                               f"{self.max_laps or 'unlimited'} laps, odom from {odom_topic}"
                               + (f"; sets off once {MR_SLOT_INFO_TOPIC} has a slot" if wait_for_server else ""))

    def _on_slot_info(self, _msg: Float64MultiArray) -> None:
        if not self.server_composing:
            self.server_composing = True
            self.get_logger().info("the server composes: setting off")
        if self._server_sub is not None:
            self.destroy_subscription(self._server_sub)
            self._server_sub = None

    def _on_odom(self, msg: Odometry) -> None:
        q = msg.pose.pose.orientation
        p = msg.pose.pose.position
        self.pose = Pose2D(p.x, p.y, yaw_from_quaternion(q.x, q.y, q.z, q.w))
        if self.s0 is None:
            self.s0 = self.path.project(self.pose[0], self.pose[1], 0.0, window_m=self.path.length_m)
            self.s = self.s0

    def _tick(self) -> None:
        if self.pose is None or self.s0 is None:
            return
        cmd = Twist()
        if not self.server_composing:
            self.pub.publish(cmd)  # held still (a zero Twist keeps the base's command watchdog fed)
            return
        if not self.done:
            v, w, self.s = self.ctrl.command(self.path, self.pose, self.s)
            laps = laps_completed(self.s - self.s0, self.path.length_m)
            if laps != self.laps:
                self.laps = laps
                self.pub_lap.publish(Int32(data=laps))
                self.get_logger().info(f"lap {laps} completed")
            if self.max_laps and self.laps >= self.max_laps:
                self.done = True
                self.get_logger().info(f"route complete after {self.laps} laps; stopping")
            else:
                cmd.linear.x, cmd.angular.z = float(v), float(w)
        self.pub.publish(cmd)

    def on_shutdown(self) -> None:
        """Leave the robot stopped."""
        with contextlib.suppress(Exception):
            self.pub.publish(Twist())


@console_main
def main(args: list[str] | None = None) -> int:
    """Console script ``gsrmr-route-follower``."""
    return run_node(RouteFollower, args, interface=INTERFACE)


if __name__ == "__main__":
    raise SystemExit(main())
