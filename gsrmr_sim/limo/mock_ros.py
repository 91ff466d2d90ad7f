"""ROS side of the mock LIMO: publishes its true pose for the simulated camera.

``sim/ground_truth/odom`` ``nav_msgs/Odometry`` (relative: ``/sim/ground_truth/odom`` in the root namespace,
``/robot2/sim/ground_truth/odom`` for robot 2 of a fleet): header.frame_id ``map``, child_frame_id
``base_link`` (REP-103: x forward, y left, yaw CCW; metres, radians), twist in ``base_link``,
published at the mock's stream rate (50 Hz), reliable QoS, depth 10.
"""

from __future__ import annotations

import math

from nav_msgs.msg import Odometry
from rclpy.node import Node

from gsrmr_common.ros_node import run_node
from gsrmr_sim.limo.mock import MockLimo

GROUND_TRUTH_TOPIC = "sim/ground_truth/odom"  # = gsrmr_sim.sim_stack.GROUND_TRUTH_TOPIC


class GroundTruthPublisher(Node):
    """Publishes ``MockLimo.true_pose()`` as nav_msgs/Odometry."""

    def __init__(self, mock: MockLimo) -> None:
        super().__init__("gsrmr_mock_limo")
        self.mock = mock
        self._pub = self.create_publisher(Odometry, GROUND_TRUTH_TOPIC, 10)
        self.create_timer(1.0 / mock.rate_hz, self._tick)
        self.get_logger().info(f"mock LIMO on {mock.link_path}; true pose on {self._pub.topic_name}")

    def _tick(self) -> None:
        x, y, yaw = self.mock.true_pose()
        v = self.mock.true_velocity()
        msg = Odometry()
        msg.header.stamp = self.get_clock().now().to_msg()
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


def run_ground_truth_node(mock: MockLimo, args: list[str]) -> int:
    """Spin a :class:`GroundTruthPublisher` until SIGINT (the caller closes the mock)."""
    return run_node(lambda: GroundTruthPublisher(mock), args)
