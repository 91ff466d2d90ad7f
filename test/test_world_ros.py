"""World nodes as real processes: the mock camera publishes Image + CameraInfo (+ virtual view and
mask) rendered at the odometry pose; the route follower drives the loop, counts a lap and stops."""

from __future__ import annotations

from collections.abc import Callable, Iterator
import math
import time

from geometry_msgs.msg import Twist
from nav_msgs.msg import Odometry
import numpy as np
import pytest
import rclpy
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Float64MultiArray, Int32

from gsrmr_common.camera import camera_from_pose
from gsrmr_common.ros_wire import UPLINK_QOS
from gsrmr_common.route import LoopPath
from gsrmr_common.wire import MR_SLOT_INFO_TOPIC, MRSlotInfo
from gsrmr_sim.world.raycast import RayCastWorld
from gsrmr_sim.world.recorder import with_resolution
from gsrmr_sim.world.scene import load_scene

pytestmark = pytest.mark.ros


@pytest.fixture
def test_node(ros_processes, monkeypatch) -> Iterator[Node]:
    """An rclpy node in the test process, in the harness's ROS domain."""
    for key in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE"):
        monkeypatch.setenv(key, ros_processes.env[key])
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(ros_processes.env["ROS_DOMAIN_ID"]))
    node = rclpy.create_node("world_test", context=ctx)
    try:
        yield node
    finally:
        node.destroy_node()
        rclpy.shutdown(context=ctx)


def spin_until(node: Node, done: Callable[[], bool], timeout_s: float, tick: Callable[[], None] | None = None) -> bool:
    """Spin the test node until ``done()`` or the timeout; ``tick`` runs between spins."""
    executor = rclpy.executors.SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    deadline = time.monotonic() + timeout_s
    try:
        while time.monotonic() < deadline:
            if done():
                return True
            if tick is not None:
                tick()
            executor.spin_once(timeout_sec=0.05)
        return done()
    finally:
        executor.remove_node(node)


def odom_msg(x: float, y: float, yaw: float) -> Odometry:
    msg = Odometry()
    msg.header.frame_id = "map"
    msg.child_frame_id = "base_link"
    msg.pose.pose.position.x, msg.pose.pose.position.y = x, y
    msg.pose.pose.orientation.z, msg.pose.pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
    return msg


def test_mock_camera_publishes_image_info_and_depth_at_the_odometry_pose(ros_processes, test_node):
    cam_proc = ros_processes.start("gsrmr-mock-camera", "--ros-args", "-p", "width:=64", "-p", "height:=48",
                                   "-p", "rate_hz:=10.0", "-p", "round:=0")
    images: list[Image] = []
    infos: list[CameraInfo] = []
    test_node.create_subscription(Image, "camera/image_raw", images.append, qos_profile_sensor_data)
    test_node.create_subscription(CameraInfo, "camera/camera_info", infos.append, qos_profile_sensor_data)
    depths: list[Image] = []
    test_node.create_subscription(Image, "camera/depth/image_raw", depths.append, qos_profile_sensor_data)
    assert spin_until(test_node, lambda: min(len(images), len(infos), len(depths)) >= 2, 60.0), \
        ros_processes.output(cam_proc)
    img, info = images[-1], infos[-1]
    assert (img.width, img.height, img.encoding, img.step) == (64, 48, "rgb8", 64 * 3)
    assert img.header.frame_id == info.header.frame_id == "camera_optical_frame"
    scene = with_resolution(load_scene("sandbox"), 64, 48)
    k = scene.camera.intrinsics
    assert np.allclose(np.asarray(info.k).reshape(3, 3), k.ros_k())
    assert (info.width, info.height) == (64, 48)
    stamps = {(m.header.stamp.sec, m.header.stamp.nanosec) for m in images}
    assert any((i.header.stamp.sec, i.header.stamp.nanosec) in stamps for i in infos)
    depth = np.frombuffer(bytes(depths[-1].data), "<f4").reshape(48, 64)
    assert depths[-1].encoding == "32FC1" and np.all(depth > 0) and np.isfinite(depth).mean() > 0.9

    # Now the true pose arrives: the camera must render exactly there.
    pose = (0.4, -0.3, 2.0)
    odom_pub = test_node.create_publisher(Odometry, "/sim/ground_truth/odom", qos_profile_sensor_data)
    expected, expected_depth = RayCastWorld(scene, 1).render(camera_from_pose(*pose, scene.camera.mount, k))
    expected_u8 = np.clip(np.round(expected * 255), 0, 255).astype(np.uint8)

    def matches() -> bool:
        if not images:
            return False
        got = np.frombuffer(bytes(images[-1].data), np.uint8).reshape(48, 64, 3)
        return bool(np.abs(got.astype(int) - expected_u8).max() <= 1)

    images.clear()
    depths.clear()
    assert spin_until(test_node, matches, 30.0, tick=lambda: odom_pub.publish(odom_msg(*pose)))
    stamp = (images[-1].header.stamp.sec, images[-1].header.stamp.nanosec)

    def depth_since_match() -> Image | None:  # the depth of the matching frame or a later one (same pose)
        return next((m for m in depths if (m.header.stamp.sec, m.header.stamp.nanosec) >= stamp), None)

    assert spin_until(test_node, lambda: depth_since_match() is not None, 5.0,
                      tick=lambda: odom_pub.publish(odom_msg(*pose)))
    got_depth = np.frombuffer(bytes(depth_since_match().data), "<f4").reshape(48, 64)
    assert np.allclose(got_depth, expected_depth, rtol=1e-6)

    # round:=0 follows the route follower's lap counter: after lap 1 the operating round starts
    lap_pub = test_node.create_publisher(Int32, "sim/route/lap", 10)
    seen = {"log": False}

    def lap_logged() -> bool:
        seen["log"] = "lap 1: round 2" in "".join(ros_processes.output(cam_proc))
        return seen["log"]

    assert spin_until(test_node, lap_logged, 20.0, tick=lambda: lap_pub.publish(Int32(data=1)))
    assert ros_processes.interrupt(cam_proc) < 10.0
    assert cam_proc.returncode == 0, ros_processes.output(cam_proc)


