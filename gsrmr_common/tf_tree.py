"""The robot's TF tree (REP-105) as plain transforms: pure numpy, no ROS import.

Tree (parent → child), each edge the pose of the child frame in the parent frame::

    map ──(robot parameter map_from_odom, static)──▶ odom
    odom ──(base driver's odometry, ~50 Hz)──▶ base_link
    base_link ──(camera mount, static)──▶ camera_optical_frame
    (on a robot whose description names the camera body: base_link ──▶ camera_link ──(fixed)──▶ optical)

A :class:`Transform` maps child-frame points into the parent frame, ``p_parent = R p_child + t`` (metres; unit
quaternion in ROS order x, y, z, w, normalised with w ≥ 0): the fields of ``geometry_msgs/Transform``. Frame axes
and the mount: :mod:`gsrmr_common.camera`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from gsrmr_common.camera import CameraMount
from gsrmr_common.pose2d import Pose2D, quaternion_from_yaw
from gsrmr_common.wire import MAP_FRAME as _WIRE_MAP_FRAME

MAP_FRAME = _WIRE_MAP_FRAME  # "map": the fixed world frame of pose keys and the GS model
ODOM_FRAME = "odom"
BASE_FRAME = "base_link"
CAMERA_FRAME = "camera_link"
CAMERA_OPTICAL_FRAME = "camera_optical_frame"

# Optical frame in an (untilted) body frame x forward, y left, z up: optical z → body +x, optical x →
# body −y, optical y → body −z. It is roll −π/2 then yaw −π/2 (the usual camera_link → *_optical_frame).
_OPTICAL_IN_BODY = (-0.5, 0.5, -0.5, 0.5)


class Transform(NamedTuple):
    """Pose of a child frame in its parent frame: translation [m] and quaternion (x, y, z, w)."""

    translation: tuple[float, float, float]
    rotation: tuple[float, float, float, float]


def _finite(**values: float) -> None:
    for name, value in values.items():
        if not math.isfinite(value):
            raise ValueError(f"transform: {name} must be finite, got {value}")


def _canonical(q: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion (x, y, z, w) with w ≥ 0 (q and −q are the same rotation)."""
    norm = float(np.linalg.norm(q))
    if not math.isfinite(norm) or norm < 1e-12:
        raise ValueError(f"quaternion {q.tolist()} cannot be normalised")
    q = q / norm
    if q[3] < 0.0:
        q = -q
    x, y, z, w = (float(v) for v in q)
    return x, y, z, w


def quaternion_multiply(q1: tuple[float, ...], q2: tuple[float, ...]) -> tuple[float, float, float, float]:
    """Hamilton product q1 ⊗ q2 of quaternions in ROS order (x, y, z, w): rotate by q2, then by q1."""
    x1, y1, z1, w1 = q1
    x2, y2, z2, w2 = q2
    return _canonical(np.array([w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                                w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                                w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
                                w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2]))


def rotation_matrix(q: tuple[float, ...]) -> np.ndarray:
    """3×3 rotation matrix of a quaternion (x, y, z, w) (normalised first)."""
    x, y, z, w = _canonical(np.asarray(q, dtype=np.float64))
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def quaternion_from_matrix(rot: np.ndarray) -> tuple[float, float, float, float]:
    """Quaternion (x, y, z, w), w ≥ 0, of a 3×3 rotation matrix (Shepperd's method, stable for any angle)."""
    m = np.asarray(rot, dtype=np.float64).reshape(3, 3)
    if not np.allclose(m @ m.T, np.eye(3), atol=1e-6) or np.linalg.det(m) < 0:
        raise ValueError("quaternion_from_matrix: not a rotation matrix")
    trace = float(np.trace(m))
    if trace > 0.0:
        s = 2.0 * math.sqrt(1.0 + trace)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    return _canonical(np.array(q))


def transform_matrix(transform: Transform) -> np.ndarray:
    """4×4 homogeneous matrix taking child-frame points into the parent frame."""
    out = np.eye(4)
    out[:3, :3] = rotation_matrix(transform.rotation)
    out[:3, 3] = np.asarray(transform.translation, dtype=np.float64)
    return out


