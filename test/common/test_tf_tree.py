"""The robot's TF tree (gsrmr_common.tf_tree) against the camera model, and the nodes that publish it.

The first part is pure (numpy, no ROS): the chain map → odom → base_link → camera_optical_frame, built
from quaternions only, must equal :func:`gsrmr_common.camera.camera_to_world_from_pose`, which builds
its matrices from rotation matrices, for many poses and mounts; an axis slip in either shows up here.
The second part checks the ROS side in-process (no DDS traffic is needed): the robot node's static
transforms through a stand-in ``tf2_ros`` (there is none in this venv), the limo node's choice of TF
output, and the INFO line when tf2_ros is missing.
"""

from __future__ import annotations

import importlib.util
import itertools
import math
from pathlib import Path
import subprocess
import sys
import types
from typing import ClassVar

import numpy as np
import pytest

from gsrmr_common import tf_tree, wire
from gsrmr_common.camera import CameraMount, Intrinsics, camera_from_pose, camera_to_world_from_pose

sys.path.insert(0, str(Path(__file__).parents[1]))
from conftest import next_domain_id

MOUNTS = [CameraMount(), CameraMount(height_m=0.15, pitch_rad=math.radians(5.0), forward_m=0.1),
          CameraMount(height_m=0.35, pitch_rad=math.radians(8.0), forward_m=0.1, left_m=0.0),
          CameraMount(height_m=0.4, pitch_rad=-0.3, forward_m=-0.05, left_m=0.07),
          CameraMount(height_m=1.2, pitch_rad=1.4, forward_m=0.2, left_m=-0.1),
          CameraMount(height_m=0.3, pitch_rad=0.2, forward_m=0.05, left_m=0.04, roll_rad=0.1, yaw_rad=-0.6)]
MAP_FROM_ODOM = [(0.0, 0.0, 0.0), (-3.5, -2.1, 1.0), (2.0, 0.5, math.pi), (0.3, -4.0, -2.6)]
ODOM_POSES = [(0.0, 0.0, 0.0), (1.25, -0.4, 0.7), (-2.0, 3.0, -3.1), (0.01, 0.02, math.pi / 2)]


def compose_planar(map_from_odom: tuple[float, float, float],
                   odom_pose: tuple[float, float, float]) -> tuple[float, float, float]:
    """The robot's pose (a, b, θ) in map, composed by hand as the robot node does for its pose keys."""
    a0, b0, t0 = map_from_odom
    x, y, yaw = odom_pose
    c, s = math.cos(t0), math.sin(t0)
    return a0 + c * x - s * y, b0 + s * x + c * y, t0 + yaw


# ------------------------------------------------------------------------------------------- pure

@pytest.mark.parametrize(("map_from_odom", "odom_pose", "mount"),
                         list(itertools.product(MAP_FROM_ODOM, ODOM_POSES, MOUNTS)))
def test_chain_equals_camera_to_world_from_pose(map_from_odom, odom_pose, mount) -> None:
    chain = tf_tree.map_from_camera_optical_matrix(map_from_odom, odom_pose, mount)
    expected = camera_to_world_from_pose(*compose_planar(map_from_odom, odom_pose), mount)
    np.testing.assert_allclose(chain, expected, atol=1e-12)
    # The same chain multiplied out by hand from the three edges (what RViz/tf2 does with the messages).
    edges = [tf_tree.map_from_odom_transform(*map_from_odom), tf_tree.odom_from_base_transform(*odom_pose),
             tf_tree.base_from_camera_optical_transform(mount)]
    by_hand = np.linalg.multi_dot([tf_tree.transform_matrix(e) for e in edges])
    np.testing.assert_allclose(by_hand, expected, atol=1e-12)


def test_chain_projects_like_the_renderer_camera() -> None:
    """A point 2 m ahead on the optical axis lands on the principal point of the renderer's camera."""
    k = Intrinsics.from_fov(160, 120, math.radians(70))
    for mount, pose in itertools.product(MOUNTS, ODOM_POSES):
        c2w = tf_tree.map_from_camera_optical_matrix((0.5, -1.0, 0.3), pose, mount)
        ahead = c2w @ np.array([0.0, 0.0, 2.0, 1.0])
        uv, z = camera_from_pose(*compose_planar((0.5, -1.0, 0.3), pose), mount, k).project(ahead[None, :3])
        np.testing.assert_allclose(uv[0], (k.cx, k.cy), atol=1e-9)
        assert z[0] == pytest.approx(2.0)


