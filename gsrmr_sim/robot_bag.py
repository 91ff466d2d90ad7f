"""A rosbag2 bag of the simulated world, recorded the way a LIMO records one (``python -m gsrmr_sim.robot_bag``).

Written with the ``rosbags`` writer (no live recorder needed), deterministic for a :class:`RobotBagRecipe` (seed
included). Topics, timing, frames and poses, the distorted camera, drift and ``truth.json``: docs/world.md, "A
recorded bag, as a robot records one".
"""

from __future__ import annotations

import argparse
from dataclasses import asdict, dataclass, field
import itertools
import json
import math
from pathlib import Path
import sys
from typing import Any

import cv2
import numpy as np
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from gsrmr_common import tf_tree
from gsrmr_common.calibration import PLUMB_BOB, CameraCalibration, rectified_intrinsics
from gsrmr_common.camera import CameraMount, Intrinsics, camera_from_pose, camera_to_world_from_pose
from gsrmr_common.jpeg import encode_jpeg
from gsrmr_common.pose2d import Pose2D
from gsrmr_common.wire import JPEG_FORMAT
from gsrmr_sim.world.kinematics import Drive, drive_route, start_pose, unicycle_step
from gsrmr_sim.world.points import make_world
from gsrmr_sim.world.recorder import with_resolution
from gsrmr_sim.world.scene import Route, load_scene

IMAGE_COMPRESSED_TOPIC = "/camera/color/image_raw/compressed"
IMAGE_RAW_TOPIC = "/camera/color/image_raw"
CAMERA_INFO_TOPIC = "/camera/color/camera_info"
TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"
ODOM_TOPIC = "/odom"
#: The optical frame's name as a real camera driver (Orbbec, RealSense) gives it — not ours on purpose.
OPTICAL_FRAME = "camera_color_optical_frame"
TF_RATE_HZ = 50.0
#: plumb_bob (k1, k2, t1, t2, k3): mild barrel distortion, as a small RGB-D camera's colour lens has.
DEFAULT_DISTORTION = (-0.12, 0.05, 0.0008, -0.0005, -0.012)
DEFAULT_START_STAMP_NS = 1_767_225_600_000_000_000  # 2026-01-01T00:00:00Z
BAG_DIR = "bag"
TRUTH_FILE = "truth.json"
TRUTH_FORMAT = "gsrmr-robot-bag-truth/1"
STORAGES = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}
_CONTROL_STEP_NS = 10_000_000  # the route controller's step (100 Hz)
BLUR_LENGTHS_PX = (9, 11, 13, 15)  # odd: the line kernel has a centre pixel
_NS_PER_S = 1_000_000_000
_TYPES = get_typestore(Stores.ROS2_KILTED)
_MSG = _TYPES.types


@dataclass(frozen=True)
class RobotBagRecipe:
    """What to record (units in the names). ``frames`` counts every image, the ``2·frames_outside`` ones outside the
    odometry's span included; the recording lasts about (``frames`` + 1) / the scene's camera rate, starting
    ``drive_start_s`` into the robot's drive along the route."""

    scene: str = "sandbox"
    frames: int = 150
    drive_start_s: float = 0.0
    width_px: int = 320
    height_px: int = 240
    drift: bool = False
    storage: str = "mcap"
    compressed: bool = True
    seed: int = 0
    distortion: tuple[float, ...] = DEFAULT_DISTORTION
    blurred_frames: int = 3
    frames_outside: int = 2
    jpeg_quality: int = 90
    start_stamp_ns: int = DEFAULT_START_STAMP_NS
    image_offset_ms: float = 7.0
    image_jitter_ms: float = 3.0
    image_latency_ms: tuple[float, float] = (12.0, 20.0)
    drift_yaw_rad_per_m: float = 0.03
    drift_scale_error: float = 0.02

    def __post_init__(self) -> None:
        if self.storage not in STORAGES:
            raise ValueError(f"storage must be one of {sorted(STORAGES)}, got {self.storage!r}")
        if self.frames_outside < 0 or self.blurred_frames < 0:
            raise ValueError("frames_outside and blurred_frames must be ≥ 0")
        inside = self.frames - 2 * self.frames_outside
        if inside < max(2, 2 * self.blurred_frames + 1):
            raise ValueError(f"{self.frames} frames leave {inside} inside the odometry's span: too few for "
                             f"{self.blurred_frames} blurred ones between sharp neighbours")
        if not 0.0 <= self.drive_start_s < 3600.0:
            raise ValueError(f"drive_start_s must be in [0, 3600) s, got {self.drive_start_s}")
        if not 0.0 <= self.image_jitter_ms < self.image_offset_ms:
            raise ValueError("image_jitter_ms must be in [0, image_offset_ms): stamps stay after their nominal time")
        if len(self.distortion) != 5 or not any(self.distortion):
            raise ValueError("distortion must be 5 plumb_bob coefficients (k1, k2, t1, t2, k3), not all zero")
        object.__setattr__(self, "distortion", tuple(float(v) for v in self.distortion))
        object.__setattr__(self, "image_latency_ms", tuple(float(v) for v in self.image_latency_ms))


