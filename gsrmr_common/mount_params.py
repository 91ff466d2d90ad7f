"""The camera mount as the ``camera_mount.*`` parameters of ``config/camera_mount.yaml`` name it (pure, no ROS)."""

from __future__ import annotations

from dataclasses import dataclass
import math

from gsrmr_common.camera import CameraMount
from gsrmr_common.node_params import NodeParameters, ros_parameter

#: The prefix the mount's parameters are declared under.
MOUNT_PREFIX = "camera_mount."
_DEFAULT = CameraMount()


@dataclass(frozen=True)
class CameraMountParameters(NodeParameters):
    """The pose of ``camera_optical_frame`` in ``base_link`` (REP-103, metres and radians), read-only; loaded into
    the robot, the server and the scorer from one file, so they cannot disagree."""

    height_m: float = ros_parameter(_DEFAULT.height_m, "Optical centre above base_link [m]", min_value=-10.0,
                                    max_value=10.0, read_only=True)
    pitch_rad: float = ros_parameter(_DEFAULT.pitch_rad, "Camera pitch, positive = looking down [rad]",
                                     min_value=-1.5, max_value=1.5, read_only=True)
    forward_m: float = ros_parameter(_DEFAULT.forward_m, "Optical centre ahead of base_link [m]", min_value=-10.0,
                                     max_value=10.0, read_only=True)
    left_m: float = ros_parameter(_DEFAULT.left_m, "Optical centre left of base_link [m]", min_value=-10.0,
                                  max_value=10.0, read_only=True)
    roll_rad: float = ros_parameter(_DEFAULT.roll_rad, "Camera roll about its optical axis (ROS RPY, about "
                                    "base_link x) [rad]", min_value=-math.pi, max_value=math.pi, read_only=True)
    yaw_rad: float = ros_parameter(_DEFAULT.yaw_rad, "Camera yaw, positive = looking left (ROS RPY) [rad]",
                                   min_value=-math.pi, max_value=math.pi, read_only=True)

    def mount(self) -> CameraMount:
        """The :class:`CameraMount` these parameters describe."""
        return CameraMount(height_m=self.height_m, pitch_rad=self.pitch_rad, forward_m=self.forward_m,
                           left_m=self.left_m, roll_rad=self.roll_rad, yaw_rad=self.yaw_rad)
