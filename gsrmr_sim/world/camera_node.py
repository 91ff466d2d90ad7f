"""``gsrmr-mock-camera``: the robot's camera in the simulated world, as a ROS 2 node.

Renders the real world at the robot's true pose. Topics, QoS, stamping, the round clock and the scripted fallback
pose: docs/world.md, "Nodes"; parameters: :class:`MockCameraParameters`. ``camera/camera_info`` carries K in the
ROS convention (pixel centres at integers), plumb_bob with zero distortion and P = [K | 0].
"""

from __future__ import annotations

from dataclasses import dataclass

from nav_msgs.msg import Odometry
import numpy as np
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Int32

from gsrmr_common.camera import camera_from_pose
from gsrmr_common.interrupts import console_main
from gsrmr_common.node_help import Endpoint, NodeInterface, ParameterGroup
from gsrmr_common.node_params import NodeParameters, ros_parameter
from gsrmr_common.pose2d import Pose2D, yaw_from_quaternion
from gsrmr_common.ros_node import declare_parameters, run_node
from gsrmr_common.ros_wire import ns_to_stamp, stamp_to_ns
from gsrmr_common.route import LoopPath
from gsrmr_common.tf_tree import CAMERA_OPTICAL_FRAME
from gsrmr_sim.limo.mock import GROUND_TRUTH_TOPIC
from gsrmr_sim.truth_frames import TruthFrameWriter
from gsrmr_sim.world.kinematics import has_moved
from gsrmr_sim.world.points import make_world
from gsrmr_sim.world.recorder import with_resolution
from gsrmr_sim.world.scene import load_scene


@dataclass(frozen=True)
class TruePose:
    """A true pose from ``odom_topic``: (a_m, b_m, theta_rad) of ``base_link`` in ``map``, the time it holds for
    (``stamp_ns``: its ``header.stamp``, or its arrival when unstamped) and its arrival on the node clock [ns]."""

    pose: Pose2D
    stamp_ns: int
    received_ns: int


def frame_pose(latest: TruePose | None, now_ns: int, odom_timeout_s: float,
               last_frame_stamp_ns: int | None) -> tuple[int, Pose2D | None] | None:
    """The stamp [ns] and pose of the frame a tick renders: the newest true pose at its own stamp when it arrived at
    most ``odom_timeout_s`` ago; else ``now_ns`` and None (the scripted pose at that time). None: no frame, the
    newest true pose was rendered already (its stamp is ``last_frame_stamp_ns``)."""
    if latest is None or now_ns - latest.received_ns > odom_timeout_s * 1e9:
        return now_ns, None
    if latest.stamp_ns == last_frame_stamp_ns:
        return None
    return latest.stamp_ns, latest.pose


def image_msg(img_u8: np.ndarray, encoding: str, stamp: object, frame_id: str = CAMERA_OPTICAL_FRAME) -> Image:
    """sensor_msgs/Image from an H×W×3 (rgb8) or H×W (mono8) uint8 array."""
    msg = Image()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.height, msg.width = int(img_u8.shape[0]), int(img_u8.shape[1])
    msg.encoding = encoding
    msg.is_bigendian = 0
    channels = 1 if img_u8.ndim == 2 else img_u8.shape[2]
    msg.step = msg.width * channels
    msg.data = np.ascontiguousarray(img_u8, dtype=np.uint8).tobytes()
    return msg


def depth_msg(depth_m: np.ndarray, stamp: object, frame_id: str = CAMERA_OPTICAL_FRAME) -> Image:
    """sensor_msgs/Image 32FC1 (metres along the optical axis, +inf = nothing in range; REP 118)."""
    msg = Image()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.height, msg.width = int(depth_m.shape[0]), int(depth_m.shape[1])
    msg.encoding = "32FC1"
    msg.is_bigendian = 0
    msg.step = msg.width * 4
    msg.data = np.ascontiguousarray(depth_m, dtype="<f4").tobytes()
    return msg