@pytest.mark.parametrize("mount", MOUNTS)
def test_camera_link_then_optical_is_the_mount_and_a_mount_comes_back_from_its_pose(mount) -> None:
    """base_link → camera_link (ROS RPY) → optical (fixed) is the one optical edge; a measured optical pose (a robot's
    static TF) gives the mount back."""
    two = tf_tree.transform_matrix(tf_tree.base_from_camera_link_transform(mount)) @ tf_tree.transform_matrix(
        tf_tree.CAMERA_LINK_FROM_OPTICAL)
    one = tf_tree.transform_matrix(tf_tree.base_from_camera_optical_transform(mount))
    np.testing.assert_allclose(two, one, atol=1e-12)
    back = CameraMount.from_optical_pose(one)
    np.testing.assert_allclose([getattr(back, k) for k in mount.as_parameters(prefix="")],
                               list(mount.as_parameters(prefix="").values()), atol=1e-9)


def test_mount_roll_pitch_yaw_turn_the_optical_axis_as_ros_rpy() -> None:
    z_axis = lambda m: tf_tree.rotation_matrix(tf_tree.base_from_camera_optical_transform(m).rotation)[:, 2]  # noqa: E731
    x_axis = lambda m: tf_tree.rotation_matrix(tf_tree.base_from_camera_optical_transform(m).rotation)[:, 0]  # noqa: E731
    np.testing.assert_allclose(z_axis(CameraMount(yaw_rad=math.pi / 2)), [0, 1, 0], atol=1e-12)  # looks left
    np.testing.assert_allclose(z_axis(CameraMount(pitch_rad=math.pi / 4)), [math.sqrt(.5), 0, -math.sqrt(.5)],
                               atol=1e-12)  # looks down
    # roll +90° about the forward axis: the image's x (right) axis points down
    np.testing.assert_allclose(x_axis(CameraMount(roll_rad=math.pi / 2)), [0, 0, -1], atol=1e-12)
    with pytest.raises(ValueError, match="yaw_rad"):
        CameraMount(yaw_rad=4.0)


def test_quaternions_are_unit_with_nonnegative_w() -> None:
    rng = np.random.default_rng(3)
    transforms = [tf_tree.base_from_camera_optical_transform(m) for m in MOUNTS]
    transforms += [tf_tree.map_from_odom_transform(*p) for p in MAP_FROM_ODOM]
    transforms += [tf_tree.odom_from_base_transform(*rng.uniform(-5, 5, 2), yaw) for yaw in rng.uniform(-9, 9, 50)]
    for t in transforms:
        assert len(t.translation) == 3 and len(t.rotation) == 4
        assert math.fsum(v * v for v in t.rotation) == pytest.approx(1.0, abs=1e-12)
        assert t.rotation[3] >= 0.0
        assert all(isinstance(v, float) for v in (*t.translation, *t.rotation))  # plain floats for ROS fields


def test_planar_edges_lie_in_the_floor_plane() -> None:
    t = tf_tree.map_from_odom_transform(1.5, -2.0, 0.4)
    assert t.translation == (1.5, -2.0, 0.0)
    assert t.rotation == pytest.approx((0.0, 0.0, math.sin(0.2), math.cos(0.2)))
    # yaw and yaw + 2π are the same rotation, quaternion included (canonical w ≥ 0)
    assert tf_tree.odom_from_base_transform(0, 0, 3.0).rotation == pytest.approx(
        tf_tree.odom_from_base_transform(0, 0, 3.0 - 2 * math.pi).rotation)


