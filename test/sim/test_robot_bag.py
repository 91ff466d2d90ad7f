"""A bag of the simulated world recorded as a LIMO records one (:mod:`gsrmr_sim.robot_bag`), read back with ``rosbags``.

One tiny bag (128×96, 12 images, in the route's first corner) is written once: its topics, types, counts and timing;
the TF chain at each image stamp, interpolated between the two odometry samples around it, is the true camera pose;
the frames carry the calibration's distortion (rectified they match a pinhole render at P, raw they do not); the
blurred frames are blurred. The distorted camera's maps are checked against an analytic pattern, the odometry's drift
without rendering, and a second tiny bag (sqlite3, raw images, drift) for its options and determinism.
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from gsrmr_common import tf_tree
from gsrmr_common.calibration import CameraCalibration, Rectifier
from gsrmr_common.camera import Intrinsics, camera_from_pose
from gsrmr_common.metrics import psnr as psnr_db
from gsrmr_common.pose2d import Pose2D
from gsrmr_sim import robot_bag as rb
from gsrmr_sim.world.points import make_world
from gsrmr_sim.world.recorder import with_resolution
from gsrmr_sim.world.scene import load_scene

# 5.5 s into the route: the robot turns into the first corner while the 12 images are taken
RECIPE = rb.RobotBagRecipe(frames=12, width_px=128, height_px=96, drive_start_s=5.5, blurred_frames=2, seed=3)
TF_STEP_NS = 20_000_000


def read_bag(path: Path) -> tuple[dict[str, list[tuple[int, str, Any]]], str]:
    """Every message by topic: (log time ns, type, message); and the storage the metadata names."""
    out: dict[str, list[tuple[int, str, Any]]] = {}
    with AnyReader([path]) as reader:
        for conn, log_ns, raw in reader.messages():
            out.setdefault(conn.topic, []).append((log_ns, conn.msgtype, reader.deserialize(raw, conn.msgtype)))
    storage = next(line.split(":")[1].strip() for line in (path / "metadata.yaml").read_text().splitlines()
                   if "storage_identifier" in line)
    return out, storage


def stamp_ns(msg: Any) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def matrix(t: Any) -> np.ndarray:
    """4×4 of a geometry_msgs/Transform (child → parent)."""
    q, v = t.rotation, t.translation
    return tf_tree.transform_matrix(tf_tree.Transform((v.x, v.y, v.z), (q.x, q.y, q.z, q.w)))


def planar(t: Any) -> tuple[float, float, float]:
    q = t.rotation
    return t.translation.x, t.translation.y, 2.0 * math.atan2(q.z, q.w)


def tf_chain_at(messages: dict[str, list[tuple[int, str, Any]]], at_ns: int) -> np.ndarray:
    """map → camera_color_optical_frame at ``at_ns``: /tf_static with odom → base_link interpolated linearly (x, y,
    yaw) between the two /tf samples around ``at_ns``."""
    static = {(t.header.frame_id, t.child_frame_id): matrix(t.transform)
              for _, _, m in messages[rb.TF_STATIC_TOPIC] for t in m.transforms}
    samples = sorted((stamp_ns(t), planar(t.transform)) for _, _, m in messages[rb.TF_TOPIC] for t in m.transforms
                     if (t.header.frame_id, t.child_frame_id) == ("odom", "base_link"))
    (t0, p0), (t1, p1) = next((a, b) for a, b in itertools.pairwise(samples) if a[0] <= at_ns <= b[0])
    w = (at_ns - t0) / (t1 - t0)
    yaw = p0[2] + w * math.remainder(p1[2] - p0[2], math.tau)
    odom_base = tf_tree.transform_matrix(tf_tree.odom_from_base_transform(p0[0] + w * (p1[0] - p0[0]),
                                                                           p0[1] + w * (p1[1] - p0[1]), yaw))
    return (static[("map", "odom")] @ odom_base @ static[("base_link", "camera_link")]
            @ static[("camera_link", "camera_color_optical_frame")])


def pose_error(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(translation error m, rotation error rad) between two 4×4 poses."""
    cos = (np.trace(a[:3, :3].T @ b[:3, :3]) - 1.0) / 2.0
    return float(np.linalg.norm(a[:3, 3] - b[:3, 3])), float(math.acos(min(1.0, max(-1.0, cos))))


def decode(msgtype: str, msg: Any) -> np.ndarray:
    """H×W×3 uint8 RGB of a CompressedImage (JPEG) or an rgb8 Image."""
    if msgtype == "sensor_msgs/msg/CompressedImage":
        return cv2.imdecode(np.asarray(msg.data, np.uint8), cv2.IMREAD_COLOR)[:, :, ::-1]
    return np.asarray(msg.data, np.uint8).reshape(msg.height, msg.width, 3)