@dataclass(frozen=True)
class MockCameraParameters(NodeParameters):
    """The mock camera's parameters."""

    scene: str = ros_parameter("sandbox", "Scene name (config/scenes) or YAML path", read_only=True)
    round: int = ros_parameter(1, "1 = mapping (static world), r >= 2 = scored round r - 1 (its change events; "
                               "persistent changes of earlier rounds stay), 0 = follow sim/route/lap (round = 1 + "
                               "laps, clock restarts per lap)", min_value=0, max_value=1000, read_only=True)
    rate_hz: float = ros_parameter(0.0, "Camera rate [Hz] (0 = the scene's)", min_value=0.0, max_value=100.0,
                                   read_only=True)
    width: int = ros_parameter(0, "Image width [px] (0 = the scene's)", min_value=0, max_value=4096, read_only=True)
    height: int = ros_parameter(0, "Image height [px] (0 = the scene's)", min_value=0, max_value=4096,
                                read_only=True)
    odom_topic: str = ros_parameter(GROUND_TRUTH_TOPIC, "True pose (nav_msgs/Odometry, map)", read_only=True)
    odom_timeout_s: float = ros_parameter(1.0, "Use the scripted pose when the true pose is older [s]",
                                          min_value=0.0, read_only=True)
    clock_from_motion: bool = ros_parameter(
        False, "Start the round clock when the true pose first moves (> 1 cm or 0.01 rad) instead of at node start: "
        "change events and agents then follow the route progress however long the stack takes to start",
        read_only=True)
    publish_depth: bool = ros_parameter(True, "Publish camera/depth/image_raw (32FC1, metres, REP 118)",
                                        read_only=True)
    truth_dir: str = ros_parameter("", "Simulation backplane: also write every colour frame to this folder for the "
                                   "scorer's ground-truth evaluation ('' = off)", read_only=True)


#: What ``gsrmr-mock-camera --help`` prints.
INTERFACE = NodeInterface(
    executable="gsrmr-mock-camera", node="gsrmr_mock_camera",
    summary="The robot's camera in the simulated world: renders the scene's real world at the robot's true pose.",
    subscribes=(Endpoint("sim/ground_truth/odom", "nav_msgs/msg/Odometry", "odom_topic: the true pose"),
                Endpoint("sim/route/lap", "std_msgs/msg/Int32", "with round 0")),
    publishes=(Endpoint("camera/image_raw", "sensor_msgs/msg/Image", "rgb8, sensor-data QoS"),
               Endpoint("camera/camera_info", "sensor_msgs/msg/CameraInfo"),
               Endpoint("camera/depth/image_raw", "sensor_msgs/msg/Image", "32FC1 metres, with publish_depth")),
    parameters=(ParameterGroup(MockCameraParameters),))