def test_unpitched_optical_axes_in_base_link() -> None:
    """Optical z (forward) = base_link +x, optical x (right) = −y, optical y (down) = −z."""
    mount = CameraMount(height_m=0.2, pitch_rad=0.0, forward_m=0.1, left_m=0.03)
    t = tf_tree.base_from_camera_optical_transform(mount)
    rot = tf_tree.rotation_matrix(t.rotation)
    np.testing.assert_allclose(rot[:, 2], [1.0, 0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(rot[:, 0], [0.0, -1.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(rot[:, 1], [0.0, 0.0, -1.0], atol=1e-15)
    assert t.translation == (0.1, 0.03, 0.2)
    assert t.rotation == pytest.approx((-0.5, 0.5, -0.5, 0.5))


def test_pitch_down_tilts_the_optical_axis_toward_the_floor() -> None:
    pitch = math.radians(10.0)
    rot = tf_tree.rotation_matrix(tf_tree.base_from_camera_optical_transform(CameraMount(pitch_rad=pitch)).rotation)
    np.testing.assert_allclose(rot[:, 2], [math.cos(pitch), 0.0, -math.sin(pitch)], atol=1e-15)
    np.testing.assert_allclose(rot[:, 0], [0.0, -1.0, 0.0], atol=1e-15)  # pitch keeps the image rows level


def test_quaternion_matrix_round_trip_including_half_turns() -> None:
    rng = np.random.default_rng(7)
    qs = list(rng.normal(size=(200, 4)))
    qs += [np.array(q, float) for q in ((1, 0, 0, 0), (0, 1, 0, 0), (0, 0, 1, 0), (0.5, 0.5, 0.5, -0.5),
                                        (1e-9, 1, 1, 0))]
    for q in qs:
        rot = tf_tree.rotation_matrix(tuple(q))
        assert np.allclose(rot @ rot.T, np.eye(3), atol=1e-12) and np.linalg.det(rot) == pytest.approx(1.0)
        back = tf_tree.quaternion_from_matrix(rot)
        np.testing.assert_allclose(tf_tree.rotation_matrix(back), rot, atol=1e-12)
        unit = q / np.linalg.norm(q)
        assert abs(float(np.dot(back, unit))) == pytest.approx(1.0, abs=1e-12)  # same rotation, ±q
    with pytest.raises(ValueError):
        tf_tree.quaternion_from_matrix(np.diag([1.0, 1.0, -1.0]))  # a reflection


def test_quaternion_multiply_composes_like_matrices() -> None:
    rng = np.random.default_rng(11)
    for _ in range(50):
        q1, q2 = (tuple(rng.normal(size=4)) for _ in range(2))
        np.testing.assert_allclose(tf_tree.rotation_matrix(tf_tree.quaternion_multiply(q1, q2)),
                                   tf_tree.rotation_matrix(q1) @ tf_tree.rotation_matrix(q2), atol=1e-12)


def test_non_finite_inputs_are_refused() -> None:
    with pytest.raises(ValueError, match="finite"):
        tf_tree.map_from_odom_transform(float("nan"), 0.0, 0.0)
    with pytest.raises(ValueError, match="finite"):
        tf_tree.odom_from_base_transform(0.0, 0.0, float("inf"))


def test_frame_names() -> None:
    assert (tf_tree.MAP_FRAME, tf_tree.ODOM_FRAME, tf_tree.BASE_FRAME, tf_tree.CAMERA_OPTICAL_FRAME) == (
        "map", "odom", "base_link", "camera_optical_frame")
    assert tf_tree.MAP_FRAME == wire.MAP_FRAME  # pose keys are in the TF root frame


def test_tf_tree_imports_no_ros() -> None:
    """tf_tree stays usable without a ROS install: importing it alone pulls in no ROS package."""
    code = ("import sys, gsrmr_common.tf_tree; "
            "bad = sorted(m for m in sys.modules if m.split('.')[0] in "
            "('rclpy', 'geometry_msgs', 'builtin_interfaces', 'tf2_ros', 'sensor_msgs', 'std_msgs')); "
            "print(bad); sys.exit(1 if bad else 0)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stdout + proc.stderr


# ------------------------------------------------------------------------------------- ROS side

class _FakeBroadcaster:
    """Stands in for tf2_ros.(Static)TransformBroadcaster: records every sendTransform call."""

    instances: ClassVar[list[_FakeBroadcaster]] = []

    def __init__(self, node) -> None:
        self.node = node
        self.sent: list[list] = []
        type(self).instances.append(self)

    def sendTransform(self, transform) -> None:  # tf2_ros's name
        self.sent.append(list(transform) if isinstance(transform, list) else [transform])


@pytest.fixture
def fake_tf2_ros(monkeypatch):
    """A ``tf2_ros`` module in sys.modules (the venv has none) whose broadcasters record what is sent."""
    module = types.ModuleType("tf2_ros")

    class Static(_FakeBroadcaster):
        instances: ClassVar[list[_FakeBroadcaster]] = []

    class Dynamic(_FakeBroadcaster):
        instances: ClassVar[list[_FakeBroadcaster]] = []

    module.StaticTransformBroadcaster = Static
    module.TransformBroadcaster = Dynamic
    monkeypatch.setitem(sys.modules, "tf2_ros", module)
    return module


@pytest.fixture
def ros_context():
    """An rclpy context in a domain of its own (nothing is spun; no other graph is touched)."""
    import rclpy
    from rclpy.context import Context

    ctx = Context()
    rclpy.init(context=ctx, domain_id=next_domain_id())
    try:
        yield ctx
    finally:
        rclpy.shutdown(context=ctx)


def _as_transform(msg) -> tuple[str, str, tf_tree.Transform]:
    t, q = msg.transform.translation, msg.transform.rotation
    return msg.header.frame_id, msg.child_frame_id, tf_tree.Transform((t.x, t.y, t.z), (q.x, q.y, q.z, q.w))


def test_transform_to_msg_fields() -> None:
    from builtin_interfaces.msg import Time

    from gsrmr_common.tf_ros import transform_to_msg

    tf = tf_tree.base_from_camera_optical_transform(CameraMount(pitch_rad=0.1))
    msg = transform_to_msg("base_link", "cam", tf, Time(sec=3, nanosec=4))
    assert (msg.header.frame_id, msg.child_frame_id, msg.header.stamp.sec, msg.header.stamp.nanosec) == (
        "base_link", "cam", 3, 4)
    assert _as_transform(msg)[2] == tf


def test_robot_node_sends_static_tf_and_resends_on_map_from_odom_change(fake_tf2_ros, ros_context) -> None:
    from rclpy.parameter import Parameter

    from gsrmr_robot.robot_node import RobotNode

    mount = CameraMount(height_m=0.15, pitch_rad=math.radians(5.0), forward_m=0.1, left_m=0.02)
    node = RobotNode(context=ros_context, parameter_overrides=[
        Parameter("map_from_odom", value=[1.0, -2.0, 0.5]),
        Parameter("camera_mount.height_m", value=mount.height_m),
        Parameter("camera_mount.pitch_rad", value=mount.pitch_rad),
        Parameter("camera_mount.forward_m", value=mount.forward_m),
        Parameter("camera_mount.left_m", value=mount.left_m),
        Parameter("live_parameter_changes", value=True)])  # issue 28: live changes are off unless started on
    try:
        (static,) = fake_tf2_ros.StaticTransformBroadcaster.instances
        assert not fake_tf2_ros.TransformBroadcaster.instances  # odom → base_link is the base driver's
        assert len(static.sent) == 1
        edges = {(p, c): t for p, c, t in map(_as_transform, static.sent[0])}
        assert set(edges) == {("map", "odom"), ("base_link", "camera_optical_frame")}
        odom_pose = (0.4, 0.3, -1.2)
        chain = (tf_tree.transform_matrix(edges["map", "odom"])
                 @ tf_tree.transform_matrix(tf_tree.odom_from_base_transform(*odom_pose))
                 @ tf_tree.transform_matrix(edges["base_link", "camera_optical_frame"]))
        np.testing.assert_allclose(chain, camera_to_world_from_pose(
            *compose_planar((1.0, -2.0, 0.5), odom_pose), mount), atol=1e-12)

        assert node.set_parameters([Parameter("map_from_odom", value=[3.0, 4.0, -1.0])])[0].successful
        assert len(static.sent) == 2
        # Every send carries both static edges: tf2_ros latches only the last /tf_static message.
        edges = {(p, c): t for p, c, t in map(_as_transform, static.sent[1])}
        assert edges["map", "odom"] == tf_tree.map_from_odom_transform(3.0, 4.0, -1.0)
        assert edges["base_link", "camera_optical_frame"] == tf_tree.base_from_camera_optical_transform(mount)

        assert not node.set_parameters([Parameter("map_from_odom", value=[1.0, 2.0])])[0].successful
        assert node.params.map_from_odom == (3.0, 4.0, -1.0)  # a refused value changes nothing
        assert node.set_parameters([Parameter("jpeg_quality", value=70)])[0].successful
        assert node.params.jpeg_quality == node.core.jpeg_quality == 70  # applied after it was accepted
        assert len(static.sent) == 2  # neither a refused value nor another parameter re-sends
    finally:
        node.destroy_node()


@pytest.mark.skipif(importlib.util.find_spec("tf2_ros") is not None, reason="tf2_ros is installed here")
def test_robot_node_without_tf2_ros_sends_nothing(ros_context) -> None:
    from gsrmr_common.tf_ros import load_tf2_ros
    from gsrmr_robot.robot_node import RobotNode

    module, why = load_tf2_ros()
    assert module is None and "tf2_ros" in why
    node = RobotNode(context=ros_context)
    try:
        assert not node.static_tf.published
        assert not [t for t in node.get_topic_names_and_types() if t[0] in ("/tf", "/tf_static")]
    finally:
        node.destroy_node()


def test_limo_tf_output_prefers_tf2_ros(fake_tf2_ros, ros_context) -> None:
    import rclpy

    from gsrmr_robot.limo.node import LimoBaseNode

    node = rclpy.create_node("limo_tf_probe", context=ros_context)
    try:
        send = LimoBaseNode._tf_sender(node)  # the method needs only Node facilities
        (broadcaster,) = fake_tf2_ros.TransformBroadcaster.instances
        assert send == broadcaster.sendTransform
    finally:
        node.destroy_node()


@pytest.mark.skipif(importlib.util.find_spec("tf2_ros") is not None or importlib.util.find_spec("tf2_msgs")
                    is not None, reason="tf2_ros or tf2_msgs is installed here")
def test_limo_tf_output_without_tf2_is_none(ros_context) -> None:
    import rclpy

    from gsrmr_robot.limo.node import LimoBaseNode

    node = rclpy.create_node("limo_tf_probe", context=ros_context)
    try:
        assert LimoBaseNode._tf_sender(node) is None
    finally:
        node.destroy_node()
