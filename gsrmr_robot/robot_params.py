"""The robot node's parameters (:class:`RobotParameters`): names, defaults, descriptors and rules (pure, no ROS).

:class:`gsrmr_robot.robot_node.RobotNode` declares them, refuses a change :meth:`RobotParameters.change_problem`
gives a reason for (on-set callback) and applies an accepted one by replacing its ``params`` (post-set callback).
Live: :data:`LIVE_PARAMETERS`; the others are read-only.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
from typing import Any

from gsrmr_common.camera import CameraMount
from gsrmr_common.link_model import SLOT_S, LinkBudget
from gsrmr_common.node_params import NodeParameters, ros_parameter
from gsrmr_common.tf_tree import BASE_FRAME, CAMERA_OPTICAL_FRAME, ODOM_FRAME

LIVE_PARAMETERS = frozenset({"jpeg_quality", "uplink_width_px", "default_upload_image", "max_frame_age_s",
                             "map_from_odom", "camera_frame_id", "hold_images_while_queued", "uplink_ack_stale_s"})


@dataclass(frozen=True)
class RobotParameters(NodeParameters):
    """Every parameter of the robot node (ROS names; units in the names)."""

    slot_s: float = ros_parameter(SLOT_S, "Slot length τ [s]; must equal the server's", min_value=0.01,
                                  max_value=10.0, read_only=True)
    jpeg_quality: int = ros_parameter(80, "JPEG quality of uploaded images (1-100)", min_value=1, max_value=100)
    uplink_width_px: int = ros_parameter(
        320, "Width of uploaded images [px]: camera frames are rectified to the pinhole camera and scaled down to it "
        "(aspect kept; narrower frames are not enlarged); uplink/camera_info describes the result",
        min_value=16, max_value=4096)
    default_upload_image: bool = ros_parameter(True, "Upload the image in slots no schedule covers")
    max_frame_age_s: float = ros_parameter(0.5, "Older camera frames are not uploaded [s]", min_value=0.0,
                                           max_value=10.0)
    map_from_odom: tuple[float, ...] = ros_parameter((0.0, 0.0, 0.0),
                                                     "Pose of the odom frame in map: [a_m, b_m, theta_rad]")
    camera_frame_id: str = ros_parameter(CAMERA_OPTICAL_FRAME, "Frame of uploaded images: the camera's optical "
                                         "frame (x right, y down, z forward)")
    hold_images_while_queued: bool = ros_parameter(
        True, "Send the pose key only (ledger held_back = 1) when the schedule asks for an image while the last one "
        "is still unacknowledged by the server (queued on the link)")
    uplink_ack_stale_s: float = ros_parameter(1.0, "An image unacknowledged this long no longer holds the next one "
                                              "back [s]", min_value=0.05, max_value=60.0)
    odom_frame_id: str = ros_parameter(ODOM_FRAME, "Odometry frame (child of map in TF)", read_only=True)
    base_frame_id: str = ros_parameter(BASE_FRAME, "Robot body frame (parent of the camera in TF)", read_only=True)
    # Declared read-only by gsrmr_common.ros_node.declare_camera_mount / declare_link_budget (config/*.yaml).
    camera_mount: CameraMount = field(default_factory=CameraMount)
    link: LinkBudget = field(default_factory=LinkBudget)

    @classmethod
    def rule(cls, name: str, value: Any) -> str | None:
        """``map_from_odom`` is 3 finite numbers; ``camera_frame_id`` is not empty."""
        if name == "map_from_odom" and (len(value) != 3 or not all(math.isfinite(v) for v in value)):
            return "map_from_odom must be 3 finite numbers [a_m, b_m, theta_rad]"
        if name == "camera_frame_id" and not value:
            return "camera_frame_id must not be empty"
        return None
