"""The ROS half of the TF tree (:mod:`gsrmr_common.tf_tree`): its messages and the optional TF packages.

``tf2_ros`` and ``tf2_msgs`` are not on PyPI for ROS 2; their one guarded import is here (docs/architecture.md,
"Deliberate lazy imports"): without them a node publishes no TF and says why.
"""

from __future__ import annotations

from types import ModuleType
from typing import Any

from builtin_interfaces.msg import Time
from geometry_msgs.msg import TransformStamped

from gsrmr_common.tf_tree import Transform


def load_tf2_ros() -> tuple[ModuleType | None, str]:
    """``(tf2_ros, "")`` where tf2_ros imports (a ROS 2 install), else ``(None, why)``."""
    try:
        import tf2_ros  # optional: only a ROS 2 install has it (lazy: docs/architecture.md)
    except ImportError as err:
        return None, f"tf2_ros does not import ({err})"
    return tf2_ros, ""


def tf_message_type() -> tuple[Any | None, str]:
    """``(tf2_msgs.msg.TFMessage, "")`` where tf2_msgs imports, else ``(None, why)``."""
    try:
        from tf2_msgs.msg import TFMessage  # optional: only a ROS 2 install has it (lazy: docs/architecture.md)
    except ImportError as err:
        return None, f"tf2_msgs does not import ({err})"
    return TFMessage, ""


def transform_to_msg(parent_frame: str, child_frame: str, transform: Transform, stamp: Time) -> TransformStamped:
    """``geometry_msgs/TransformStamped``: the pose of ``child_frame`` in ``parent_frame`` (metres, unit quaternion)."""
    msg = TransformStamped()
    msg.header.stamp = stamp
    msg.header.frame_id = parent_frame
    msg.child_frame_id = child_frame
    t, q = msg.transform.translation, msg.transform.rotation
    t.x, t.y, t.z = transform.translation
    q.x, q.y, q.z, q.w = transform.rotation
    return msg