def planar_transform(x_m: float, y_m: float, yaw_rad: float) -> Transform:
    """A frame at (x, y) [m] in the parent's z = 0 plane, yawed by ``yaw_rad`` (CCW about +z)."""
    _finite(x_m=x_m, y_m=y_m, yaw_rad=yaw_rad)
    return Transform((float(x_m), float(y_m), 0.0), quaternion_from_yaw(yaw_rad))


def map_from_odom_transform(a_m: float, b_m: float, theta_rad: float) -> Transform:
    """``map → odom``: the pose of ``odom`` in ``map``, the robot parameter ``map_from_odom = [a, b, θ]``.

    ``a_m``, ``b_m`` [m] and ``theta_rad`` [rad, CCW about +z]: where the robot stood (and faced) in
    ``map`` when its odometry started at zero.
    """
    return planar_transform(a_m, b_m, theta_rad)


def odom_from_base_transform(x_m: float, y_m: float, yaw_rad: float) -> Transform:
    """``odom → base_link``: the base driver's odometry pose (x, y [m], yaw [rad]) of ``base_link`` in ``odom``."""
    return planar_transform(x_m, y_m, yaw_rad)


def base_from_camera_link_transform(mount: CameraMount) -> Transform:
    """``base_link → camera_link`` for a camera mount (static): the camera body frame (x forward, y left, z up)
    at ``(forward_m, left_m, height_m)`` [m], turned by the mount's roll, pitch and yaw (ROS RPY)."""
    _finite(height_m=mount.height_m, pitch_rad=mount.pitch_rad, forward_m=mount.forward_m, left_m=mount.left_m,
            roll_rad=mount.roll_rad, yaw_rad=mount.yaw_rad)
    return Transform((float(mount.forward_m), float(mount.left_m), float(mount.height_m)),
                     quaternion_from_matrix(mount.body_rotation()))


#: ``camera_link → camera_optical_frame``: the fixed optical rotation (REP-103 ``_optical`` suffix), no offset.
CAMERA_LINK_FROM_OPTICAL = Transform((0.0, 0.0, 0.0), _OPTICAL_IN_BODY)


def base_from_camera_optical_transform(mount: CameraMount) -> Transform:
    """``base_link → camera_optical_frame`` for a camera mount (static): ``base_link → camera_link`` composed
    with the fixed optical rotation.

    Translation: the optical centre ``(forward_m, left_m, height_m)`` in ``base_link`` [m]. Rotation:
    the optical axes (x right, y down, z forward) turned into the body axes (x forward, y left, z up),
    then by the mount's roll, pitch and yaw (pitch: a rotation by +pitch about ``base_link`` +y, which tips
    the optical axis toward −z). With a zero rotation the optical z axis is ``base_link`` +x.
    """
    body = base_from_camera_link_transform(mount)
    return Transform(body.translation, quaternion_multiply(body.rotation, _OPTICAL_IN_BODY))


def map_from_camera_optical_matrix(map_from_odom: Pose2D, odom_pose: Pose2D, mount: CameraMount) -> np.ndarray:
    """4×4 ``map → camera_optical_frame`` through the tree (map → odom → base_link → camera_optical_frame).

    ``map_from_odom`` = (a_m, b_m, theta_rad) as in :func:`map_from_odom_transform`; ``odom_pose`` =
    (x_m, y_m, yaw_rad) of ``base_link`` in ``odom``. The result maps optical-frame points into ``map``
    (the camera→world matrix of :mod:`gsrmr_common.camera`).
    """
    return (transform_matrix(map_from_odom_transform(*map_from_odom))
            @ transform_matrix(odom_from_base_transform(*odom_pose))
            @ transform_matrix(base_from_camera_optical_transform(mount)))


__all__ = ["BASE_FRAME", "CAMERA_FRAME", "CAMERA_LINK_FROM_OPTICAL", "CAMERA_OPTICAL_FRAME", "MAP_FRAME",
           "ODOM_FRAME", "Transform", "base_from_camera_link_transform", "base_from_camera_optical_transform",
           "map_from_camera_optical_matrix", "map_from_odom_transform", "odom_from_base_transform",
           "planar_transform", "quaternion_from_matrix", "quaternion_multiply", "rotation_matrix",
           "transform_matrix"]