def test_route_follower_drives_counts_a_lap_and_stops(ros_processes, test_node):
    proc = ros_processes.start("gsrmr-route-follower", "--ros-args", "-p", "laps:=1", "-p", "rate_hz:=20.0")
    cmds: list[Twist] = []
    laps: list[int] = []
    test_node.create_subscription(Twist, "cmd_vel", cmds.append, 10)
    test_node.create_subscription(Int32, "sim/route/lap", lambda m: laps.append(m.data), 10)
    odom_pub = test_node.create_publisher(Odometry, "odom", 10)
    path = LoopPath(load_scene("sandbox").route.waypoints)
    state = {"s": 0.0}

    def at_progress() -> Odometry:
        x, y = path.point_at(state["s"])
        return odom_msg(x, y, path.heading_at(state["s"]))

    assert spin_until(test_node, lambda: len(cmds) >= 3, 30.0, tick=lambda: odom_pub.publish(at_progress())), \
        ros_processes.output(proc)
    assert cmds[-1].linear.x == pytest.approx(0.3) and abs(cmds[-1].angular.z) < 0.05

    # Walk the pose around the loop (0.2 m steps): one lap is counted, then the follower stops.
    last = {"t": 0.0}

    def advance() -> None:
        if time.monotonic() - last["t"] > 0.06 and state["s"] < path.length_m + 0.5:
            state["s"] += 0.2
            last["t"] = time.monotonic()
        odom_pub.publish(at_progress())

    assert spin_until(test_node, lambda: laps == [1], 60.0, tick=advance), (laps, ros_processes.output(proc))
    cmds.clear()
    assert spin_until(test_node, lambda: len(cmds) >= 3, 10.0, tick=lambda: odom_pub.publish(at_progress()))
    assert all(c.linear.x == 0.0 and c.angular.z == 0.0 for c in cmds[-3:])
    assert ros_processes.interrupt(proc) < 10.0
    assert proc.returncode == 0


def test_route_follower_waiting_for_the_server_holds_still_until_a_slot_is_composed(ros_processes, test_node):
    """``wait_for_server`` (as sim.launch.py sets it): zero Twists, however long, until mr/slot_info has a message;
    then it drives."""
    proc = ros_processes.start("gsrmr-route-follower", "--ros-args", "-p", "wait_for_server:=true")
    cmds: list[Twist] = []
    test_node.create_subscription(Twist, "cmd_vel", cmds.append, 10)
    odom_pub = test_node.create_publisher(Odometry, "odom", 10)
    info_pub = test_node.create_publisher(Float64MultiArray, MR_SLOT_INFO_TOPIC, UPLINK_QOS)
    path = LoopPath(load_scene("sandbox").route.waypoints)
    at_start = odom_msg(*path.point_at(0.0), path.heading_at(0.0))
    assert spin_until(test_node, lambda: len(cmds) >= 20, 30.0, tick=lambda: odom_pub.publish(at_start)), \
        ros_processes.output(proc)
    assert all(c.linear.x == 0.0 and c.angular.z == 0.0 for c in cmds)
    info = Float64MultiArray(data=MRSlotInfo.of(1, "render", None, 0.0).to_data())
    assert spin_until(test_node, lambda: cmds[-1].linear.x > 0.0, 30.0,
                      tick=lambda: (odom_pub.publish(at_start), info_pub.publish(info))), ros_processes.output(proc)
    assert cmds[-1].linear.x == pytest.approx(0.3)
    assert "the server composes: setting off" in "".join(ros_processes.output(proc))
    assert ros_processes.interrupt(proc) < 10.0
    assert proc.returncode == 0
