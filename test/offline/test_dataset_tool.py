"""``gsrmr-dataset`` (gsrmr_offline.dataset_tool) on small synthetic bags written with the rosbags writer.

The recorded round: a robot drives a circle arc (0.3 m/s, 0.5 rad/s); TF map → odom (static) → base_link
(moving, 50 Hz) → camera_link → camera_optical_frame (static, a 6-DoF mount); a 96×72 camera with plumb_bob
distortion at 10 Hz whose stamps fall between the TF samples and whose recorder times lag by 40 ms (using
them would move the camera 12 mm). Each raw frame is the analytic pattern sampled at every raw pixel's
undistorted ray, so the rectified output must be the pattern as the rectified pinhole camera sees it. The
truth poses are composed directly from the trajectory, not through the tool's TF buffer.
"""

from __future__ import annotations

from dataclasses import dataclass
import itertools
import json
import math
from pathlib import Path
import re
import struct

import cv2
import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
import yaml

from gsrmr_common.calibration import CameraCalibration, Rectifier
from gsrmr_common.camera import CameraMount, rpy_matrix
from gsrmr_common.image_decode import decode_colour, decode_depth_m, format_stamp, is_depth_message
from gsrmr_common.metrics import psnr
from gsrmr_common.nerfstudio import read_dataset
from gsrmr_common.tf_tree import base_from_camera_link_transform, quaternion_from_matrix, transform_matrix
from gsrmr_offline import dataset_tool
from gsrmr_offline.bag_dataset import CSV_COLUMNS
from gsrmr_offline.keyframes import blurred, spaced, thin_evenly

NS = 1_000_000_000
T0 = 1_700_000_000 * NS
W, H = 96, 72
K = np.array([[80.0, 0.0, 47.3], [0.0, 79.0, 35.6], [0.0, 0.0, 1.0]])
PLUMB_BOB = (-0.2, 0.05, 0.001, -0.0005, 0.0)
MOUNT = CameraMount(height_m=0.15, pitch_rad=0.1, forward_m=0.1, left_m=0.02, roll_rad=0.02, yaw_rad=-0.05)
MAP_FROM_ODOM = (1.0, -0.5, 0.3)  # a, b, θ
SPEED_MPS, YAW_RATE = 0.3, 0.5
OPTICAL_IN_LINK = (-0.5, 0.5, -0.5, 0.5)
KILTED = get_typestore(Stores.ROS2_KILTED)
NOETIC = get_typestore(Stores.ROS1_NOETIC)
NOETIC.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
IMAGE_TOPIC, INFO_TOPIC = "/camera/color/image_raw", "/camera/color/camera_info"
DEPTH_TOPIC = "/camera/aligned_depth_to_color/image_raw"
CALIB = CameraCalibration(W, H, K, "plumb_bob", PLUMB_BOB, frame_id="camera_optical_frame")


# ------------------------------------------------------------------------------------------------ the truth

def pattern(x_n: np.ndarray, y_n: np.ndarray, phase: float) -> np.ndarray:
    """An RGB texture over normalised image coordinates (periods of 7–20 px at f = 80), in [0, 1]."""
    a = 0.5 + 0.4 * np.sin(33.0 * x_n + phase) * np.cos(29.0 * y_n)
    b = 0.5 + 0.4 * np.cos(51.0 * x_n - 23.0 * y_n + 2.0 * phase)
    c = 0.5 + 0.4 * np.sin(70.0 * y_n + 11.0 * x_n)
    return np.stack([a, b, c], axis=-1)


def raw_rays(calib: CameraCalibration) -> tuple[np.ndarray, np.ndarray]:
    """The normalised ray (x/z, y/z) of every raw pixel centre (ROS: integers) of the distorted camera."""
    uu, vv = np.meshgrid(np.arange(calib.width, dtype=np.float64), np.arange(calib.height, dtype=np.float64))
    pts = np.stack([uu.ravel(), vv.ravel()], axis=1).reshape(-1, 1, 2)
    norm = cv2.undistortPoints(pts, calib.k, calib.distortion_array(),
                               criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12))
    norm = norm.reshape(calib.height, calib.width, 2)
    return norm[..., 0], norm[..., 1]


RAYS = raw_rays(CALIB)


def raw_frame(i: int) -> np.ndarray:
    """Frame i as the distorted camera records it (uint8 RGB)."""
    return np.clip(np.round(pattern(*RAYS, phase=0.3 * i) * 255.0), 0, 255).astype(np.uint8)


def pinhole_view(i: int, rect: Rectifier) -> np.ndarray:
    """Frame i as the rectified pinhole camera sees it (float RGB in [0, 1])."""
    k = rect.intrinsics
    u = (np.arange(k.width) + 0.5 - k.cx) / k.fx
    v = (np.arange(k.height) + 0.5 - k.cy) / k.fy
    return pattern(*np.meshgrid(u, v), phase=0.3 * i)


def raw_depth_mm(i: int) -> np.ndarray:
    """Aligned depth of frame i in millimetres (a tilted plane, never 0)."""
    uu, vv = np.meshgrid(np.arange(W), np.arange(H))
    return (1500 + 7 * uu + 3 * vv + 10 * i).astype(np.uint16)


def planar(x: float, y: float, theta: float) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = rpy_matrix(0.0, 0.0, theta)
    out[:3, 3] = (x, y, 0.0)
    return out


def odom_pose(t_s: float) -> tuple[float, float, float]:
    """base_link in odom at t seconds after T0: a circle arc at SPEED_MPS, YAW_RATE."""
    r = SPEED_MPS / YAW_RATE
    return r * math.sin(YAW_RATE * t_s), r * (1.0 - math.cos(YAW_RATE * t_s)), YAW_RATE * t_s


def true_base(stamp_ns: int) -> np.ndarray:
    return planar(*MAP_FROM_ODOM) @ planar(*odom_pose((stamp_ns - T0) / NS))