@pytest.fixture(scope="module")
def bag(tmp_path_factory) -> rb.RobotBag:
    return rb.write_robot_bag(tmp_path_factory.mktemp("robot_bag"), RECIPE)


@pytest.fixture(scope="module")
def messages(bag) -> dict[str, list[tuple[int, str, Any]]]:
    return read_bag(bag.bag_path)[0]


def test_topics_types_counts_and_timing(bag, messages):
    n_tf = (bag.tf_last_stamp_ns - bag.tf_first_stamp_ns) // TF_STEP_NS + 1
    assert {topic: (len(msgs), msgs[0][1]) for topic, msgs in messages.items()} == {
        "/camera/color/image_raw/compressed": (12, "sensor_msgs/msg/CompressedImage"),
        "/camera/color/camera_info": (12, "sensor_msgs/msg/CameraInfo"),
        "/tf": (n_tf, "tf2_msgs/msg/TFMessage"), "/odom": (n_tf, "nav_msgs/msg/Odometry"),
        "/tf_static": (1, "tf2_msgs/msg/TFMessage")}
    assert read_bag(bag.bag_path)[1] == "mcap"
    # /tf_static: the chain with the driver's optical frame name
    assert [(t.header.frame_id, t.child_frame_id) for t in messages["/tf_static"][0][2].transforms] == [
        ("map", "odom"), ("base_link", "camera_link"), ("camera_link", "camera_color_optical_frame")]
    # /tf and /odom: odom → base_link at 50 Hz, the same poses
    tf_stamps = [stamp_ns(m.transforms[0]) for _, _, m in messages["/tf"]]
    assert np.all(np.diff(tf_stamps) == TF_STEP_NS) and tf_stamps[0] == bag.tf_first_stamp_ns
    for (_, _, tf), (_, _, odom) in zip(messages["/tf"], messages["/odom"], strict=True):
        t = tf.transforms[0]
        assert (odom.header.frame_id, odom.child_frame_id) == ("odom", "base_link") == (t.header.frame_id,
                                                                                          t.child_frame_id)
        assert stamp_ns(odom) == stamp_ns(t) and odom.pose.pose.position.x == t.transform.translation.x
    # images: JPEG as image_transport writes it, 10 Hz, off the TF grid, recorded 12–20 ms after their stamp
    images = messages["/camera/color/image_raw/compressed"]
    stamps = [stamp_ns(m) for _, _, m in images]
    assert all(m.format == "rgb8; jpeg compressed bgr8" and m.header.frame_id == "camera_color_optical_frame"
               for _, _, m in images)
    assert np.all(np.abs(np.diff(stamps) - 100_000_000) <= 6_000_000)
    assert all(4_000_000 <= (s - bag.tf_first_stamp_ns) % TF_STEP_NS <= 10_000_000 for s in stamps)
    assert all(12_000_000 <= log - stamp_ns(m) <= 20_000_000 for log, _, m in images)
    assert [stamp_ns(m) for _, _, m in messages["/camera/color/camera_info"]] == stamps
    # two images before the first odometry sample, two after the last one; truth says so
    inside = [bag.tf_first_stamp_ns <= s <= bag.tf_last_stamp_ns for s in stamps]
    assert inside == [False] * 2 + [True] * 8 + [False] * 2 == [f.in_pose_range for f in bag.frames]
    assert [f.stamp_ns for f in bag.frames] == stamps
    back = rb.load_truth(bag.truth_path.parent)  # truth.json holds what write_robot_bag returned
    assert (back.recipe, back.rectified, back.drift, back.map_from_odom) == (bag.recipe, bag.rectified, None,
                                                                             bag.map_from_odom)
    assert back.calibration.d == bag.calibration.d and np.array_equal(back.calibration.p, bag.calibration.p)
    assert all((a.stamp_ns, a.log_time_ns, a.pose, a.blurred, a.in_pose_range)
               == (b.stamp_ns, b.log_time_ns, b.pose, b.blurred, b.in_pose_range)
               and np.array_equal(a.map_from_optical, b.map_from_optical) for a, b in zip(back.frames, bag.frames,
                                                                                        strict=True))


