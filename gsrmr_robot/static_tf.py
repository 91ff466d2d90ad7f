"""The robot's static transforms on ``/tf_static`` (REP-105): ``map → odom`` from ``map_from_odom`` and
``base_link → camera_optical_frame`` from the camera mount, where ``tf2_ros`` imports (a ROS install)."""

from __future__ import annotations

from rclpy.node import Node

from gsrmr_common.camera import CameraMount
from gsrmr_common.tf_ros import load_tf2_ros, transform_to_msg
from gsrmr_common.tf_tree import MAP_FRAME, base_from_camera_optical_transform, map_from_odom_transform


class StaticFrames:
    """Sends the robot's static transforms; without ``tf2_ros`` it logs once, at INFO, that none are published."""

    def __init__(self, node: Node, odom_frame: str, base_frame: str, camera_frame: str) -> None:
        self.node = node
        tf2_ros, why = load_tf2_ros()
        self._broadcaster = None if tf2_ros is None else tf2_ros.StaticTransformBroadcaster(node)
        if tf2_ros is None:
            node.get_logger().info(f"TF not published: {why}; map → {odom_frame} and {base_frame} → {camera_frame} "
                                   "need a ROS 2 install with tf2_ros")

    @property
    def published(self) -> bool:
        """Whether the transforms go out (tf2_ros imported)."""
        return self._broadcaster is not None

    def send(self, map_from_odom: tuple[float, ...], odom_frame: str, base_frame: str, camera_frame: str,
             mount: CameraMount) -> None:
        """(Re)send ``map → odom`` (``map_from_odom`` = (a_m, b_m, theta_rad)) and ``base_link → camera``, both in one
        message: rclpy's StaticTransformBroadcaster latches only the last message it sent (depth 1)."""
        if self._broadcaster is None:
            return
        stamp = self.node.get_clock().now().to_msg()
        self._broadcaster.sendTransform([
            transform_to_msg(MAP_FRAME, odom_frame, map_from_odom_transform(*map_from_odom), stamp),
            transform_to_msg(base_frame, camera_frame, base_from_camera_optical_transform(mount), stamp)])
