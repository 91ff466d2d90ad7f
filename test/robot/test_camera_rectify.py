"""The robot uploads rectified, uplink-sized frames and says which pinhole camera they are (gsrmr_robot.camera_rectify,
the robot node's camera path).

A distorted camera is simulated exactly as in ``test_calibration``: each raw pixel centre is undistorted to its ray
and an analytic pattern sampled there; the frame the robot would encode must be the pattern as the published
pinhole camera sees it (a frame only resized, not remapped, is ~17 dB away from it).
"""

from __future__ import annotations

from functools import cache
import time

import cv2
import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from support.calibration_pattern import interior, pinhole_view, raw_view

from gsrmr_common.calibration import CalibrationError, CameraCalibration, rectified_intrinsics
from gsrmr_common.camera import Intrinsics
from gsrmr_common.jpeg import decode_jpeg
from gsrmr_common.metrics import psnr as psnr_db
from gsrmr_common.ros_wire import (
    CAMERA_INFO_QOS,
    IMAGE_UPLOAD_QOS,
    camera_info_from_intrinsics,
    image_to_msg,
    intrinsics_from_camera_info,
)
from gsrmr_robot.camera_rectify import PASS_THROUGH, UplinkCamera
from gsrmr_robot.robot_node import RobotNode

RAW_W, RAW_H = 640, 480  # a real camera's VGA stream
K_RAW = np.array([[520.0, 0.0, 322.1], [0.0, 516.0, 237.9], [0.0, 0.0, 1.0]])  # ROS convention
DISTORTIONS = {
    "plumb_bob": (-0.28, 0.09, 0.0007, -0.0004, -0.012),
    "rational_polynomial": (-0.25, 0.07, 0.0005, -0.0003, 0.01, 0.05, -0.02, 0.004),
    "equidistant": (-0.02, 0.01, -0.004, 0.0008),
}
FRAME_ID = "camera_color_optical_frame"  # the driver's; the uplink labels its camera with camera_frame_id


def distorted(model: str, width: int = RAW_W, height: int = RAW_H) -> CameraCalibration:
    scale = width / RAW_W  # K of the same camera at another resolution (pixel centres at integers)
    k = K_RAW.copy()
    k[:2] *= scale
    k[0, 2], k[1, 2] = (K_RAW[0, 2] + 0.5) * scale - 0.5, (K_RAW[1, 2] + 0.5) * scale - 0.5
    return CameraCalibration(width, height, k, model, DISTORTIONS[model], frame_id=FRAME_ID)


def undistorted(width: int, height: int) -> CameraCalibration:
    return CameraCalibration(width, height, Intrinsics.from_fov(width, height, 1.2).ros_k(), frame_id=FRAME_ID)


@cache
def raw_frame(model: str) -> np.ndarray:
    """The pattern as the distorted 640×480 camera records it, 8-bit RGB (what the driver publishes)."""
    return np.rint(raw_view(distorted(model)) * 255.0).astype(np.uint8)


def pinhole_frame(k: Intrinsics) -> np.ndarray:
    """The pattern as the pinhole camera ``k`` records it, 8-bit RGB."""
    return np.rint(pinhole_view(k) * 255.0).astype(np.uint8)


def quality_db(got_u8: np.ndarray, k: Intrinsics, margin: int = 2) -> float:
    """PSNR [dB] of an uplink frame against the pattern as the pinhole camera ``k`` sees it (inner pixels)."""
    return psnr_db(interior(got_u8 / 255.0, margin), interior(pinhole_view(k), margin))


# ------------------------------------------------------------------ the pure class


@pytest.mark.parametrize(("width", "height"), [(320, 240), (160, 120)])
def test_an_undistorted_camera_at_or_below_the_uplink_width_passes_through(width, height):
    calib = undistorted(width, height)
    camera = UplinkCamera(320)
    assert camera.offer(calib)
    raw = pinhole_frame(rectified_intrinsics(calib))
    assert camera.frame(raw) is raw  # no remap, no resize, no copy
    assert camera.rectifier is not None and camera.rectifier.is_identity and camera.mode == PASS_THROUGH
    assert camera.intrinsics == Intrinsics.from_ros_k(calib.k, width, height)  # not enlarged


@pytest.mark.parametrize("model", sorted(DISTORTIONS))
def test_a_distorted_camera_is_uploaded_as_the_pinhole_view_at_the_uplink_width(model):
    calib = distorted(model)
    camera = UplinkCamera(320)
    camera.offer(calib)
    k = camera.intrinsics
    assert k == rectified_intrinsics(calib, 320)  # the one rule the model's training data follows too
    assert (k.width, k.height) == (320, 240) and camera.mode == "remap+resize"
    got = camera.frame(raw_frame(model))
    assert got.shape == (240, 320, 3) and got.dtype == np.uint8
    quality = quality_db(got, k)
    assert quality > 40.0, (model, quality)  # measured 56 dB
    # what the robot sent before (the raw frame, only scaled) is not that camera's view
    scaled = cv2.resize(raw_frame(model), (320, 240), interpolation=cv2.INTER_AREA)
    assert quality_db(scaled, k) < 25.0  # measured 17 dB