def test_camera_info_is_the_distorted_camera_with_its_alpha0_projection(bag, messages):
    info = messages["/camera/color/camera_info"][0][2]
    calib = CameraCalibration.from_camera_info(info)
    k = with_resolution(load_scene("sandbox"), 128, 96).camera.intrinsics
    assert (info.width, info.height, info.distortion_model) == (128, 96, "plumb_bob")
    assert calib.d == rb.DEFAULT_DISTORTION and calib.frame_id == "camera_color_optical_frame"
    assert np.allclose(calib.k, k.ros_k())
    # P as camera_calibration writes it: OpenCV's alpha-0 optimal new camera matrix
    alpha0, _ = cv2.getOptimalNewCameraMatrix(calib.k, calib.distortion_array(), (128, 96), 0.0, (128, 96))
    assert np.allclose(np.asarray(info.p).reshape(3, 4), np.hstack([alpha0, np.zeros((3, 1))]))
    assert Rectifier(calib).intrinsics == bag.rectified


def test_tf_chain_at_each_image_stamp_is_the_true_camera_pose(bag, messages):
    errors, nearest_errors = [], []
    tf_stamps = [stamp_ns(m.transforms[0]) for _, _, m in messages["/tf"]]
    for frame in (f for f in bag.frames if f.in_pose_range):
        errors.append(pose_error(tf_chain_at(messages, frame.stamp_ns), frame.map_from_optical))
        nearest = min(tf_stamps, key=lambda s, at=frame.stamp_ns: abs(s - at))
        nearest_errors.append(pose_error(tf_chain_at(messages, nearest), frame.map_from_optical)[0])
    worst_m, worst_rad = max(e[0] for e in errors), max(e[1] for e in errors)
    assert worst_m < 1e-3 and worst_rad < 1e-3, (worst_m, worst_rad)  # measured: 8 µm, 7e-6 rad (turning at 0.5 rad/s)
    assert min(nearest_errors) > 1e-3, nearest_errors  # stamps between samples: nearest 1.4–2.6 mm off
    # and the truth is the camera of the true planar pose
    f = bag.frames[6]
    assert np.allclose(np.linalg.inv(camera_from_pose(*f.pose, bag.mount, bag.rectified).world_to_camera),
                       f.map_from_optical)


def test_the_frames_carry_the_calibrations_distortion(bag, messages):
    calib = CameraCalibration.from_camera_info(messages["/camera/color/camera_info"][0][2])
    rectify = Rectifier(calib)
    world = make_world(with_resolution(load_scene("sandbox"), 128, 96), 1)
    gains = []
    for frame, (_, msgtype, msg) in zip(bag.frames, messages["/camera/color/image_raw/compressed"], strict=True):
        if frame.blurred:
            continue
        raw = decode(msgtype, msg).astype(np.float32) / 255.0
        pinhole, _ = world.render(camera_from_pose(*frame.pose, bag.mount, rectify.intrinsics))
        rectified_db = psnr_db(rectify(raw)[2:-2, 2:-2], pinhole[2:-2, 2:-2])
        raw_db = psnr_db(raw[2:-2, 2:-2], pinhole[2:-2, 2:-2])
        assert rectified_db > 33.0, (frame.index, rectified_db)  # measured 36.3–37.9 dB
        gains.append(rectified_db - raw_db)
    assert min(gains) > 2.5, gains  # measured 3.1–4.2 dB (raw 33.0–34.1 dB)


def test_distorted_camera_samples_each_raw_pixel_at_its_ray():
    """An analytic pattern rendered by the pinhole camera, distorted, then rectified: the pattern as the rectified
    camera sees it (and, raw, as each raw pixel centre's ray sees it) — the half-pixel conventions line up."""
    def pattern(x_n: np.ndarray, y_n: np.ndarray) -> np.ndarray:
        a = 0.5 + 0.45 * np.sin(23.0 * x_n) * np.cos(19.0 * y_n)
        return np.stack([a, 0.5 + 0.45 * np.cos(17.0 * x_n + 9.0 * y_n), 0.5 * a], axis=-1).astype(np.float32)

    def view(k: Intrinsics) -> np.ndarray:
        x_n = (np.arange(k.width) + 0.5 - k.cx) / k.fx
        return pattern(*np.meshgrid(x_n, (np.arange(k.height) + 0.5 - k.cy) / k.fy))

    cam = rb.DistortedCamera(Intrinsics.from_fov(320, 240, math.radians(70.0)), rb.DEFAULT_DISTORTION)
    render = cam.render_intrinsics
    assert render.width > 320 and render.height > 240  # barrel: the raw corners see past the pinhole's
    raw = cam.distort(view(render))
    rect = Rectifier(cam.calibration)
    quality = psnr_db(rect(raw)[3:-3, 3:-3], view(rect.intrinsics)[3:-3, 3:-3])
    assert quality > 55.0, quality  # measured 65 dB
    # a half-pixel slip of the render camera (either convention applied twice) is far worse: measured 37 dB
    shifted = Intrinsics(render.fx, render.fy, render.cx + 0.5, render.cy + 0.5, render.width, render.height)
    slipped = rect(cam.distort(view(shifted)))
    assert psnr_db(slipped[3:-3, 3:-3], view(rect.intrinsics)[3:-3, 3:-3]) < quality - 20


