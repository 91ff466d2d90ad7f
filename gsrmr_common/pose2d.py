"""The planar pose (:class:`Pose2D`), angle wrapping and yaw ↔ quaternion: the one place they are defined (pure)."""

from __future__ import annotations

from collections.abc import Sequence
import math
from typing import NamedTuple


def wrap_angle(angle_rad: float) -> float:
    """``angle_rad`` wrapped to (−π, π] (exact for an angle already in it)."""
    wrapped = math.remainder(angle_rad, math.tau)
    return math.pi if wrapped == -math.pi else wrapped


def yaw_from_quaternion(x: float, y: float, z: float, w: float) -> float:
    """The yaw [rad] (rotation about +z, counter-clockwise, in (−π, π]) of the quaternion (x, y, z, w), ROS order;
    roll and pitch are ignored."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def quaternion_from_yaw(yaw_rad: float) -> tuple[float, float, float, float]:
    """The rotation by ``yaw_rad`` about +z as a quaternion (x, y, z, w), ROS order, with w ≥ 0."""
    half = 0.5 * wrap_angle(yaw_rad)
    return 0.0, 0.0, math.sin(half), math.cos(half)


class Pose2D(NamedTuple):
    """A frame's planar pose in its parent frame (REP-103): origin ``(x_m, y_m)`` in metres and heading
    ``theta_rad``, counter-clockwise from the parent's +x. As a robot pose it is base_link in ``map`` — the pose
    key's (a, b, θ). A tuple, so ``x, y, theta = pose`` and ``pose[:2]`` work.

    Example::

        map_from_odom = Pose2D(1.0, 2.0, math.pi / 2)
        odom_from_base = Pose2D(0.5, 0.0, 0.0)
        map_from_base = map_from_odom.compose(odom_from_base)  # Pose2D(1.0, 2.5, π/2)
    """

    x_m: float = 0.0
    y_m: float = 0.0
    theta_rad: float = 0.0

    @classmethod
    def of(cls, values: Sequence[float]) -> Pose2D:
        """A pose from any three numbers ``(x_m, y_m, theta_rad)`` (a tuple, a list, an array row)."""
        x_m, y_m, theta_rad = values
        return cls(float(x_m), float(y_m), float(theta_rad))

    def compose(self, other: Sequence[float]) -> Pose2D:
        """``self ∘ other``: ``other`` (a pose in this pose's frame) in this pose's parent frame; the heading is
        wrapped to (−π, π]."""
        x_m, y_m, theta_rad = other
        c, s = math.cos(self.theta_rad), math.sin(self.theta_rad)
        return Pose2D(self.x_m + c * x_m - s * y_m, self.y_m + s * x_m + c * y_m,
                      wrap_angle(self.theta_rad + theta_rad))

    def inverse(self) -> Pose2D:
        """The parent's pose in this pose's frame: ``self.compose(self.inverse())`` is the identity."""
        c, s = math.cos(self.theta_rad), math.sin(self.theta_rad)
        return Pose2D(-(c * self.x_m + s * self.y_m), -(-s * self.x_m + c * self.y_m), wrap_angle(-self.theta_rad))

    def relative_to(self, base: Sequence[float]) -> Pose2D:
        """This pose in the frame of ``base`` (both in the same parent): ``base⁻¹ ∘ self``."""
        return Pose2D.of(base).inverse().compose(self)

    def distance_m(self, other: Sequence[float]) -> float:
        """The distance [m] between the two origins."""
        return math.hypot(self.x_m - other[0], self.y_m - other[1])

    def heading_error_rad(self, other: Sequence[float]) -> float:
        """``self.theta_rad − other.theta_rad`` wrapped to (−π, π]."""
        return wrap_angle(self.theta_rad - other[2])

    def quaternion(self) -> tuple[float, float, float, float]:
        """The heading as a quaternion (x, y, z, w), ROS order, w ≥ 0."""
        return quaternion_from_yaw(self.theta_rad)

    def wrapped(self) -> Pose2D:
        """The same pose with its heading in (−π, π]."""
        return Pose2D(self.x_m, self.y_m, wrap_angle(self.theta_rad))
