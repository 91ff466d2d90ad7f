"""``map → odom`` from another localizer (AMCL, slam_toolbox), on the graph: its base pose in ``map``
(``localization`` pose: ``geometry_msgs/PoseWithCovarianceStamped`` on ``amcl_pose``, joined with the odometry at its
stamp) or its ``map → odom`` on ``/tf`` (``localization`` tf, where tf2_msgs imports). Each is taken only from
``correction_writers`` and put in force as the next numbered correction (:meth:`MapSource.set_external`)."""

from __future__ import annotations

import math
import threading
from typing import Any

from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.node import Node

from gsrmr_common.plausibility import Implausible
from gsrmr_common.ros_admission import GatedInputs
from gsrmr_common.ros_wire import stamp_to_ns
from gsrmr_common.tf_ros import tf_message_type
from gsrmr_common.tf_tree import MAP_FRAME
from gsrmr_robot.key_poses import KeyPoses
from gsrmr_robot.map_source import MapSource, map_from_odom_of, map_to_odom_edges, planar_pose
from gsrmr_robot.robot_params import LOCALIZER_POSE_TOPIC, RobotParameters

#: A localizer's pose is joined with the odometry sample nearest its stamp, within this [ns].
ODOM_MATCH_NS = 50_000_000


class ExternalLocalizer:
    """Subscribes the other localizer's output and puts it in force in ``maps`` (holding ``lock``); refusals are
    counted in ``implausible`` (``correction_malformed``: a wrong frame, non-finite values) and ``unmatched`` (no
    odometry within :data:`ODOM_MATCH_NS` of a pose's stamp)."""

    def __init__(self, node: Node, inputs: GatedInputs, params: RobotParameters, maps: MapSource, keys: KeyPoses,
                 lock: threading.Lock, implausible: Implausible, odom_frame: str) -> None:
        self.node, self.maps, self.keys, self._lock, self.implausible = node, maps, keys, lock, implausible
        self.odom_frame = odom_frame
        self.unmatched = 0
        if params.localization == "pose":
            inputs.subscribe(PoseWithCovarianceStamped, LOCALIZER_POSE_TOPIC, lambda msg, _gid: self._on_pose(msg),
                             10, params.correction_writers, rate_hz=50.0, burst=50.0)
        elif params.localization == "tf":
            tf_message, why = tf_message_type()
            if tf_message is None:
                raise RuntimeError(f"localization tf: {why}; on the PyPI wheels take localization pose "
                                   f"({LOCALIZER_POSE_TOPIC})")
            inputs.subscribe(tf_message, "/tf", lambda msg, _gid: self._on_tf(msg), 100, params.correction_writers,
                             rate_hz=200.0, burst=200.0)

    def _on_pose(self, msg: PoseWithCovarianceStamped) -> None:
        """The base's pose in ``map`` at the message's stamp: map → odom = it ∘ (odometry then)⁻¹."""
        if msg.header.frame_id.lstrip("/") != MAP_FRAME:
            self.implausible["correction_malformed"] += 1
            self.node.get_logger().warning(f"{LOCALIZER_POSE_TOPIC} in frame {msg.header.frame_id!r}, not "
                                           f"{MAP_FRAME!r}: refused", throttle_duration_sec=5.0)
            return
        stamp_ns = stamp_to_ns(msg.header.stamp)
        cov = msg.pose.covariance
        with self._lock:
            odom = self.keys.odom_at(stamp_ns, ODOM_MATCH_NS)
            if odom is None:
                self.unmatched += 1
                return
            map_from_base = planar_pose(msg.pose.pose.position, msg.pose.pose.orientation)
            self.maps.set_external(map_from_odom_of(map_from_base, odom), stamp_ns / 1e9,
                                   (float(cov[0]), float(cov[7]), float(cov[35])))

    def _on_tf(self, msg: Any) -> None:
        """The localizer's own ``map → odom`` (the newest edge of the message)."""
        edges = map_to_odom_edges(msg.transforms, self.odom_frame)
        if edges:
            stamp_ns, pose = max(edges, key=lambda e: e[0])
            with self._lock:
                self.maps.set_external(pose, stamp_ns / 1e9, (math.nan,) * 3)