def base_from_optical(mount: CameraMount = MOUNT) -> np.ndarray:
    optical = np.eye(4)
    optical[:3, :3] = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    link = np.eye(4)
    link[:3, :3] = rpy_matrix(mount.roll_rad, mount.pitch_rad, mount.yaw_rad)
    link[:3, 3] = (mount.forward_m, mount.left_m, mount.height_m)
    return link @ optical


def true_camera(stamp_ns: int, mount: CameraMount = MOUNT) -> np.ndarray:
    return true_base(stamp_ns) @ base_from_optical(mount)


def pose_errors(got: np.ndarray, want: np.ndarray) -> tuple[float, float]:
    """(position error [m], rotation error [deg]) between two camera→world matrices."""
    cos = (np.trace(got[:3, :3].T @ want[:3, :3]) - 1.0) / 2.0
    return float(np.linalg.norm(got[:3, 3] - want[:3, 3])), math.degrees(math.acos(min(1.0, cos)))


# ------------------------------------------------------------------------------------------- the recording

@dataclass
class Recording:
    """A synthetic round and the knobs the tests turn."""

    n_frames: int = 24
    first_image_s: float = -0.05  # image i at first + i/10 + 7.3 ms (TF: a 20 ms grid from 0): out of range
    image_record_lag_s: float = 0.04
    tf_until_s: float = 2.6
    tf_dropout_s: tuple[float, float] | None = (1.01, 1.39)  # no odom samples in here
    blurred_frames: tuple[int, ...] = ()
    image_kind: str = "raw"  # raw (rgb8 Image) | jpeg | png
    jpeg_copy: bool = False  # also the image_transport republish …/image_raw/compressed
    depth: bool = False
    unregistered_depth: bool = False
    camera_info: bool = True
    tf_static: bool = True
    dynamic_tf: bool = True
    odometry_topic: str | None = None  # "/odom": nav_msgs/Odometry of odom → base_link
    pose_stamped_topic: str | None = None  # "/robot_pose": PoseStamped of base_link in map
    camera_static_tf: bool = True
    image_stamp_shift_s: float = 0.0
    map_from_odom_hz: float | None = None  # map → odom on /tf at this rate (half a period off the images), as a
    #                                         localizer or a ROS 1 static_transform_publisher sends it …
    map_from_odom_wobble_m: float = 0.0  # … its samples alternately this far off in x …
    map_from_odom_drift_mps: float = 0.0  # … and moving this fast in x (a localizer correcting)

    def image_stamp(self, i: int) -> int:
        return T0 + round((self.first_image_s + i * 0.1 + self.image_stamp_shift_s) * NS) + 7_300_000

    def tf_stamps(self) -> list[int]:
        out = []
        for k in range(int(self.tf_until_s / 0.02) + 1):
            t = k * 0.02
            if self.tf_dropout_s and self.tf_dropout_s[0] < t < self.tf_dropout_s[1]:
                continue
            out.append(T0 + k * 20_000_000)
        return out