@dataclass(frozen=True)
class OdometryDrift:
    """Dead-reckoning error: every odometry increment is scaled by ``1 + scale_error`` (a wrong wheel radius) and its
    yaw grows by ``yaw_rad_per_m`` per metre travelled (a gyro bias per distance)."""

    yaw_rad_per_m: float
    scale_error: float

    @classmethod
    def draw(cls, rng: np.random.Generator, max_yaw_rad_per_m: float, max_scale_error: float) -> OdometryDrift:
        """A seeded drift: each magnitude in [0.5, 1] × its maximum, each sign at random."""
        yaw, scale = rng.uniform(0.5, 1.0, 2) * np.array([max_yaw_rad_per_m, max_scale_error])
        signs = rng.choice([-1.0, 1.0], 2)
        return cls(float(yaw * signs[0]), float(scale * signs[1]))


@dataclass(frozen=True)
class TruthFrame:
    """One image of the bag: header stamp and bag record time [ns since the epoch], the true planar pose
    (``base_link`` in ``map``: a_m, b_m, theta_rad), the true ``map → optical`` 4×4 (OpenCV axes), motion blur
    (``blur_length_px`` 0 = sharp) and whether the stamp lies within the odometry's span."""

    index: int
    stamp_ns: int
    log_time_ns: int
    pose: Pose2D
    map_from_optical: np.ndarray = field(repr=False)
    blurred: bool
    blur_length_px: int
    in_pose_range: bool

    def to_json(self) -> dict[str, Any]:
        return {"index": self.index, "stamp_ns": self.stamp_ns, "log_time_ns": self.log_time_ns,
                "pose": list(self.pose), "map_from_optical": self.map_from_optical.tolist(), "blurred": self.blurred,
                "blur_length_px": self.blur_length_px, "in_pose_range": self.in_pose_range}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> TruthFrame:
        return cls(int(d["index"]), int(d["stamp_ns"]), int(d["log_time_ns"]),
                   (float(d["pose"][0]), float(d["pose"][1]), float(d["pose"][2])),
                   np.asarray(d["map_from_optical"], dtype=np.float64), bool(d["blurred"]), int(d["blur_length_px"]),
                   bool(d["in_pose_range"]))


@dataclass(frozen=True)
class RobotBag:
    """A written bag and its ground truth (``truth.json``; :func:`load_truth` reads it back)."""

    bag_path: Path
    truth_path: Path
    recipe: RobotBagRecipe
    calibration: CameraCalibration
    rectified: Intrinsics  # the rectified pinhole camera (P), pixel centres at +0.5
    mount: CameraMount
    map_from_odom: Pose2D  # a_m, b_m, theta_rad: the true pose where odometry started
    tf_first_stamp_ns: int
    tf_last_stamp_ns: int
    drift: OdometryDrift | None
    frames: tuple[TruthFrame, ...]

    @property
    def image_topic(self) -> str:
        return IMAGE_COMPRESSED_TOPIC if self.recipe.compressed else IMAGE_RAW_TOPIC


# ---------------------------------------------------------------------------------------------------- the robot


