"""World nodes as real processes: the mock camera publishes Image + CameraInfo (+ depth) rendered at the true
pose and stamped with that pose's stamp; the route follower drives the loop, counts a lap and stops."""

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
from gsrmr_sim.world.camera_node import TruePose, frame_pose
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


def odom_msg(x: float, y: float, yaw: float, stamp: tuple[int, int] = (0, 0)) -> Odometry:
    msg = Odometry()
    msg.header.stamp.sec, msg.header.stamp.nanosec = stamp
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

    # Now the true pose arrives, two poses in turn, each message with its own stamp (the publisher's clock, here far
    # from the camera's): each frame must be rendered exactly at one of them and carry that pose's stamp.
    poses = [(0.4, -0.3, 2.0), (0.4, -0.3, 2.4)]
    odom_pub = test_node.create_publisher(Odometry, "/sim/ground_truth/odom", qos_profile_sensor_data)
    rendered = [RayCastWorld(scene, 1).render(camera_from_pose(*p, scene.camera.mount, k)) for p in poses]
    expected_u8 = [np.clip(np.round(rgb * 255), 0, 255).astype(np.uint8) for rgb, _ in rendered]
    published: dict[tuple[int, int], int] = {}  # stamp → index of the pose sent with it
    current = {"pose": 0}

    def key(m: Image | CameraInfo) -> tuple[int, int]:
        return m.header.stamp.sec, m.header.stamp.nanosec

    def true_frames() -> list[Image]:
        return [m for m in images if key(m) in published]

    def publish_next() -> None:
        # Pose 0 until a frame rendered at it has arrived, then pose 1. (Alternating per message could lock to the
        # camera's rate: with an even number of messages between two of its frames, every frame named the same pose
        # — a clean-clone CI run failed so.)
        if current["pose"] == 0 and any(published[key(m)] == 0 for m in true_frames()):
            current["pose"] = 1
        n = len(published)
        stamp = (1_000 + n, 250_000_000 + n)
        published[stamp] = current["pose"]
        odom_pub.publish(odom_msg(*poses[current["pose"]], stamp=stamp))

    images.clear()
    depths.clear()
    infos.clear()
    assert spin_until(test_node, lambda: {published[key(m)] for m in true_frames()} == {0, 1}, 30.0,
                      tick=publish_next), (len(published), [published[key(m)] for m in true_frames()], len(images),
                                           ros_processes.output(cam_proc))
    first = images.index(true_frames()[0])
    assert all(key(m) in published for m in images[first:])  # from the first true pose on: only its stamps
    assert len({key(m) for m in images}) == len(images)  # no stamp twice
    for m in true_frames():
        got = np.frombuffer(bytes(m.data), np.uint8).reshape(48, 64, 3)
        assert np.abs(got.astype(int) - expected_u8[published[key(m)]]).max() <= 1, key(m)
    # CameraInfo and depth carry the frame's stamp too, the depth of the pose it names
    assert spin_until(test_node, lambda: any(key(m) in published for m in depths)
                      and any(key(m) in published for m in infos), 5.0, tick=publish_next)
    assert {key(m) for m in infos if key(m) in published} & {key(m) for m in true_frames()}
    for m in (m for m in depths if key(m) in published):
        got_depth = np.frombuffer(bytes(m.data), "<f4").reshape(48, 64)
        assert np.allclose(got_depth, rendered[published[key(m)]][1], rtol=1e-6)

    # round:=0 follows the route follower's lap counter: after lap 1 the operating round starts
    lap_pub = test_node.create_publisher(Int32, "sim/route/lap", 10)
    seen = {"log": False}

    def lap_logged() -> bool:
        seen["log"] = "lap 1: round 2" in "".join(ros_processes.output(cam_proc))
        return seen["log"]

    assert spin_until(test_node, lap_logged, 20.0, tick=lambda: lap_pub.publish(Int32(data=1)))
    assert ros_processes.interrupt(cam_proc) < 10.0
    assert cam_proc.returncode == 0, ros_processes.output(cam_proc)


def test_a_frame_is_stamped_with_the_true_pose_it_renders():
    """The mock camera's rule (:func:`frame_pose`): the newest true pose at its own stamp; nothing when that pose was
    rendered already; the scripted pose at ``now`` once the true pose is older than the timeout."""
    pose = (0.4, -0.3, 2.0)
    latest = TruePose(pose, stamp_ns=5_000_000_123, received_ns=9_000_000_000)
    assert frame_pose(latest, 9_010_000_000, 1.0, None) == (5_000_000_123, pose)
    assert frame_pose(latest, 9_010_000_000, 1.0, 5_000_000_123) is None
    assert frame_pose(latest, 10_000_000_001, 1.0, 5_000_000_123) == (10_000_000_001, None)
    assert frame_pose(None, 42, 1.0, None) == (42, None)


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