def test_frames_are_scaled_to_the_uplink_width_keeping_the_aspect():
    plain = UplinkCamera(320)
    plain.offer(undistorted(RAW_W, RAW_H))  # undistorted but too wide: resized only
    assert plain.mode == "resize"
    got = plain.frame(pinhole_frame(rectified_intrinsics(undistorted(RAW_W, RAW_H))))
    assert got.shape == (240, 320, 3) and quality_db(got, plain.intrinsics) > 40.0
    odd = UplinkCamera(200)
    odd.offer(distorted("plumb_bob"))
    assert (odd.intrinsics.width, odd.intrinsics.height) == (200, 150)
    assert odd.frame(raw_frame("plumb_bob")).shape == (150, 200, 3)
    narrow = UplinkCamera(640)  # a distorted camera narrower than the uplink: remapped, not enlarged
    narrow.offer(distorted("plumb_bob", 320, 240))
    assert narrow.mode == "remap" and (narrow.intrinsics.width, narrow.intrinsics.height) == (320, 240)


def test_maps_are_built_once_per_calibration_and_uplink_width():
    camera = UplinkCamera(320)
    assert camera.offer(distorted("plumb_bob")) and camera.rectifiers_built == 1
    rectifier = camera.rectifier
    raw = raw_frame("plumb_bob")
    first = camera.frame(raw)
    assert camera.frame(raw) is first  # the same raw frame in two slots is rectified once
    # the same calibration again (a new message, another frame id): nothing is rebuilt, nothing changed
    again = CameraCalibration(RAW_W, RAW_H, K_RAW.copy(), "plumb_bob", DISTORTIONS["plumb_bob"], frame_id="other")
    assert not camera.offer(again)
    assert camera.rectifiers_built == 1 and camera.rectifier is rectifier and camera.frame(raw) is first
    # new coefficients: new maps and a new pinhole camera (alpha 0 follows the distortion)
    assert camera.offer(distorted("rational_polynomial")) and camera.rectifiers_built == 2
    assert camera.rectifier is not rectifier
    # new maps whose camera is the same (a P fixes it): rebuilt, but the uplink intrinsics did not change
    p = np.hstack([K_RAW, np.zeros((3, 1))])
    assert camera.offer(CameraCalibration(RAW_W, RAW_H, K_RAW, "plumb_bob", DISTORTIONS["plumb_bob"], p=p))
    assert not camera.offer(CameraCalibration(RAW_W, RAW_H, K_RAW, "plumb_bob", (-0.2, 0.05, 0.0, 0.0, 0.0), p=p))
    assert camera.rectifiers_built == 4
    # the uplink width: the same one changes nothing, another one rebuilds at the new size
    assert not camera.set_uplink_width(320) and camera.rectifiers_built == 4
    assert camera.set_uplink_width(160) and camera.rectifiers_built == 5
    assert camera.frame(raw).shape == (120, 160, 3)


def test_no_frame_before_the_first_calibration_nor_of_another_size():
    camera = UplinkCamera(320)
    assert not camera.set_uplink_width(160)  # nothing to rebuild yet
    assert camera.intrinsics is None and not camera.is_calibrated and camera.describe() == "waiting for camera_info"
    with pytest.raises(CalibrationError, match="no camera_info yet"):
        camera.frame(raw_frame("plumb_bob"))
    camera.offer(distorted("plumb_bob", 320, 240))
    with pytest.raises(CalibrationError, match="640×480, the calibration is for 320×240"):
        camera.frame(raw_frame("plumb_bob"))
    with pytest.raises(ValueError, match="positive integer"):
        UplinkCamera(0)


@pytest.mark.parametrize("model", ["equidistant", "none"])
def test_the_uplink_camera_info_is_the_rectified_pinhole_camera(model):
    camera = UplinkCamera(320)
    camera.offer(distorted(model) if model != "none" else undistorted(320, 240))
    k = camera.intrinsics
    msg = camera_info_from_intrinsics(k, 123, "camera_optical_frame")
    assert (msg.width, msg.height, msg.header.frame_id) == (k.width, k.height, "camera_optical_frame")
    assert msg.distortion_model == "plumb_bob" and list(msg.d) == [0.0] * 5
    np.testing.assert_array_equal(np.reshape(msg.r, (3, 3)), np.eye(3))
    ros_k = np.reshape(msg.k, (3, 3))
    assert (ros_k[0, 2], ros_k[1, 2]) == pytest.approx((k.cx - 0.5, k.cy - 0.5), abs=1e-12)  # centres at integers
    np.testing.assert_array_equal(np.reshape(msg.p, (3, 4)), np.hstack([ros_k, np.zeros((3, 1))]))
    # the server takes it as it is (no distortion to refuse) and gets the same camera back
    back = intrinsics_from_camera_info(msg)
    assert (back.width, back.height) == (k.width, k.height)
    assert np.allclose((back.fx, back.fy, back.cx, back.cy), (k.fx, k.fy, k.cx, k.cy), rtol=0, atol=1e-9)
    # and a robot given that camera uploads its frames untouched: the uplink camera is a fixed point
    again = UplinkCamera(320)
    again.offer(CameraCalibration.from_camera_info(msg))
    assert again.mode == PASS_THROUGH