class TrueTrajectory:
    """The robot's true planar pose in ``map`` at any time ``t_ns`` [ns since the recording started]: the route driven
    closed loop from its start (:func:`~gsrmr_sim.world.kinematics.drive_route`, one control per 10 ms step); within
    a step the pose follows that step's arc exactly. Before 0 the robot stands at the start."""

    def __init__(self, route: Route, duration_ns: int) -> None:
        steps = int(duration_ns // _CONTROL_STEP_NS) + 2
        self.drive: Drive = drive_route(route, steps, _CONTROL_STEP_NS / _NS_PER_S, pose0=start_pose(route),
                                        substeps=1)

    def pose_at(self, t_ns: int) -> Pose2D:
        """(a_m, b_m, theta_rad) of ``base_link`` in ``map`` at ``t_ns``."""
        if t_ns <= 0:
            return Pose2D.of(self.drive.poses[0])
        k = int(t_ns // _CONTROL_STEP_NS)
        if k >= len(self.drive.poses):
            raise ValueError(f"t_ns {t_ns} is past the driven trajectory")
        a, b, th = (float(v) for v in self.drive.poses[k])
        v_mps, omega_rps = (float(v) for v in self.drive.controls[k])
        return unicycle_step((a, b, th), v_mps, omega_rps, (t_ns - k * _CONTROL_STEP_NS) / _NS_PER_S)


def odometry_poses(map_poses: list[Pose2D],
                   drift: OdometryDrift | None) -> list[Pose2D]:
    """``odom → base_link`` at each sample of the true ``map`` poses; ``odom`` is the first pose. Without drift
    exact; with drift, the true increments between samples, corrupted by ``drift``, integrated from zero."""
    origin_inverse = Pose2D.of(map_poses[0]).inverse()
    if drift is None:
        return [origin_inverse.compose(p) for p in map_poses]
    out = [Pose2D()]
    for before, after in itertools.pairwise(map_poses):
        dx, dy, dyaw = Pose2D.of(after).relative_to(before)
        travelled_m = math.hypot(dx, dy)
        scale = 1.0 + drift.scale_error
        out.append(out[-1].compose((dx * scale, dy * scale, dyaw + drift.yaw_rad_per_m * travelled_m)))
    return out


# ---------------------------------------------------------------------------------------------------- the camera


class DistortedCamera:
    """The raw camera: a plumb_bob calibration on the scene's pinhole intrinsics (K in ROS convention, P the alpha-0
    rectified camera), the pinhole camera to render (same focal lengths, large enough for every raw pixel's ray plus a
    2 px margin) and the raw-pixel → render-pixel maps."""

    MARGIN_PX = 2

    def __init__(self, pinhole: Intrinsics, distortion: tuple[float, ...]) -> None:
        k_ros = pinhole.ros_k()
        bare = CameraCalibration(pinhole.width, pinhole.height, k_ros, PLUMB_BOB, distortion)
        self.rectified = rectified_intrinsics(bare)
        p = np.hstack([self.rectified.ros_k(), np.zeros((3, 1))])
        self.calibration = CameraCalibration(pinhole.width, pinhole.height, k_ros, PLUMB_BOB, distortion, p=p,
                                             frame_id=OPTICAL_FRAME)
        # every raw pixel centre (integers, ROS) → its normalised ray
        uu, vv = np.meshgrid(np.arange(pinhole.width, dtype=np.float64), np.arange(pinhole.height, dtype=np.float64))
        pts = np.stack([uu.ravel(), vv.ravel()], axis=1).reshape(-1, 1, 2)
        norm = cv2.undistortPoints(pts, k_ros, bare.distortion_array(),
                                   criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12))
        norm = norm.reshape(pinhole.height, pinhole.width, 2)
        x0, x1 = float(norm[..., 0].min()), float(norm[..., 0].max())
        y0, y1 = float(norm[..., 1].min()), float(norm[..., 1].max())
        m = self.MARGIN_PX
        fx, fy = pinhole.fx, pinhole.fy
        # a ray x lands at fx·x + cx (pixel centres at +0.5): x0 at the centre of pixel m
        cx, cy = m + 0.5 - fx * x0, m + 0.5 - fy * y0
        self.render_intrinsics = Intrinsics(fx, fy, cx, cy, math.ceil(fx * (x1 - x0)) + 2 * m + 1,
                                            math.ceil(fy * (y1 - y0)) + 2 * m + 1)
        # cv2.remap samples at integer pixel centres: subtract the half pixel
        self.map_x = (fx * norm[..., 0] + cx - 0.5).astype(np.float32)
        self.map_y = (fy * norm[..., 1] + cy - 0.5).astype(np.float32)

    def distort(self, render: np.ndarray) -> np.ndarray:
        """The raw frame (calibration size) from a render of :attr:`render_intrinsics` (bilinear)."""
        return cv2.remap(render, self.map_x, self.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def motion_blur(frame_u8: np.ndarray, length_px: int, angle_rad: float) -> np.ndarray:
    """``frame_u8`` smeared along a line of ``length_px`` (odd) at ``angle_rad`` from the image x axis."""
    kernel = np.zeros((length_px, length_px), np.float32)
    c = length_px // 2
    dx, dy = c * math.cos(angle_rad), c * math.sin(angle_rad)
    cv2.line(kernel, (round(c - dx), round(c - dy)), (round(c + dx), round(c + dy)), 1.0, thickness=1)
    kernel /= kernel.sum()
    return cv2.filter2D(frame_u8, -1, kernel, borderType=cv2.BORDER_REFLECT)


def _blur_choice(rng: np.random.Generator, inside: list[int], count: int) -> list[int]:
    """``count`` seeded indices among ``inside`` (sorted), neither at its ends nor next to each other (every such
    set equally likely: ``count`` sorted draws from the interior shortened by ``count − 1``, spread by 0, 1, 2, …)."""
    interior = inside[1:-1]
    if count == 0:
        return []
    if len(interior) < 2 * count - 1:
        raise ValueError(f"cannot place {count} blurred frames between sharp neighbours among {len(inside)}")
    picks = np.sort(rng.choice(len(interior) - count + 1, size=count, replace=False))
    return [interior[int(p) + n] for n, p in enumerate(picks)]


# ---------------------------------------------------------------------------------------------------- messages


def _time(stamp_ns: int) -> Any:
    sec, nanosec = divmod(int(stamp_ns), _NS_PER_S)
    return _MSG["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)


def _header(stamp_ns: int, frame_id: str) -> Any:
    return _MSG["std_msgs/msg/Header"](stamp=_time(stamp_ns), frame_id=frame_id)


def _transform_stamped(stamp_ns: int, parent: str, child: str, t: tf_tree.Transform) -> Any:
    vector3, quaternion = _MSG["geometry_msgs/msg/Vector3"], _MSG["geometry_msgs/msg/Quaternion"]
    return _MSG["geometry_msgs/msg/TransformStamped"](
        header=_header(stamp_ns, parent), child_frame_id=child,
        transform=_MSG["geometry_msgs/msg/Transform"](translation=vector3(*t.translation),
                                                      rotation=quaternion(*t.rotation)))


def tf_message(transforms: list[Any]) -> Any:
    """``tf2_msgs/TFMessage`` of ``geometry_msgs/TransformStamped`` messages."""
    return _MSG["tf2_msgs/msg/TFMessage"](transforms=transforms)


def odometry_message(stamp_ns: int, pose: Pose2D, v_mps: float, omega_rps: float) -> Any:
    """``nav_msgs/Odometry`` ``odom → base_link``: pose (x_m, y_m, yaw_rad) in ``odom``, twist in ``base_link``."""
    t = tf_tree.odom_from_base_transform(*pose)
    zeros36 = np.zeros(36, np.float64)
    geo = {name: _MSG[f"geometry_msgs/msg/{name}"] for name in ("Point", "Quaternion", "Pose", "Vector3", "Twist",
                                                                "PoseWithCovariance", "TwistWithCovariance")}
    return _MSG["nav_msgs/msg/Odometry"](
        header=_header(stamp_ns, tf_tree.ODOM_FRAME), child_frame_id=tf_tree.BASE_FRAME,
        pose=geo["PoseWithCovariance"](pose=geo["Pose"](position=geo["Point"](*t.translation),
                                                        orientation=geo["Quaternion"](*t.rotation)),
                                       covariance=zeros36),
        twist=geo["TwistWithCovariance"](twist=geo["Twist"](linear=geo["Vector3"](v_mps, 0.0, 0.0),
                                                            angular=geo["Vector3"](0.0, 0.0, omega_rps)),
                                         covariance=zeros36.copy()))


def camera_info_message(stamp_ns: int, calib: CameraCalibration) -> Any:
    """``sensor_msgs/CameraInfo`` of ``calib`` (ROS conventions, as a driver publishes it)."""
    return _MSG["sensor_msgs/msg/CameraInfo"](
        header=_header(stamp_ns, calib.frame_id), height=calib.height, width=calib.width,
        distortion_model=calib.distortion_model, d=np.asarray(calib.d, np.float64),
        k=calib.k.reshape(-1).astype(np.float64), r=calib.r.reshape(-1).astype(np.float64),
        p=calib.p.reshape(-1).astype(np.float64), binning_x=0, binning_y=0,
        roi=_MSG["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))


def image_message(stamp_ns: int, frame_u8: np.ndarray, compressed: bool, jpeg_quality: int) -> Any:
    """``sensor_msgs/CompressedImage`` (JPEG, image_transport's format string) or ``sensor_msgs/Image`` (rgb8)."""
    header = _header(stamp_ns, OPTICAL_FRAME)
    if compressed:
        data = np.frombuffer(encode_jpeg(frame_u8, jpeg_quality), np.uint8)
        return _MSG["sensor_msgs/msg/CompressedImage"](header=header, format=JPEG_FORMAT, data=data)
    h, w = frame_u8.shape[:2]
    return _MSG["sensor_msgs/msg/Image"](header=header, height=h, width=w, encoding="rgb8", is_bigendian=0,
                                         step=w * 3, data=np.ascontiguousarray(frame_u8, np.uint8).reshape(-1))


def _qos(reliability: QosReliability, durability: QosDurability, depth: int) -> Qos:
    infinite = QosTime(9223372036, 854775807)  # RMW_DURATION_INFINITE, as ros2 bag writes it
    return Qos(QosHistory.KEEP_LAST, depth, reliability, durability, infinite, infinite, QosLiveliness.AUTOMATIC,
               infinite, False)


_SENSOR_QOS = _qos(QosReliability.BEST_EFFORT, QosDurability.VOLATILE, 5)
_RELIABLE_QOS = _qos(QosReliability.RELIABLE, QosDurability.VOLATILE, 100)
_LATCHED_QOS = _qos(QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL, 1)


# ---------------------------------------------------------------------------------------------------- the bag


@dataclass(frozen=True)
class _Timeline:
    """Times in ns since the recording started: image stamps, the odometry's samples and its span."""

    image_ns: list[int]
    tf_ns: list[int]


def _timeline(recipe: RobotBagRecipe, rate_hz: float, rng: np.random.Generator) -> _Timeline:
    period_ns = round(_NS_PER_S / rate_hz)
    tf_step_ns = round(_NS_PER_S / TF_RATE_HZ)
    jitter_ns = rng.uniform(-1.0, 1.0, recipe.frames) * recipe.image_jitter_ms * 1e6
    lead_ns = period_ns  # the first image one period in: every time is positive
    image_ns = [lead_ns + i * period_ns + round(recipe.image_offset_ms * 1e6 + float(j))
                for i, j in enumerate(jitter_ns)]
    n_out = recipe.frames_outside
    # the odometry's span: from the last 50 Hz tick before the midpoint between the last image before it and the
    # first one in it, to the first tick after the midpoint at the other end
    first = image_ns[n_out] - period_ns // 2 if n_out == 0 else (image_ns[n_out - 1] + image_ns[n_out]) // 2
    last_in = recipe.frames - n_out - 1
    last = (image_ns[last_in] + period_ns // 2 if n_out == 0
            else (image_ns[last_in] + image_ns[last_in + 1]) // 2)
    tf_first = (first // tf_step_ns) * tf_step_ns
    tf_last = -(-last // tf_step_ns) * tf_step_ns
    return _Timeline(image_ns, list(range(tf_first, tf_last + 1, tf_step_ns)))


def write_robot_bag(out_dir: str | Path, recipe: RobotBagRecipe | None = None, *, progress: bool = False) -> RobotBag:
    """Record the simulated world as a LIMO records it (module docstring) into ``out_dir/bag`` (which must not exist)
    and write ``out_dir/truth.json``; returns the bag, its calibration and the ground truth."""
    recipe = recipe or RobotBagRecipe()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    scene = with_resolution(load_scene(recipe.scene), recipe.width_px, recipe.height_px)
    mount = scene.camera.mount
    # one seeded stream per purpose: drift on or off leaves the stamps, latencies and blurred frames alike
    rng_stamps, rng_drift, rng_latency, rng_blur = (np.random.default_rng((recipe.seed, n)) for n in range(4))
    timeline = _timeline(recipe, scene.camera.rate_hz, rng_stamps)
    start_ns = int(recipe.start_stamp_ns)
    drive_start_ns = round(recipe.drive_start_s * _NS_PER_S)
    trajectory = TrueTrajectory(scene.route, drive_start_ns + max(timeline.image_ns[-1], timeline.tf_ns[-1]))
    camera = DistortedCamera(scene.camera.intrinsics, recipe.distortion)
    drift = None
    if recipe.drift:
        drift = OdometryDrift.draw(rng_drift, recipe.drift_yaw_rad_per_m, recipe.drift_scale_error)

    messages: list[tuple[int, str, Any]] = []  # (log time ns, topic, message)
    # odometry: /tf and /odom at 50 Hz
    map_poses = [trajectory.pose_at(drive_start_ns + t) for t in timeline.tf_ns]
    odom = odometry_poses(map_poses, drift)
    tf_latency_ns = rng_latency.uniform(0.3e6, 1.5e6, len(odom))
    dt_s = 1.0 / TF_RATE_HZ
    for j, (t_ns, pose) in enumerate(zip(timeline.tf_ns, odom, strict=True)):
        stamp = start_ns + t_ns
        prev = odom[max(j - 1, 0)]
        step = Pose2D.of(pose).relative_to(prev)
        v_mps, omega_rps = (math.copysign(math.hypot(step[0], step[1]), step[0]) / dt_s, step[2] / dt_s) if j else (
            0.0, 0.0)
        log = stamp + round(float(tf_latency_ns[j]))
        messages.append((log, TF_TOPIC, tf_message([_transform_stamped(
            stamp, tf_tree.ODOM_FRAME, tf_tree.BASE_FRAME, tf_tree.odom_from_base_transform(*pose))])))
        messages.append((log + 100_000, ODOM_TOPIC, odometry_message(stamp, pose, v_mps, omega_rps)))
    # /tf_static, latched, at the start of the recording
    map_from_odom = map_poses[0]
    messages.append((start_ns + 1_000_000, TF_STATIC_TOPIC, tf_message([
        _transform_stamped(start_ns, tf_tree.MAP_FRAME, tf_tree.ODOM_FRAME,
                           tf_tree.map_from_odom_transform(*map_from_odom)),
        _transform_stamped(start_ns, tf_tree.BASE_FRAME, tf_tree.CAMERA_FRAME,
                           tf_tree.base_from_camera_link_transform(mount)),
        _transform_stamped(start_ns, tf_tree.CAMERA_FRAME, OPTICAL_FRAME, tf_tree.CAMERA_LINK_FROM_OPTICAL)])))

    # images
    tf_first, tf_last = timeline.tf_ns[0], timeline.tf_ns[-1]
    inside = [i for i, t in enumerate(timeline.image_ns) if tf_first <= t <= tf_last]
    expected_inside = list(range(recipe.frames_outside, recipe.frames - recipe.frames_outside))
    if inside != expected_inside:  # only a camera rate near the TF rate can do this
        raise ValueError(f"camera rate {scene.camera.rate_hz} Hz: the odometry span does not separate the images")
    blurred = set(_blur_choice(rng_blur, inside, recipe.blurred_frames))
    latency_ns = rng_latency.uniform(recipe.image_latency_ms[0] * 1e6, recipe.image_latency_ms[1] * 1e6, recipe.frames)
    world = make_world(scene, 1)
    truth: list[TruthFrame] = []
    for i, t_ns in enumerate(timeline.image_ns):
        pose = trajectory.pose_at(drive_start_ns + t_ns)
        render, _depth = world.render(camera_from_pose(*pose, mount, camera.render_intrinsics),
                                      (drive_start_ns + t_ns) / _NS_PER_S)
        frame_u8 = np.clip(np.round(camera.distort(render) * 255.0), 0, 255).astype(np.uint8)
        blur_px = 0
        if i in blurred:
            blur_px = int(rng_blur.choice(BLUR_LENGTHS_PX))
            frame_u8 = motion_blur(frame_u8, blur_px, float(rng_blur.uniform(0.0, math.pi)))
        stamp = start_ns + t_ns
        log = stamp + round(float(latency_ns[i]))
        topic = IMAGE_COMPRESSED_TOPIC if recipe.compressed else IMAGE_RAW_TOPIC
        messages.append((log, topic, image_message(stamp, frame_u8, recipe.compressed, recipe.jpeg_quality)))
        messages.append((log + 200_000, CAMERA_INFO_TOPIC, camera_info_message(stamp, camera.calibration)))
        truth.append(TruthFrame(i, stamp, log, pose, camera_to_world_from_pose(*pose, mount), i in blurred, blur_px,
                                tf_first <= t_ns <= tf_last))
        if progress and i % 20 == 0:
            print(f"robot bag: image {i}/{recipe.frames}", flush=True)

    bag = RobotBag(out / BAG_DIR, out / TRUTH_FILE, recipe, camera.calibration, camera.rectified, mount,
                   map_from_odom, start_ns + tf_first, start_ns + tf_last, drift, tuple(truth))
    _write_bag(bag.bag_path, recipe.storage, messages)
    bag.truth_path.write_text(json.dumps(_truth_json(bag), indent=1))
    return bag


def _write_bag(path: Path, storage: str, messages: list[tuple[int, str, Any]]) -> None:
    """The rosbag2 bag of ``messages`` (written in log-time order), every topic with its type and offered QoS."""
    qos = {TF_STATIC_TOPIC: _LATCHED_QOS, IMAGE_COMPRESSED_TOPIC: _SENSOR_QOS, IMAGE_RAW_TOPIC: _SENSOR_QOS,
           CAMERA_INFO_TOPIC: _SENSOR_QOS}
    with Writer(path, version=Writer.VERSION_LATEST, storage_plugin=STORAGES[storage]) as writer:
        connections: dict[str, Any] = {}
        for log_ns, topic, msg in sorted(messages, key=lambda m: m[0]):
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msg.__msgtype__, typestore=_TYPES,
                                                           offered_qos_profiles=[qos.get(topic, _RELIABLE_QOS)])
            writer.write(connections[topic], log_ns, _TYPES.serialize_cdr(msg, msg.__msgtype__))


def _truth_json(bag: RobotBag) -> dict[str, Any]:
    k = bag.rectified
    recipe = asdict(bag.recipe)
    return {"format": TRUTH_FORMAT, "recipe": recipe, "bag": bag.bag_path.name,
            "topics": {"image": bag.image_topic, "camera_info": CAMERA_INFO_TOPIC, "tf": TF_TOPIC,
                       "tf_static": TF_STATIC_TOPIC, "odom": ODOM_TOPIC},
            "optical_frame": OPTICAL_FRAME, "calibration": bag.calibration.to_yaml_dict(),
            "rectified_intrinsics": {"fl_x": k.fx, "fl_y": k.fy, "cx": k.cx, "cy": k.cy, "w": k.width, "h": k.height},
            "mount": bag.mount.as_parameters(prefix=""), "map_from_odom": list(bag.map_from_odom),
            "tf_rate_hz": TF_RATE_HZ, "tf_first_stamp_ns": bag.tf_first_stamp_ns,
            "tf_last_stamp_ns": bag.tf_last_stamp_ns, "drift": asdict(bag.drift) if bag.drift else None,
            "frames": [f.to_json() for f in bag.frames]}


def load_truth(out_dir: str | Path) -> RobotBag:
    """The :class:`RobotBag` that :func:`write_robot_bag` wrote into ``out_dir`` (from its ``truth.json``)."""
    out = Path(out_dir)
    doc = json.loads((out / TRUTH_FILE).read_text())
    if doc.get("format") != TRUTH_FORMAT:
        raise ValueError(f"{out / TRUTH_FILE}: not a {TRUTH_FORMAT} file")
    recipe = RobotBagRecipe(**{key: tuple(v) if isinstance(v, list) else v for key, v in doc["recipe"].items()})
    cal = doc["calibration"]
    calib = CameraCalibration(cal["image_width"], cal["image_height"], cal["camera_matrix"]["data"],
                              cal["distortion_model"], tuple(cal["distortion_coefficients"]["data"]),
                              r=cal["rectification_matrix"]["data"], p=cal["projection_matrix"]["data"],
                              frame_id=cal["camera_name"])
    k = doc["rectified_intrinsics"]
    m = doc["map_from_odom"]
    return RobotBag(out / doc["bag"], out / TRUTH_FILE, recipe, calib,
                    Intrinsics(k["fl_x"], k["fl_y"], k["cx"], k["cy"], k["w"], k["h"]), CameraMount(**doc["mount"]),
                    (float(m[0]), float(m[1]), float(m[2])), int(doc["tf_first_stamp_ns"]),
                    int(doc["tf_last_stamp_ns"]), OdometryDrift(**doc["drift"]) if doc["drift"] else None,
                    tuple(TruthFrame.from_json(f) for f in doc["frames"]))


# ---------------------------------------------------------------------------------------------------- CLI


def build_parser() -> argparse.ArgumentParser:
    defaults = RobotBagRecipe()
    p = argparse.ArgumentParser(prog="python -m gsrmr_sim.robot_bag", description=__doc__.splitlines()[0])
    p.add_argument("out", help="output folder (gets bag/ and truth.json; bag/ must not exist)")
    p.add_argument("--scene", default=defaults.scene, help="scene name (config/scenes) or YAML path")
    length = p.add_mutually_exclusive_group()
    length.add_argument("--frames", type=int, default=None, help=f"images in all (default {defaults.frames})")
    length.add_argument("--duration-s", type=float, default=None, help="or: seconds at the scene's camera rate")
    p.add_argument("--drive-start-s", type=float, default=defaults.drive_start_s,
                   help="seconds the robot has driven the route when the recording starts")
    p.add_argument("--width", type=int, default=defaults.width_px)
    p.add_argument("--height", type=int, default=defaults.height_px)
    p.add_argument("--drift", action="store_true", help="odometry drifts (seeded yaw per metre and scale error)")
    p.add_argument("--storage", choices=sorted(STORAGES), default=defaults.storage)
    p.add_argument("--raw", action="store_true", help=f"sensor_msgs/Image on {IMAGE_RAW_TOPIC} instead of JPEG")
    p.add_argument("--seed", type=int, default=defaults.seed)
    p.add_argument("--blurred", type=int, default=defaults.blurred_frames, help="motion-blurred images")
    p.add_argument("--outside", type=int, default=defaults.frames_outside,
                   help="images before the first and after the last odometry sample (each end)")
    return p


def main(argv: list[str] | None = None) -> int:
    """``python -m gsrmr_sim.robot_bag OUT [...]``: writes the bag, prints a one-line JSON summary."""
    ns = build_parser().parse_args(argv)
    frames = ns.frames
    if ns.duration_s is not None:
        frames = max(1, round(ns.duration_s * load_scene(ns.scene).camera.rate_hz))
    recipe = RobotBagRecipe(scene=ns.scene, frames=frames or RobotBagRecipe.frames, drive_start_s=ns.drive_start_s,
                            width_px=ns.width,
                            height_px=ns.height, drift=ns.drift, storage=ns.storage, compressed=not ns.raw,
                            seed=ns.seed, blurred_frames=ns.blurred, frames_outside=ns.outside)
    bag = write_robot_bag(ns.out, recipe, progress=True)
    print(json.dumps({"bag": str(bag.bag_path), "truth": str(bag.truth_path), "images": len(bag.frames),
                      "in_pose_range": sum(f.in_pose_range for f in bag.frames),
                      "blurred": [f.index for f in bag.frames if f.blurred], "drift": asdict(bag.drift)
                      if bag.drift else None}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