class Msgs:
    """Message constructors for one typestore (ROS 2 or ROS 1 field names)."""

    def __init__(self, store, ros1: bool) -> None:
        self.t, self.ros1 = store.types, ros1

    def header(self, stamp_ns: int, frame: str):
        time = self.t["builtin_interfaces/msg/Time"](sec=stamp_ns // NS, nanosec=stamp_ns % NS)
        frame = "/" + frame if self.ros1 and frame else frame
        if self.ros1:
            return self.t["std_msgs/msg/Header"](seq=0, stamp=time, frame_id=frame)
        return self.t["std_msgs/msg/Header"](stamp=time, frame_id=frame)

    def transform(self, matrix: np.ndarray):
        q = quaternion_from_matrix(matrix[:3, :3])
        return self.t["geometry_msgs/msg/Transform"](
            translation=self.t["geometry_msgs/msg/Vector3"](*(float(v) for v in matrix[:3, 3])),
            rotation=self.t["geometry_msgs/msg/Quaternion"](*q))

    def tf(self, stamp_ns: int, edges: list[tuple[str, str, np.ndarray]]):
        stamped = [self.t["geometry_msgs/msg/TransformStamped"](
            header=self.header(stamp_ns, parent), child_frame_id=("/" + child) if self.ros1 else child,
            transform=self.transform(m)) for parent, child, m in edges]
        return self.t["tf2_msgs/msg/TFMessage"](transforms=stamped)

    def pose(self, matrix: np.ndarray):
        q = quaternion_from_matrix(matrix[:3, :3])
        return self.t["geometry_msgs/msg/Pose"](position=self.t["geometry_msgs/msg/Point"](
            *(float(v) for v in matrix[:3, 3])), orientation=self.t["geometry_msgs/msg/Quaternion"](*q))

    def odometry(self, stamp_ns: int, matrix: np.ndarray):
        zero3 = self.t["geometry_msgs/msg/Vector3"](0.0, 0.0, 0.0)
        return self.t["nav_msgs/msg/Odometry"](
            header=self.header(stamp_ns, "odom"), child_frame_id="base_link",
            pose=self.t["geometry_msgs/msg/PoseWithCovariance"](pose=self.pose(matrix), covariance=np.zeros(36)),
            twist=self.t["geometry_msgs/msg/TwistWithCovariance"](
                twist=self.t["geometry_msgs/msg/Twist"](linear=zero3, angular=zero3), covariance=np.zeros(36)))

    def pose_stamped(self, stamp_ns: int, frame: str, matrix: np.ndarray):
        return self.t["geometry_msgs/msg/PoseStamped"](header=self.header(stamp_ns, frame), pose=self.pose(matrix))

    def image(self, stamp_ns: int, frame: str, pixels: np.ndarray, encoding: str):
        step = pixels.shape[1] * (pixels.shape[2] if pixels.ndim == 3 else 1) * pixels.dtype.itemsize
        return self.t["sensor_msgs/msg/Image"](
            header=self.header(stamp_ns, frame), height=pixels.shape[0], width=pixels.shape[1], encoding=encoding,
            is_bigendian=0, step=step, data=np.frombuffer(pixels.astype(pixels.dtype.newbyteorder("<")).tobytes(),
                                                          dtype=np.uint8))

    def compressed(self, stamp_ns: int, frame: str, data: bytes, fmt: str):
        return self.t["sensor_msgs/msg/CompressedImage"](header=self.header(stamp_ns, frame), format=fmt,
                                                         data=np.frombuffer(data, dtype=np.uint8))

    def camera_info(self, stamp_ns: int, calib: CameraCalibration):
        fields = {"d": np.array(calib.d), "k": calib.k.ravel(), "r": calib.r.ravel(), "p": calib.p.ravel()}
        if self.ros1:
            fields = {k.upper(): v for k, v in fields.items()}
        roi = self.t["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        return self.t["sensor_msgs/msg/CameraInfo"](
            header=self.header(stamp_ns, calib.frame_id), height=calib.height, width=calib.width,
            distortion_model=calib.distortion_model, binning_x=0, binning_y=0, roi=roi, **fields)


def messages(rec: Recording, m: Msgs) -> list[tuple[str, str, int, object]]:
    """(topic, type, log time, message) of the whole round, any order."""
    out: list[tuple[str, str, int, object]] = []
    tf_msg = "tf2_msgs/msg/TFMessage"
    if rec.map_from_odom_hz:
        period_ns = round(NS / rec.map_from_odom_hz)
        for k in range(-1, round(rec.tf_until_s * rec.map_from_odom_hz) + 2):
            s = T0 + k * period_ns + period_ns // 2
            x_m = MAP_FROM_ODOM[0] + rec.map_from_odom_wobble_m * (k % 2) + rec.map_from_odom_drift_mps * (s - T0) / NS
            out.append(("/tf", tf_msg, s + 1_000_000, m.tf(s, [("map", "odom", planar(x_m, *MAP_FROM_ODOM[1:]))])))
    if rec.tf_static:
        edges = [] if rec.map_from_odom_hz else [("map", "odom", planar(*MAP_FROM_ODOM))]
        if rec.camera_static_tf:
            link = transform_matrix(base_from_camera_link_transform(MOUNT))
            optical = transform_matrix(type(base_from_camera_link_transform(MOUNT))((0.0, 0.0, 0.0), OPTICAL_IN_LINK))
            edges += [("base_link", "camera_link", link), ("camera_link", "camera_optical_frame", optical)]
        out.append(("/tf_static", tf_msg, T0 - NS, m.tf(T0 - NS, edges)))
    for s in rec.tf_stamps():
        odom = planar(*odom_pose((s - T0) / NS))
        if rec.dynamic_tf:
            out.append(("/tf", tf_msg, s + 1_000_000, m.tf(s, [("odom", "base_link", odom)])))
        if rec.odometry_topic:
            out.append((rec.odometry_topic, "nav_msgs/msg/Odometry", s + 2_000_000, m.odometry(s, odom)))
        if rec.pose_stamped_topic:
            out.append((rec.pose_stamped_topic, "geometry_msgs/msg/PoseStamped", s + 2_000_000,
                        m.pose_stamped(s, "map", true_base(s))))
    for i in range(rec.n_frames):
        stamp = rec.image_stamp(i)
        log = stamp + round(rec.image_record_lag_s * NS)
        rgb = raw_frame(i)
        if i in rec.blurred_frames:
            rgb = cv2.GaussianBlur(rgb, (0, 0), 1.6)
        if rec.image_kind == "raw":
            out.append((IMAGE_TOPIC, "sensor_msgs/msg/Image", log, m.image(stamp, "camera_optical_frame", rgb, "rgb8")))
        if rec.image_kind != "raw" or rec.jpeg_copy:
            ext, fmt = (".png", "bgr8; png compressed bgr8") if rec.image_kind == "png" else \
                (".jpg", "rgb8; jpeg compressed bgr8")
            ok, data = cv2.imencode(ext, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])
            assert ok
            out.append((IMAGE_TOPIC + "/compressed", "sensor_msgs/msg/CompressedImage", log,
                        m.compressed(stamp, "camera_optical_frame", data.tobytes(), fmt)))
        if rec.depth:
            depth_stamp = stamp + 3_000_000
            out.append((DEPTH_TOPIC, "sensor_msgs/msg/Image", log,
                        m.image(depth_stamp, "camera_optical_frame", raw_depth_mm(i), "16UC1")))
        if rec.unregistered_depth:
            out.append(("/camera/depth/image_raw", "sensor_msgs/msg/Image", log,
                        m.image(stamp, "camera_depth_optical_frame", raw_depth_mm(i)[:, :80], "16UC1")))
        if rec.camera_info and i % 5 == 0:
            out.append((INFO_TOPIC, "sensor_msgs/msg/CameraInfo", log, m.camera_info(stamp, CALIB)))
    return sorted(out, key=lambda x: x[2])


def write_bag(path: Path, rec: Recording, storage: str = "mcap") -> Path:
    """The round as a rosbag2 folder (``mcap`` or ``sqlite3``) or a ROS 1 ``.bag`` (``ros1``)."""
    if storage == "ros1":
        path = path.with_suffix(".bag")
        with Ros1Writer(path) as writer:
            conns: dict = {}
            for topic, msgtype, log, msg in messages(rec, Msgs(NOETIC, ros1=True)):
                if topic not in conns:
                    conns[topic] = writer.add_connection(topic, msgtype, typestore=NOETIC)
                writer.write(conns[topic], log, NOETIC.serialize_ros1(msg, msgtype))
        return path
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as writer:
        conns = {}
        for topic, msgtype, log, msg in messages(rec, Msgs(KILTED, ros1=False)):
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=KILTED)
            writer.write(conns[topic], log, KILTED.serialize_cdr(msg, msgtype))
    return path


