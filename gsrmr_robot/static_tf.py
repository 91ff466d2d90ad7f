"""The robot's transforms (REP-105), where ``tf2_ros`` imports (a ROS install): ``base_link →
camera_optical_frame`` from the camera mount on ``/tf_static``, and ``map → odom`` — the ``map_from_odom``
parameter as the server's corrections move it — on ``/tf``."""

from __future__ import annotations

from rclpy.node import Node

from gsrmr_common.camera import CameraMount
from gsrmr_common.pose2d import Pose2D
from gsrmr_common.tf_ros import load_tf2_ros, transform_to_msg
from gsrmr_common.tf_tree import MAP_FRAME, base_from_camera_optical_transform, map_from_odom_transform


class StaticFrames:
    """Sends the robot's transforms; without ``tf2_ros`` it logs once, at INFO, that none are published."""

    def __init__(self, node: Node, odom_frame: str, base_frame: str, camera_frame: str) -> None:
        self.node = node
        tf2_ros, why = load_tf2_ros()
        self._static = None if tf2_ros is None else tf2_ros.StaticTransformBroadcaster(node)
        self._dynamic = None if tf2_ros is None else tf2_ros.TransformBroadcaster(node)
        if tf2_ros is None:
            node.get_logger().info(f"TF not published: {why}; map → {odom_frame} and {base_frame} → {camera_frame} "
                                   "need a ROS 2 install with tf2_ros")

    @property
    def published(self) -> bool:
        """Whether the transforms go out (tf2_ros imported)."""
        return self._static is not None

    def send_mount(self, base_frame: str, camera_frame: str, mount: CameraMount) -> None:
        """(Re)send ``base_link → camera`` on /tf_static."""
        if self._static is None:
            return
        stamp = self.node.get_clock().now().to_msg()
        self._static.sendTransform([transform_to_msg(base_frame, camera_frame,
                                                     base_from_camera_optical_transform(mount), stamp)])

    def send_map_to_odom(self, map_from_odom: Pose2D, odom_frame: str) -> None:
        """``map → odom`` (``map_from_odom`` = (a_m, b_m, theta_rad)) on /tf, stamped now."""
        if self._dynamic is None:
            return
        stamp = self.node.get_clock().now().to_msg()
        self._dynamic.sendTransform(transform_to_msg(MAP_FRAME, odom_frame, map_from_odom_transform(*map_from_odom),
                                                     stamp))
