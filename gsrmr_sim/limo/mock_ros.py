"""``gsrmr-mock-limo``: the mock LIMO base (:mod:`gsrmr_sim.limo.mock`) as a process, publishing its true pose.

:data:`~gsrmr_sim.limo.mock.GROUND_TRUTH_TOPIC` (relative: ``/robot2/sim/ground_truth/odom`` for robot 2 of a fleet),
``nav_msgs/Odometry``: frame ``map``, child ``base_link`` (REP-103: x forward, y left, yaw CCW; metres, radians),
twist in ``base_link``, at the mock's stream rate (50 Hz), reliable QoS, depth 10.
"""

from __future__ import annotations

import math
from pathlib import Path
import signal
import sys
import threading

from nav_msgs.msg import Odometry
from rclpy.node import Node
from rclpy.time import Time

from gsrmr_common.interrupts import console_main
from gsrmr_common.node_help import Endpoint, NodeInterface, format_help, wants_help
from gsrmr_common.ros_node import run_node
from gsrmr_sim.limo.mock import GROUND_TRUTH_TOPIC, MockLimo, build_parser, mock_from_args

#: What ``gsrmr-mock-limo --help`` prints after its own arguments.
INTERFACE = NodeInterface(
    executable="gsrmr-mock-limo", node="gsrmr_mock_limo", arguments="--link PATH [options]",
    summary="The mock LIMO base on a pty (the LIMO serial protocol, byte-exact), publishing its true pose.",
    publishes=(Endpoint(GROUND_TRUTH_TOPIC, "nav_msgs/msg/Odometry", "the true pose: map → base_link, 50 Hz"),))


class GroundTruthPublisher(Node):
    """Publishes ``MockLimo.true_pose()`` as nav_msgs/Odometry."""

    def __init__(self, mock: MockLimo, truth_log: str = "", **node_kwargs) -> None:
        super().__init__("gsrmr_mock_limo", **node_kwargs)
        self.mock = mock
        if truth_log:
            Path(truth_log).parent.mkdir(parents=True, exist_ok=True)
        self._log = open(truth_log, "w", buffering=1 << 16) if truth_log else None  # noqa: SIM115 (closed on exit)
        if self._log is not None:
            self._log.write("stamp_ns,x_m,y_m,yaw_rad,tick_late_ms\n")
        self._pub = self.create_publisher(Odometry, GROUND_TRUTH_TOPIC, 10)
        self.create_timer(1.0 / mock.rate_hz, self._tick)
        self.get_logger().info(f"mock LIMO on {mock.link_path}; true pose on {self._pub.topic_name}")

    def _tick(self) -> None:
        stamp_ns, (x, y, yaw) = self.mock.true_pose_stamped()
        stamp_ns = stamp_ns or self.get_clock().now().nanoseconds
        v = self.mock.true_velocity()
        msg = Odometry()
        # stamped with the time the pose is true at (the mock's integration tick, up to one tick before now),
        # so the mock camera renders each frame at exactly the pose its stamp names
        msg.header.stamp = Time(nanoseconds=stamp_ns).to_msg()
        msg.header.frame_id = "map"
        msg.child_frame_id = "base_link"
        msg.pose.pose.position.x = x
        msg.pose.pose.position.y = y
        msg.pose.pose.orientation.z = math.sin(yaw / 2)
        msg.pose.pose.orientation.w = math.cos(yaw / 2)
        msg.twist.twist.linear.x = v.vx_mps
        msg.twist.twist.linear.y = v.vy_mps
        msg.twist.twist.angular.z = v.wz_radps
        self._pub.publish(msg)
        if self._log is not None:
            late_s = self.mock.take_tick_lateness_s()  # its ticks' since the last row (nan: none)
            self._log.write(f"{stamp_ns},{x!r},{y!r},{yaw!r},{math.nan if late_s is None else 1e3 * late_s!r}\n")

    def on_shutdown(self) -> None:
        """Close the truth log (called by run_node on exit)."""
        if self._log is not None:
            self._log.close()


def _wait_for_a_signal() -> None:
    """Block until SIGINT or SIGTERM (the ``--no-ros`` run: nothing spins)."""
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    while not stop.wait(0.2):
        pass


@console_main
def main(argv: list[str] | None = None) -> int:
    """Console script ``gsrmr-mock-limo`` (arguments: :func:`gsrmr_sim.limo.mock.build_parser`; the rest are
    ROS arguments)."""
    argv = list(sys.argv if argv is None else argv)
    if wants_help(argv):
        print(build_parser().format_help())
        print(format_help(INTERFACE), end="")
        return 0
    ns, rest = build_parser().parse_known_args(argv[1:])
    mock = mock_from_args(ns).start()
    print(f"mock LIMO ready: {mock.link_path} -> {mock.slave_name}", flush=True)
    try:
        if ns.ros:
            return run_node(lambda: GroundTruthPublisher(mock, ns.truth_log), [argv[0], *rest], interface=INTERFACE)
        _wait_for_a_signal()
        return 0
    finally:
        mock.close()
        print("mock LIMO stopped", flush=True)
