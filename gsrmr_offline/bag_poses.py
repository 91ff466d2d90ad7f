"""Where the camera was: a :class:`~gsrmr_common.tf_buffer.TfBuffer` filled from a bag's ``/tf`` and ``/tf_static``, or
from a pose topic's edge and the camera mount (docs/dataset_tool.md, "Where the camera was"). Messages are rosbags'
dataclasses (duck-typed: no ROS import); units: metres, quaternions (x, y, z, w), stamps from ``header.stamp``.
"""

from __future__ import annotations

from dataclasses import fields
import math
from pathlib import Path
from typing import Any

import yaml

from gsrmr_common.camera import CameraMount
from gsrmr_common.image_decode import stamp_ns
from gsrmr_common.tf_buffer import TfBuffer, strip_frame
from gsrmr_common.tf_tree import Transform

TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"
ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
POSE_STAMPED_TYPE = "geometry_msgs/msg/PoseStamped"
POSE_COV_STAMPED_TYPE = "geometry_msgs/msg/PoseWithCovarianceStamped"
POSE_TYPES = (ODOMETRY_TYPE, POSE_STAMPED_TYPE, POSE_COV_STAMPED_TYPE)
MOUNT_PREFIX = "camera_mount"


def _transform(translation: Any, rotation: Any) -> Transform:
    t = (float(translation.x), float(translation.y), float(translation.z))
    q = (float(rotation.x), float(rotation.y), float(rotation.z), float(rotation.w))
    norm = math.sqrt(sum(v * v for v in q))
    if not all(math.isfinite(v) for v in (*t, *q)) or norm < 1e-6:
        raise ValueError(f"not a rigid transform: translation {t}, quaternion {q}")
    return Transform(t, tuple(v / norm for v in q))


def transform_of(msg_transform: Any) -> Transform:
    """A ``geometry_msgs/Transform`` (``translation``, ``rotation``) → :class:`Transform`; ``ValueError`` for a
    non-finite value or a zero quaternion."""
    return _transform(msg_transform.translation, msg_transform.rotation)


def transform_of_pose(pose: Any) -> Transform:
    """A ``geometry_msgs/Pose`` (``position``, ``orientation``) → :class:`Transform` (the pose as a frame)."""
    return _transform(pose.position, pose.orientation)


def add_tf_message(buffer: TfBuffer, msg: Any, static: bool, skip_children: frozenset[str] = frozenset()) -> int:
    """Add every transform of a ``TFMessage`` to ``buffer`` (static edges from ``/tf_static``); transforms into
    a frame of ``skip_children`` are left out. Returns how many transforms were unusable (bad numbers, a frame
    named like its parent or empty)."""
    bad = 0
    for stamped in msg.transforms:
        parent, child = strip_frame(stamped.header.frame_id), strip_frame(stamped.child_frame_id)
        if child in skip_children:
            continue
        try:
            transform = transform_of(stamped.transform)
            if static:
                buffer.set_static(parent, child, transform)
            else:
                buffer.add_sample(parent, child, stamp_ns(stamped.header.stamp), transform)
        except ValueError:
            bad += 1
    return bad


def pose_child_frame(msg: Any, msgtype: str, base_frame: str) -> str:
    """The frame a pose message places: ``Odometry.child_frame_id``, else ``base_frame``."""
    child = strip_frame(getattr(msg, "child_frame_id", "")) if msgtype == ODOMETRY_TYPE else ""
    return child or strip_frame(base_frame)


def pose_edge(msg: Any, msgtype: str, base_frame: str) -> tuple[str, str, int, Transform]:
    """A pose message → (parent frame, child frame, stamp [ns], the child's pose in the parent) — module
    docstring for the child. ``ValueError`` for another type, an empty parent frame or bad numbers."""
    if msgtype not in POSE_TYPES:
        raise ValueError(f"{msgtype} is not a pose type ({', '.join(POSE_TYPES)})")
    pose = msg.pose.pose if msgtype in (ODOMETRY_TYPE, POSE_COV_STAMPED_TYPE) else msg.pose
    parent = strip_frame(msg.header.frame_id)
    if not parent:
        raise ValueError(f"a {msgtype} message has an empty header.frame_id")
    return parent, pose_child_frame(msg, msgtype, base_frame), stamp_ns(msg.header.stamp), transform_of_pose(pose)


def _flatten(prefix: str, value: Any, out: dict[str, Any]) -> None:
    if isinstance(value, dict):
        for key, inner in value.items():
            _flatten(f"{prefix}.{key}" if prefix else str(key), inner, out)
    else:
        out[prefix] = value


def read_camera_mount(path: str | Path) -> CameraMount:
    """The camera mount from a ROS 2 parameter file with ``camera_mount.{forward_m,left_m,height_m,roll_rad,
    pitch_rad,yaw_rad}`` under ``<node or /**>: ros__parameters:`` (dotted or nested keys), as
    ``config/camera_mount.yaml``; missing keys take :class:`CameraMount`'s defaults. ``ValueError`` (one line)
    for an unreadable file, an unknown ``camera_mount.*`` key or a bad value."""
    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as err:
        raise ValueError(f"cannot read the camera mount file {path} ({err})") from None
    params: dict[str, Any] = {}
    if isinstance(doc, dict):
        for node in doc.values():
            if isinstance(node, dict) and isinstance(node.get("ros__parameters"), dict):
                _flatten("", node["ros__parameters"], params)
    names = {f.name for f in fields(CameraMount)}
    mount = {k.split(".", 1)[1]: v for k, v in params.items() if k.startswith(f"{MOUNT_PREFIX}.")}
    if not mount:
        raise ValueError(f"{path}: no camera_mount.* parameters under <node>: ros__parameters: (see "
                         "config/camera_mount.yaml)")
    unknown = sorted(set(mount) - names)
    if unknown:
        raise ValueError(f"{path}: unknown camera_mount parameters {unknown} (known: {sorted(names)})")
    try:
        return CameraMount(**{k: float(v) for k, v in mount.items()})
    except (TypeError, ValueError) as err:
        raise ValueError(f"{path}: {err}") from None