ALL_FRAMES = ["--min-translation-m", "0", "--min-rotation-deg", "0"]


def run(capsys, bag: Path, out: Path, *args: str) -> tuple[int, str, str]:
    code = dataset_tool.main([str(bag), "--out", str(out), *args])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def read_csv(out: Path) -> list[dict[str, str]]:
    lines = (out / "frames.csv").read_text().splitlines()
    header = lines[0].split(",")
    return [dict(zip(header, line.split(","), strict=True)) for line in lines[1:]]


def tree_bytes(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


# ------------------------------------------------------------------------------------------------ the tests

@pytest.fixture(scope="module")
def mcap_round(tmp_path_factory) -> tuple[Path, Recording]:
    rec = Recording()
    return write_bag(tmp_path_factory.mktemp("bags") / "round", rec), rec


def test_mcap_round_poses_images_frames_csv_and_determinism(mcap_round, tmp_path, capsys):
    bag, rec = mcap_round
    code, out, err = run(capsys, bag, tmp_path / "a", *ALL_FRAMES)
    assert code == 0, err
    rows = read_csv(tmp_path / "a")
    assert list(rows[0]) == list(CSV_COLUMNS)
    status = {int(r["index"]): r["status"] for r in rows}
    stamps = {i: rec.image_stamp(i) for i in range(rec.n_frames)}
    in_gap = {i for i, s in stamps.items() if T0 + 1.0 * NS < s < T0 + 1.4 * NS}
    assert status[0] == "out_of_range"  # before the first TF sample
    assert {i for i, s in status.items() if s == "gap"} == in_gap and len(in_gap) == 4
    kept = sorted(i for i, s in status.items() if s == "kept")
    assert kept == sorted(set(range(1, rec.n_frames)) - in_gap)
    assert out.strip().splitlines()[-1].startswith(f"gsrmr-dataset: {rec.n_frames} frames read from {IMAGE_TOPIC}, "
                                                   f"{len(kept)} kept, {rec.n_frames - len(kept)} dropped "
                                                   "(out_of_range 1, gap 4)")
    by_index = {int(r["index"]): r for r in rows}
    assert by_index[3]["stamp_s"] == format_stamp(stamps[3]) and len(by_index[3]["stamp_s"].split(".")[1]) == 9
    assert float(by_index[3]["gap_s"]) == pytest.approx(0.02)
    before_m, after_m = true_camera(stamps[3] - 5_000_000)[:3, 3], true_camera(stamps[3] + 5_000_000)[:3, 3]
    assert float(by_index[3]["speed_mps"]) == pytest.approx(np.linalg.norm(after_m - before_m) / 0.01, rel=1e-3)
    assert float(by_index[3]["angular_speed_radps"]) == pytest.approx(YAW_RATE, rel=1e-3)
    assert float(by_index[3]["motion_bound_rad"]) == pytest.approx(YAW_RATE * 0.02, rel=1e-3)
    gap_row = by_index[min(in_gap)]
    assert float(gap_row["gap_s"]) == pytest.approx(0.4) and gap_row["file_path"] == ""

    frames = read_dataset(tmp_path / "a")
    assert len(frames) == len(kept)
    rect = Rectifier(CALIB)
    k = frames[0].camera.intrinsics
    assert k == rect.intrinsics and (k.width, k.height) == (W, H)
    worst_m = worst_deg = worst_pose = 0.0
    for frame, i in zip(frames, kept, strict=True):
        assert frame.file_path == by_index[i]["file_path"]
        pos_m, rot_deg = pose_errors(frame.camera.camera_to_world, true_camera(stamps[i]))
        worst_m, worst_deg = max(worst_m, pos_m), max(worst_deg, rot_deg)
        a, b, theta = frame.pose
        base = true_base(stamps[i])
        worst_pose = max(worst_pose, math.hypot(a - base[0, 3], b - base[1, 3]),
                         abs(theta - math.atan2(base[1, 0], base[0, 0])))
        # the rectified frame is the pattern as the pinhole camera sees it (8-bit; the border may interpolate)
        assert psnr(frame.image[3:-3, 3:-3], pinhole_view(i, rect)[3:-3, 3:-3].astype(np.float32)) > 35.0
    assert worst_m < 1e-3 and worst_deg < 0.05 and worst_pose < 1e-3, (worst_m, worst_deg, worst_pose)
    # the recorder's time is 40 ms late: a tool using it would be off by ≈ 12 mm
    late = pose_errors(frames[0].camera.camera_to_world, true_camera(stamps[kept[0]] + 40_000_000))[0]
    assert late > 0.01

    code, _out, _err = run(capsys, bag, tmp_path / "b", *ALL_FRAMES)  # another folder, and the same folder again
    assert code == 0 and tree_bytes(tmp_path / "a") == tree_bytes(tmp_path / "b")
    before = tree_bytes(tmp_path / "a")
    code, _out, _err = run(capsys, bag, tmp_path / "a", *ALL_FRAMES, "--max-frames", "5")
    assert code == 0 and len(read_dataset(tmp_path / "a", load_images=False)) == 5
    assert not (tmp_path / "a" / "images" / "frame_00005.png").exists()  # the earlier run's extra files are gone
    code, _out, _err = run(capsys, bag, tmp_path / "a", *ALL_FRAMES)
    assert code == 0 and tree_bytes(tmp_path / "a") == before


def test_sqlite3_and_ros1_bags_give_the_same_dataset(mcap_round, tmp_path, capsys):
    bag, rec = mcap_round
    assert run(capsys, bag, tmp_path / "mcap", *ALL_FRAMES)[0] == 0
    want = tree_bytes(tmp_path / "mcap")
    for storage in ("sqlite3", "ros1"):  # the ROS 1 bag names its frames with a leading '/'
        other = write_bag(tmp_path / f"round-{storage}", rec, storage)
        code, _out, err = run(capsys, other, tmp_path / storage, *ALL_FRAMES)
        assert code == 0, err
        assert tree_bytes(tmp_path / storage) == want, storage


def test_keyframe_rules_blur_spacing_and_thinning(tmp_path, capsys):
    rec = Recording(n_frames=20, tf_dropout_s=None, first_image_s=0.0, blurred_frames=(6,))
    bag = write_bag(tmp_path / "round", rec)
    code, _out, err = run(capsys, bag, tmp_path / "all", *ALL_FRAMES)
    assert code == 0, err
    rows = {int(r["index"]): r for r in read_csv(tmp_path / "all")}
    assert [i for i, r in rows.items() if r["status"] == "blur"] == [6]
    sharp = [float(r["sharpness"]) for i, r in rows.items() if i != 6]
    assert float(rows[6]["sharpness"]) < 0.5 * float(np.median(sharp))
    # spacing: the camera moves ≈ 3 cm and turns 2.9° per frame; 8 cm or 10° → every third frame
    code, _out, err = run(capsys, bag, tmp_path / "spaced", "--min-translation-m", "0.08", "--min-rotation-deg", "10")
    assert code == 0, err
    rows = {int(r["index"]): r for r in read_csv(tmp_path / "spaced")}
    kept = [i for i, r in rows.items() if r["status"] == "kept"]
    want, last = [0], true_camera(rec.image_stamp(0))
    for i in range(1, rec.n_frames):  # the rule, on the true cameras (6 is blurred: not a candidate)
        cam = true_camera(rec.image_stamp(i))
        moved_m, turned_deg = pose_errors(cam, last)
        if i != 6 and (moved_m >= 0.08 or turned_deg >= 10.0):
            want.append(i)
            last = cam
    assert kept == want and len(want) < rec.n_frames // 2 and rows[1]["status"] == "keyframe_skip"
    frames = read_dataset(tmp_path / "spaced", load_images=False)
    steps = [np.linalg.norm(b.camera.center_world - a.camera.center_world) for a, b in itertools.pairwise(frames)]
    assert min(steps) >= 0.08
    # thinning: 7 of the 19 sharp frames, evenly spread
    code, _out, err = run(capsys, bag, tmp_path / "thin", *ALL_FRAMES, "--max-frames", "7")
    assert code == 0, err
    rows = read_csv(tmp_path / "thin")
    sharp_idx = [int(r["index"]) for r in rows if r["status"] in ("kept", "max_frames")]
    kept = [int(r["index"]) for r in rows if r["status"] == "kept"]
    assert kept == [sharp_idx[j] for j in thin_evenly(len(sharp_idx), 7)] and kept[0] == 0 and kept[-1] == 19


def test_keyframe_functions():
    assert thin_evenly(10, 4) == [0, 3, 6, 9] and thin_evenly(5, None) == [0, 1, 2, 3, 4] and thin_evenly(9, 1) == [0]
    assert thin_evenly(11, 3) == [0, 5, 10] and thin_evenly(4, 3) == [0, 2, 3]  # 1.5 rounds half up
    assert blurred([10, 10, 2, 10, 10], 2, 0.5) == [False, False, True, False, False]
    assert blurred([10, 10, 2, 10, 10], 2, 0.0) == [False] * 5 and blurred([1.0, 9.0], 2, 0.5) == [False, False]
    poses = [np.eye(4) for _ in range(4)]
    for i, p in enumerate(poses):
        p[0, 3] = 0.04 * i
    assert spaced(poses, 0.07, 0.0) == [True, False, True, False]
    assert spaced(poses, 0.0, 0.0) == [True] * 4


def test_pose_topic_with_the_mount_from_static_tf_and_from_a_yaml(tmp_path, capsys):
    # Odometry of odom → base_link, no /tf at all; the mount from /tf_static
    rec = Recording(n_frames=10, dynamic_tf=False, odometry_topic="/odom", tf_dropout_s=None, first_image_s=0.0)
    bag = write_bag(tmp_path / "odom", rec)
    code, out, err = run(capsys, bag, tmp_path / "odom-out", *ALL_FRAMES, "--pose-topic", "/odom")
    assert code == 0, err
    assert "poses from /odom (base_link in its frame) ∘ camera mount (mount base_link → camera_optical_frame from " \
           "the bag's TF)" in out
    frames = read_dataset(tmp_path / "odom-out", load_images=False)
    assert len(frames) == 10
    for i, frame in enumerate(frames):
        pos_m, rot_deg = pose_errors(frame.camera.camera_to_world, true_camera(rec.image_stamp(i)))
        assert pos_m < 1e-3 and rot_deg < 0.05

    # PoseStamped of base_link in map, no camera TF: the mount from a parameter file
    rec = Recording(n_frames=6, dynamic_tf=False, pose_stamped_topic="/robot_pose", camera_static_tf=False,
                    tf_dropout_s=None, first_image_s=0.0)
    bag = write_bag(tmp_path / "pose", rec)
    mount_file = tmp_path / "mount.yaml"
    mount_file.write_text(yaml.safe_dump({"/**": {"ros__parameters": MOUNT.as_parameters()}}))
    code, out, err = run(capsys, bag, tmp_path / "pose-out", *ALL_FRAMES, "--pose-topic", "/robot_pose",
                         "--camera-mount", str(mount_file))
    assert code == 0, err
    assert "from mount.yaml" in out
    for i, frame in enumerate(read_dataset(tmp_path / "pose-out", load_images=False)):
        pos_m, rot_deg = pose_errors(frame.camera.camera_to_world, true_camera(rec.image_stamp(i)))
        assert pos_m < 1e-3 and rot_deg < 0.05
        assert frame.pose is not None
    # without --camera-mount: the package's config/camera_mount.yaml (another mount: other camera poses)
    code, out, err = run(capsys, bag, tmp_path / "default-out", *ALL_FRAMES, "--pose-topic", "/robot_pose")
    assert code == 0, err
    assert "from camera_mount.yaml" in out
    config = yaml.safe_load((Path(__file__).parents[2] / "config" / "camera_mount.yaml").read_text())
    params = {k.split(".", 1)[1]: v for k, v in config["/**"]["ros__parameters"].items()}
    for i, frame in enumerate(read_dataset(tmp_path / "default-out", load_images=False)):
        pos_m, rot_deg = pose_errors(frame.camera.camera_to_world, true_camera(rec.image_stamp(i),
                                                                               CameraMount(**params)))
        assert pos_m < 1e-3 and rot_deg < 0.05


def test_handheld_rig_six_dof_without_base_link(tmp_path, capsys):
    """A camera carried by hand: map → camera_link moving in 6-DoF at 50 Hz; no base_link, so no gsrmr_pose."""
    def rig(t: float) -> np.ndarray:
        out = np.eye(4)
        out[:3, :3] = rpy_matrix(0.3 * math.sin(1.1 * t), 0.2 * math.sin(0.7 * t + 0.4), 0.6 * t)
        out[:3, 3] = (0.4 * t, 0.2 * math.sin(t), 1.2 + 0.1 * math.cos(1.3 * t))
        return out

    optical = transform_matrix(type(base_from_camera_link_transform(MOUNT))((0.0, 0.0, 0.0), OPTICAL_IN_LINK))
    m = Msgs(KILTED, ros1=False)
    items = [("/tf_static", "tf2_msgs/msg/TFMessage", T0, m.tf(T0, [("camera_link", "camera_optical_frame", optical)]))]
    items += [("/tf", "tf2_msgs/msg/TFMessage", T0 + k * 20_000_000,
               m.tf(T0 + k * 20_000_000, [("map", "camera_link", rig(k * 0.02))])) for k in range(60)]
    stamps = [T0 + 31_000_000 + i * 100_000_000 for i in range(10)]
    items += [(IMAGE_TOPIC, "sensor_msgs/msg/Image", s, m.image(s, "camera_optical_frame", raw_frame(i), "rgb8"))
              for i, s in enumerate(stamps)]
    items += [(INFO_TOPIC, "sensor_msgs/msg/CameraInfo", stamps[0], m.camera_info(stamps[0], CALIB))]
    bag = tmp_path / "rig"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns: dict = {}
        for topic, msgtype, log, msg in sorted(items, key=lambda x: x[2]):
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=KILTED)
            writer.write(conns[topic], log, KILTED.serialize_cdr(msg, msgtype))
    code, _out, err = run(capsys, bag, tmp_path / "out", *ALL_FRAMES)
    assert code == 0, err
    frames = read_dataset(tmp_path / "out", load_images=False)
    assert len(frames) == 10 and all(f.pose is None for f in frames)
    for frame, s in zip(frames, stamps, strict=True):
        pos_m, rot_deg = pose_errors(frame.camera.camera_to_world, rig((s - T0) / NS) @ optical)
        assert pos_m < 1e-3 and rot_deg < 0.05, (pos_m, rot_deg)