def test_blurred_frames_are_less_sharp_than_their_neighbours(bag, messages):
    images = messages["/camera/color/image_raw/compressed"]

    def sharpness(i: int) -> float:
        gray = cv2.cvtColor(decode(images[i][1], images[i][2]), cv2.COLOR_RGB2GRAY)
        return float(cv2.Laplacian(gray, cv2.CV_64F).var())

    blurred = [f.index for f in bag.frames if f.blurred]
    assert len(blurred) == 2 and all(bag.frames[i].in_pose_range and bag.frames[i].blur_length_px in rb.BLUR_LENGTHS_PX
                                     for i in blurred)
    for i in blurred:
        # a blur along one direction keeps the edges along it: measured 0.13 and 0.45 of the less sharp neighbour
        assert sharpness(i) < 0.6 * min(sharpness(i - 1), sharpness(i + 1)), i


def test_odometry_drift_grows_with_distance_and_is_zero_without():
    trajectory = rb.TrueTrajectory(load_scene("sandbox").route, 12_000_000_000)
    map_poses = [trajectory.pose_at(t) for t in range(0, 12_000_000_001, TF_STEP_NS)]
    origin = map_poses[0]
    exact = rb.odometry_poses(map_poses, None)
    assert max(math.dist(Pose2D.of(origin).compose(o)[:2], p[:2]) for o, p in zip(exact, map_poses, strict=True)) < 1e-9
    drift = rb.OdometryDrift(yaw_rad_per_m=0.03, scale_error=0.02)
    drifted = rb.odometry_poses(map_poses, drift)
    travelled_m = np.cumsum([0.0] + [math.dist(a[:2], b[:2]) for a, b in itertools.pairwise(map_poses)])
    position_error_m = [math.dist(Pose2D.of(origin).compose(o)[:2], p[:2]) for o, p in zip(drifted, map_poses,
                                                                                           strict=True)]
    yaw_error_rad = [math.remainder(Pose2D.of(origin).compose(o)[2] - p[2], math.tau)
                     for o, p in zip(drifted, map_poses, strict=True)]
    assert yaw_error_rad[-1] == pytest.approx(0.03 * travelled_m[-1], rel=1e-3)  # 3.6 m: 0.108 rad
    quarter = len(map_poses) // 4
    assert 0.0 < position_error_m[quarter] < position_error_m[2 * quarter] < position_error_m[-1]
    assert position_error_m[quarter] > 0.02 * travelled_m[quarter] * 0.9  # at least the scale error


def test_sqlite3_raw_images_with_drift_and_the_same_bag_for_the_same_seed(tmp_path):
    recipe = rb.RobotBagRecipe(frames=7, width_px=32, height_px=24, frames_outside=1, blurred_frames=1, drift=True,
                               storage="sqlite3", compressed=False, seed=11, drive_start_s=1.0)
    first = rb.write_robot_bag(tmp_path / "a", recipe)
    messages, storage = read_bag(first.bag_path)
    assert storage == "sqlite3" and first.drift is not None
    images = messages["/camera/color/image_raw"]
    assert len(images) == 7 and all(t == "sensor_msgs/msg/Image" and (m.encoding, m.step) == ("rgb8", 96)
                                    for _, t, m in images)
    # with drift the TF chain misses the true camera, by more the later the image
    inside = [f for f in first.frames if f.in_pose_range]
    misses_m = [pose_error(tf_chain_at(messages, f.stamp_ns), f.map_from_optical)[0] for f in inside]
    assert 1e-3 < misses_m[-1] < 0.05 and misses_m[-1] > misses_m[0], misses_m  # measured 0.4 → 2.7 mm
    # deterministic: the same recipe gives the same truth and the same frames
    second = rb.write_robot_bag(tmp_path / "b", recipe)
    assert second.truth_path.read_text() == first.truth_path.read_text()
    again = read_bag(second.bag_path)[0]["/camera/color/image_raw"]
    assert all(bytes(a[2].data) == bytes(b[2].data) for a, b in zip(images, again, strict=True))