class MockCamera(Node):
    """Renders the scene's real world at the robot's true pose."""

    def __init__(self) -> None:
        super().__init__("gsrmr_mock_camera")
        p = declare_parameters(self, MockCameraParameters)
        scene_name, rate, width, height, odom_topic, truth_dir = (p.scene, p.rate_hz, p.width, p.height,
                                                                  p.odom_topic, p.truth_dir)
        self.round_param, self.odom_timeout_s = p.round, p.odom_timeout_s
        self.clock_from_motion, self.publish_depth = p.clock_from_motion, p.publish_depth
        self.round_index = self.round_param or 1
        self.truth = TruthFrameWriter(truth_dir) if truth_dir else None
        self.scene = with_resolution(load_scene(scene_name), width or None, height or None)
        self.world = make_world(self.scene, self.round_index)
        self.path = LoopPath(self.scene.route.waypoints)
        self.k = self.scene.camera.intrinsics
        self.pub_image = self.create_publisher(Image, "camera/image_raw", qos_profile_sensor_data)
        self.pub_info = self.create_publisher(CameraInfo, "camera/camera_info", qos_profile_sensor_data)
        self.pub_depth = self.create_publisher(Image, "camera/depth/image_raw", qos_profile_sensor_data)
        self.create_subscription(Odometry, odom_topic, self._on_odom, qos_profile_sensor_data)
        if self.round_param == 0:
            self.create_subscription(Int32, "sim/route/lap", self._on_lap, 10)
        self.true_pose: TruePose | None = None
        self.rest_pose: Pose2D | None = None  # first true pose, while waiting for motion
        # the round's start on the node clock [ns] (None: waiting for the true pose to move)
        self.start_ns: int | None = None if self.clock_from_motion else self.get_clock().now().nanoseconds
        self.last_frame_stamp_ns: int | None = None
        self.frames = 0
        self.pose_source = ""
        period = 1.0 / (rate or self.scene.camera.rate_hz)
        self.timer = self.create_timer(period, self._tick)
        self.get_logger().info(f"mock camera ready: scene {self.scene.name}, round {self.round_index}, "
                               f"{self.k.width}x{self.k.height} at {1.0 / period:.1f} Hz, "
                               f"pose from {odom_topic} "
                               "(scripted route until it arrives)")

    def _on_lap(self, msg: Int32) -> None:
        new_round = min(1000, 1 + int(msg.data))  # persistent changes accumulate lap after lap
        self.start_ns = self.get_clock().now().nanoseconds
        if new_round != self.round_index:
            self.round_index = new_round
            self.world = make_world(self.scene, new_round)
        self.get_logger().info(f"lap {msg.data}: round {self.round_index}, round clock restarted")

    def _on_odom(self, msg: Odometry) -> None:
        q = msg.pose.pose.orientation
        pose = Pose2D(msg.pose.pose.position.x, msg.pose.pose.position.y, yaw_from_quaternion(q.x, q.y, q.z, q.w))
        received_ns = self.get_clock().now().nanoseconds
        try:
            stamp_ns = stamp_to_ns(msg.header.stamp) or received_ns  # unstamped: holds for its arrival
        except ValueError as err:
            self.get_logger().warning(f"true pose refused: {err}", throttle_duration_sec=5.0)
            return
        self.true_pose = TruePose(pose, stamp_ns, received_ns)
        if self.start_ns is None:
            self.rest_pose = self.rest_pose or pose
            if has_moved(pose, self.rest_pose):
                self.start_ns = stamp_ns
                self.get_logger().info("robot moving: round clock started")

    def scripted_pose(self, t_s: float) -> Pose2D:
        """Open-loop route pose at round time ``t_s``: arc length speed·t along the loop."""
        s = self.scene.route.speed_mps * t_s
        x, y = self.path.point_at(s)
        return x, y, self.path.heading_at(s)

    def camera_info(self, stamp: object) -> CameraInfo:
        """CameraInfo with the ROS-convention K of the current intrinsics."""
        info = CameraInfo()
        info.header.stamp = stamp
        info.header.frame_id = CAMERA_OPTICAL_FRAME
        info.width, info.height = self.k.width, self.k.height
        info.distortion_model = "plumb_bob"
        info.d = [0.0] * 5
        k = self.k.ros_k()
        info.k = k.reshape(-1).tolist()
        info.r = np.eye(3).reshape(-1).tolist()
        info.p = np.hstack([k, np.zeros((3, 1))]).reshape(-1).tolist()
        return info

    def _tick(self) -> None:
        choice = frame_pose(self.true_pose, self.get_clock().now().nanoseconds, self.odom_timeout_s,
                            self.last_frame_stamp_ns)
        if choice is None:  # the newest true pose is on the last frame already
            return
        stamp_ns, true_pose = choice
        t_s = 0.0 if self.start_ns is None else max(0.0, (stamp_ns - self.start_ns) * 1e-9)
        pose = true_pose if true_pose is not None else self.scripted_pose(t_s)
        cam = camera_from_pose(*pose, self.scene.camera.mount, self.k)
        rgb, depth = self.world.render(cam, t_s)
        stamp = ns_to_stamp(stamp_ns)
        rgb_u8 = np.clip(np.round(rgb * 255), 0, 255).astype(np.uint8)
        self.pub_image.publish(image_msg(rgb_u8, "rgb8", stamp))
        if self.truth is not None:
            self.truth.put(stamp_ns, rgb_u8)
        self.pub_info.publish(self.camera_info(stamp))
        if self.publish_depth:
            self.pub_depth.publish(depth_msg(depth, stamp))
        self.last_frame_stamp_ns = stamp_ns
        self.frames += 1
        source = "true pose, stamped with its stamp" if true_pose is not None else "scripted"
        if self.frames == 1:
            self.get_logger().info(f"first frame published (pose source: {source})")
        elif source != self.pose_source:
            self.get_logger().info(f"frame {self.frames}: pose source now {source}")
        self.pose_source = source


@console_main
def main(args: list[str] | None = None) -> int:
    """Console script ``gsrmr-mock-camera``."""
    return run_node(MockCamera, args, interface=INTERFACE)


if __name__ == "__main__":
    raise SystemExit(main())