@pytest.mark.parametrize("kind", ["jpeg", "png"])
def test_compressed_images(kind, tmp_path, capsys):
    rec = Recording(n_frames=5, image_kind=kind, tf_dropout_s=None, first_image_s=0.0)
    bag = write_bag(tmp_path / "round", rec)
    code, out, err = run(capsys, bag, tmp_path / "out", *ALL_FRAMES)  # the sibling of …/image_raw/compressed
    assert code == 0, err
    assert f"read from {IMAGE_TOPIC}/compressed" in out
    rect = Rectifier(CALIB)
    for i, frame in enumerate(read_dataset(tmp_path / "out")):
        want = rect(raw_frame(i))
        got = np.round(frame.image * 255.0).astype(np.uint8)
        if kind == "png":
            assert np.array_equal(got, want)  # lossless, and the channel order right
        else:  # what the JPEG holds, rectified; and nearer the true colours than to their swap
            bgr = cv2.cvtColor(raw_frame(i), cv2.COLOR_RGB2BGR)
            data = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 95])[1]
            assert np.array_equal(got, rect(cv2.cvtColor(cv2.imdecode(data, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)))
            right = psnr(frame.image, want.astype(np.float32) / 255.0)
            swapped = psnr(frame.image, want[:, :, ::-1].astype(np.float32) / 255.0)
            assert right > 20.0 and right > swapped + 5.0, (right, swapped)


def test_aligned_depth_is_detected_rectified_and_written(tmp_path, capsys):
    rec = Recording(n_frames=4, depth=True, unregistered_depth=True, tf_dropout_s=None, first_image_s=0.0,
                    jpeg_copy=True)
    bag = write_bag(tmp_path / "round", rec)
    code, out, err = run(capsys, bag, tmp_path / "out", *ALL_FRAMES)
    assert code == 0, err
    assert "4 with depth" in out and f"read from {IMAGE_TOPIC}, " in out  # the raw topic, not its JPEG copy
    assert "depth topic /camera/depth/image_raw not used: it is in frame camera_depth_optical_frame" in err
    rect = Rectifier(CALIB)
    meta = json.loads((tmp_path / "out" / "transforms.json").read_text())
    assert meta["depth_unit_scale_factor"] == 0.001
    for i, entry in enumerate(meta["frames"]):
        mm = cv2.imread(str(tmp_path / "out" / entry["depth_file_path"]), cv2.IMREAD_UNCHANGED)
        assert mm.dtype == np.uint16 and np.array_equal(mm, rect.rectify_depth(raw_depth_mm(i)))
    rows = read_csv(tmp_path / "out")
    assert all(float(r["depth_offset_s"]) == pytest.approx(0.003) for r in rows)
    code, out, err = run(capsys, bag, tmp_path / "none", *ALL_FRAMES, "--no-depth")
    assert code == 0 and not (tmp_path / "none" / "depths").exists()


def test_image_decoding_of_the_encodings_drivers_send():
    m = Msgs(KILTED, ros1=False)
    rgb = raw_frame(0)
    for encoding, pixels in (("rgb8", rgb), ("bgr8", rgb[:, :, ::-1].copy()),
                             ("rgba8", np.dstack([rgb, np.full((H, W), 7, np.uint8)]))):
        assert np.array_equal(decode_colour(m.image(0, "c", pixels, encoding), "sensor_msgs/msg/Image"), rgb)
    grey = rgb[:, :, 1].copy()
    assert np.array_equal(decode_colour(m.image(0, "c", grey, "mono8"), "sensor_msgs/msg/Image"),
                          np.dstack([grey] * 3))
    # YUV 4:2:2 (UYVY as `yuv422`/`uyvy`, YUYV as `yuv422_yuy2`/`yuyv`; BT.601 video range as cameras send it) of
    # colour blocks 8 px wide: the shared chroma of a pixel pair is exact, only the 8-bit YUV rounding remains
    blocks = np.repeat(np.repeat(np.array([[[200, 30, 60], [20, 180, 90], [40, 60, 220], [128, 128, 128]]] * 3,
                                          np.uint8), 8, axis=0), 24, axis=1)
    r, g, b = (blocks[:, :, c].astype(np.float64) for c in range(3))
    y = np.round(16 + 0.257 * r + 0.504 * g + 0.098 * b).astype(np.uint8)
    u = np.round(128 - 0.148 * r - 0.291 * g + 0.439 * b).astype(np.uint8)[:, 0::2]
    v = np.round(128 + 0.439 * r - 0.368 * g - 0.071 * b).astype(np.uint8)[:, 0::2]
    uyvy = np.empty((*blocks.shape[:2], 2), np.uint8)
    uyvy[:, :, 1], uyvy[:, 0::2, 0], uyvy[:, 1::2, 0] = y, u, v
    yuyv = uyvy[:, :, ::-1].copy()
    for encoding, packed in (("yuv422", uyvy), ("uyvy", uyvy), ("yuv422_yuy2", yuyv), ("yuyv", yuyv)):
        got = decode_colour(m.image(0, "c", packed, encoding), "sensor_msgs/msg/Image")
        assert got.shape == blocks.shape and np.abs(got.astype(int) - blocks).max() <= 3, encoding
    depth_mm = raw_depth_mm(1)
    as_16 = m.image(0, "c", depth_mm, "16UC1")
    assert is_depth_message(as_16, "sensor_msgs/msg/Image")
    np.testing.assert_allclose(decode_depth_m(as_16, "sensor_msgs/msg/Image"), depth_mm / 1000.0, rtol=1e-6)
    metres = (depth_mm / 1000.0).astype(np.float32)
    metres[0, :5] = (np.nan, np.inf, -1.0, 0.0, 2.5)
    got = decode_depth_m(m.image(0, "c", metres, "32FC1"), "sensor_msgs/msg/Image")
    assert list(got[0, :5]) == [0.0, 0.0, 0.0, 0.0, 2.5] and np.array_equal(got[1:], metres[1:])
    # compressedDepth (compressed_depth_image_transport): a 12-byte header, then a 16-bit PNG of millimetres
    png = cv2.imencode(".png", depth_mm)[1].tobytes()
    msg = m.compressed(0, "c", struct.pack("<iff", 0, 0.0, 0.0) + png, "16UC1; compressedDepth png")
    assert is_depth_message(msg, "sensor_msgs/msg/CompressedImage")
    np.testing.assert_allclose(decode_depth_m(msg, "sensor_msgs/msg/CompressedImage"), depth_mm / 1000.0, rtol=1e-6)
    # … and of 32FC1: inverse depth quantised, v = A / d + B, d = A / (v − B); the codec's defaults (quantisation
    # 100, 10 m) give A = 100·101, B = 1 − A / 10
    quant_a = 100.0 * 101.0
    quant_b = 1.0 - quant_a / 10.0
    inv = np.round(quant_a / (depth_mm / 1000.0) + quant_b).astype(np.uint16)
    msg = m.compressed(0, "c", struct.pack("<iff", 0, quant_a, quant_b) + cv2.imencode(".png", inv)[1].tobytes(),
                       "32FC1; compressedDepth png")
    np.testing.assert_allclose(decode_depth_m(msg, "sensor_msgs/msg/CompressedImage"), depth_mm / 1000.0, rtol=1e-3)


# ------------------------------------------------------------------------------------------------ bad input

def one_line_error(code: int, err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1 and lines[0].startswith("gsrmr-dataset: "), (code, err)
    return lines[0]


def test_missing_image_topic_lists_the_image_topics(mcap_round, tmp_path, capsys):
    bag, _rec = mcap_round
    line = one_line_error(*run(capsys, bag, tmp_path / "o", "--image-topic", "/camera/rgb")[::2])
    assert "no topic /camera/rgb" in line and f"{IMAGE_TOPIC} (sensor_msgs/msg/Image, 24 msgs)" in line
    assert "--image-topic TOPIC" in line


def test_no_camera_info_then_a_calibration_file(tmp_path, capsys):
    rec = Recording(n_frames=3, camera_info=False, tf_dropout_s=None, first_image_s=0.0)
    bag = write_bag(tmp_path / "round", rec)
    line = one_line_error(*run(capsys, bag, tmp_path / "o", *ALL_FRAMES)[::2])
    assert f"no CameraInfo on {INFO_TOPIC} (the sibling of {IMAGE_TOPIC})" in line
    assert "--camera-info FILE" in line and "CameraInfo topics: none" in line
    calib_file = tmp_path / "ost.yaml"
    calib_file.write_text(yaml.safe_dump(CALIB.to_yaml_dict()))
    code, _out, err = run(capsys, bag, tmp_path / "o", *ALL_FRAMES, "--camera-info", str(calib_file))
    assert code == 0, err
    frames = read_dataset(tmp_path / "o", load_images=False)
    assert frames[0].camera.intrinsics == Rectifier(CALIB).intrinsics and len(frames) == 3


def test_no_tf_path_lists_the_frames_and_their_parents(tmp_path, capsys):
    rec = Recording(n_frames=3, tf_static=False, tf_dropout_s=None, first_image_s=0.0)
    bag = write_bag(tmp_path / "round", rec)
    line = one_line_error(*run(capsys, bag, tmp_path / "o", *ALL_FRAMES)[::2])
    assert "no TF path from map to camera_optical_frame" in line and "base_link (parent odom, moving)" in line
    assert "(the bag has no /tf_static)" in line and "transient_local" in line


def test_every_frame_outside_the_pose_range(tmp_path, capsys):
    rec = Recording(n_frames=4, tf_dropout_s=None, first_image_s=0.0, image_stamp_shift_s=100.0)
    bag = write_bag(tmp_path / "round", rec)
    line = one_line_error(*run(capsys, bag, tmp_path / "o", *ALL_FRAMES)[::2])
    assert "all 4 frames of /camera/color/image_raw are outside the pose range" in line
    assert "image stamps 1700000100.007–1700000100.307 s" in line
    assert "TF map → camera_optical_frame 1700000000.000–1700000002.600 s" in line


def test_truncated_mcap_uses_what_is_readable(tmp_path, capsys):
    """A recording killed mid-write: no metadata.yaml, the MCAP cut in its second chunk (rosbags writes 1 MiB
    chunks; 60 frames of 96×72 rgb8 plus 50 Hz TF fill about 1.3 MB)."""
    rec = Recording(n_frames=60, tf_dropout_s=None, first_image_s=0.0, tf_until_s=6.2)
    bag = write_bag(tmp_path / "round", rec)
    code, _out, err = run(capsys, bag, tmp_path / "whole", *ALL_FRAMES)
    assert code == 0, err
    (bag / "metadata.yaml").unlink()
    mcap_file = next(bag.glob("*.mcap"))
    data = mcap_file.read_bytes()
    mcap_file.write_bytes(data[: int(len(data) * 0.9)])
    code, out, err = run(capsys, bag, tmp_path / "cut", *ALL_FRAMES)
    assert code == 0, err
    warnings = [line for line in err.splitlines() if "warning" in line]
    pattern_text = (r"is damaged \(the file ends in the middle of a record\): read ([0-9.]+) MB of ([0-9.]+) MB "
                    r"\(\d+ %\), (\d+) messages up to log time [0-9.]+ s; the rest is lost")
    damaged = [re.search(pattern_text, w) for w in warnings]
    found = [d for d in damaged if d]
    assert len(found) == 1, err
    readable_mb, total_mb = float(found[0].group(1)), float(found[0].group(2))
    assert total_mb == pytest.approx(mcap_file.stat().st_size / 1e6, abs=0.006)
    assert 0.7 * total_mb < readable_mb < total_mb  # the first 1 MiB chunk, not the cut one
    assert any("no metadata.yaml" in w for w in warnings), err
    read = len(read_csv(tmp_path / "cut"))
    assert 30 <= read < 60 and f"{read} frames read" in out
    whole = {r["index"]: r["file_path"] for r in read_csv(tmp_path / "whole")}
    cut = read_dataset(tmp_path / "cut", load_images=False)
    assert len(cut) >= 30 and cut[0].file_path == whole["0"]


def test_options_are_checked(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        dataset_tool.main([str(tmp_path), "--out", str(tmp_path / "o"), "--max-gap-s", "0"])
    assert exc.value.code == 2 and "--max-gap-s: expected a finite number > 0.0" in capsys.readouterr().err
    line = one_line_error(*run(capsys, tmp_path / "nothing", tmp_path / "o")[::2])
    assert "does not exist" in line


@pytest.mark.parametrize("wobble_m", [0.0, 0.0004])
def test_a_constant_map_to_odom_on_tf_moves_nothing(tmp_path, capsys, wobble_m):
    """map → odom sent on /tf at 1 Hz, half a period off the images (a localizer, a ROS 1 static_transform_publisher):
    its samples agree (within the tolerance: a 0.4 mm wobble too), so it moves nothing between them, and the bag keeps
    the frames, at the poses, it keeps with the edge on /tf_static."""
    assert run(capsys, write_bag(tmp_path / "static", Recording()), tmp_path / "a", *ALL_FRAMES)[0] == 0
    dynamic = write_bag(tmp_path / "dynamic", Recording(map_from_odom_hz=1.0, map_from_odom_wobble_m=wobble_m))
    code, _out, err = run(capsys, dynamic, tmp_path / "b", *ALL_FRAMES)
    assert code == 0, err
    a, b = read_csv(tmp_path / "a"), read_csv(tmp_path / "b")
    assert [r["status"] for r in a] == [r["status"] for r in b] and sum(r["status"] == "kept" for r in b) >= 15
    frames_a = json.loads((tmp_path / "a" / "transforms.json").read_text())["frames"]
    frames_b = json.loads((tmp_path / "b" / "transforms.json").read_text())["frames"]
    assert len(frames_a) == len(frames_b)
    for fa, fb in zip(frames_a, frames_b, strict=True):
        np.testing.assert_allclose(fb["transform_matrix"], fa["transform_matrix"], atol=1e-3)


def test_a_moving_edge_sampled_slowly_is_still_a_gap(tmp_path, capsys):
    """The same 1 Hz edge moving 5 cm a second (a localizer correcting): its brackets are 1 s, wider than
    --max-gap-s, and no frame has poses to keep."""
    bag = write_bag(tmp_path / "moving", Recording(map_from_odom_hz=1.0, map_from_odom_drift_mps=0.05))
    code, _out, err = run(capsys, bag, tmp_path / "c", *ALL_FRAMES)
    assert code != 0 and "max-gap-s" in err and "map → odom" not in err.split("—")[-1], err