# ------------------------------------------------------------------ the node, over DDS




def camera_info_msg(calib: CameraCalibration, stamp) -> CameraInfo:
    """A driver's CameraInfo of ``calib`` (no P: the robot derives the rectified camera itself)."""
    msg = CameraInfo()
    msg.header.stamp, msg.header.frame_id = stamp, calib.frame_id
    msg.width, msg.height = calib.width, calib.height
    msg.distortion_model, msg.d = calib.distortion_model, list(calib.d)
    msg.k, msg.r, msg.p = calib.k.ravel().tolist(), np.eye(3).ravel().tolist(), [0.0] * 12
    return msg


@pytest.mark.ros
def test_robot_node_uploads_the_rectified_frame_at_the_uplink_width(ros_context):
    calib = distorted("plumb_bob")
    raw = raw_frame("plumb_bob")
    robot = RobotNode(context=ros_context,  # issue 28: live changes are off unless the node starts with them on
                      parameter_overrides=[Parameter("live_parameter_changes", value=True)])
    probe = rclpy.create_node("rectify_probe", context=ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    try:
        executor.add_node(robot)
        executor.add_node(probe)
        pub_info = probe.create_publisher(CameraInfo, "camera/camera_info", qos_profile_sensor_data)
        pub_image = probe.create_publisher(Image, "camera/image_raw", qos_profile_sensor_data)
        infos: list[CameraInfo] = []
        uploads: list[CompressedImage] = []
        probe.create_subscription(CameraInfo, "uplink/camera_info", infos.append, CAMERA_INFO_QOS)
        probe.create_subscription(CompressedImage, "uplink/image_raw/compressed", uploads.append, IMAGE_UPLOAD_QOS)

        def feed_until(done, timeout_s: float, with_info: bool = True) -> None:
            """Publish the camera's frame (and its calibration) at 20 Hz and spin until ``done()``."""
            deadline = time.monotonic() + timeout_s
            while not done():
                assert time.monotonic() < deadline, (robot.camera.describe(), len(infos), len(uploads))
                now = probe.get_clock().now()
                if with_info:
                    pub_info.publish(camera_info_msg(calib, now.to_msg()))
                pub_image.publish(image_to_msg(raw, now.nanoseconds, FRAME_ID))
                end = time.monotonic() + 0.05
                while time.monotonic() < end:
                    executor.spin_once(timeout_sec=0.01)

        # frames without a calibration: withheld (keys only), counted, nothing on uplink/camera_info
        feed_until(lambda: robot.port.frames_withheld >= 3, 30, with_info=False)
        assert not uploads and not infos and "waiting for camera_info" in robot._problems()

        feed_until(lambda: bool(infos) and len(uploads) >= 2, 30)
        info = infos[0]
        assert (info.width, info.height, info.header.frame_id) == (320, 240, "camera_optical_frame")
        assert info.distortion_model == "plumb_bob" and not any(info.d)
        want = rectified_intrinsics(calib, 320)
        np.testing.assert_allclose(np.reshape(info.k, (3, 3)), want.ros_k(), rtol=0, atol=1e-9)
        np.testing.assert_allclose(np.reshape(info.p, (3, 4))[:, :3], want.ros_k(), rtol=0, atol=1e-9)
        got = decode_jpeg(bytes(uploads[-1].data))
        assert got.shape == (240, 320, 3)
        quality = quality_db(got, intrinsics_from_camera_info(info))
        assert quality > 30.0, quality  # JPEG q80 of the rectified view: measured 41.6 dB (unrectified: 17.6 dB)
        feed_until(lambda: len(uploads) >= 5, 30)
        assert len(infos) == 1 and robot.camera.rectifiers_built == 1  # the same calibration: no re-publish

        # a live uplink width: new maps, a new latched camera_info, smaller uploads
        assert robot.set_parameters([Parameter("uplink_width_px", value=160)])[0].successful
        n = len(uploads)
        feed_until(lambda: len(infos) >= 2 and len(uploads) >= n + 2, 30)
        assert (infos[1].width, infos[1].height) == (160, 120)
        got = decode_jpeg(bytes(uploads[-1].data))
        assert got.shape == (120, 160, 3)
        assert quality_db(got, intrinsics_from_camera_info(infos[1])) > 30.0  # measured 36 dB
        assert robot.port.changes == 2 and robot.camera.rectifiers_built == 2
    finally:
        executor.shutdown()
        probe.destroy_node()
        robot.destroy_node()
