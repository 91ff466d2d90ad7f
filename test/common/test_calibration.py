"""The camera calibration and rectification library (gsrmr_common.calibration): pure, no ROS.

A distorted camera is simulated exactly: every raw pixel's centre is undistorted by OpenCV to its normalised
ray, and an analytic pattern is sampled there. Rectifying that frame must give the pattern as the rectified
pinhole camera sees it — at full size and resized to an uplink width — to well under a pixel (a half-pixel
slip in either convention costs 30 dB here).
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from support.calibration_pattern import interior, pinhole_view, raw_view
import yaml

from gsrmr_common.calibration import (
    CalibrationError,
    CameraCalibration,
    Rectifier,
    distort_points,
    output_size,
    rectified_intrinsics,
)
from gsrmr_common.camera import Intrinsics
from gsrmr_common.metrics import psnr as psnr_db

W, H = 320, 240
K = np.array([[260.0, 0.0, 161.3], [0.0, 258.0, 118.7], [0.0, 0.0, 1.0]])  # ROS convention
DISTORTIONS = {
    "plumb_bob": (-0.28, 0.09, 0.0007, -0.0004, -0.012),
    "rational_polynomial": (-0.25, 0.07, 0.0005, -0.0003, 0.01, 0.05, -0.02, 0.004),
    "equidistant": (-0.02, 0.01, -0.004, 0.0008),
}


@pytest.mark.parametrize("model", sorted(DISTORTIONS))
@pytest.mark.parametrize("out_width", [None, 160])
def test_rectified_frame_is_the_pinhole_view(model, out_width):
    calib = CameraCalibration(W, H, K, model, DISTORTIONS[model])
    rect = Rectifier(calib, out_width)
    got = rect(raw_view(calib))
    want = pinhole_view(rect.intrinsics)
    assert got.shape == (rect.intrinsics.height, rect.intrinsics.width, 3)
    # alpha 0: every rectified pixel comes from inside the raw frame (the border row may be interpolated)
    margin = 3 if out_width is None else 2
    quality = psnr_db(interior(got, margin), interior(want, margin))
    assert quality > 50.0, (model, out_width, quality)  # measured 58–64 dB
    # a half-pixel slip of the principal point, in either direction, is far worse
    k = rect.intrinsics
    for shift in (-0.5, 0.5):
        slipped = Intrinsics(k.fx, k.fy, k.cx + shift, k.cy + shift, k.width, k.height)
        assert psnr_db(interior(got, margin), interior(pinhole_view(slipped), margin)) < quality - 20.0  # 28–34 dB


def test_distort_points_is_the_inverse_of_rectification():
    for model, d in DISTORTIONS.items():
        calib = CameraCalibration(W, H, K, model, d)
        rect = Rectifier(calib)
        k = rect.intrinsics
        # points spread over the rectified image (0.5 convention) → normalised rays → raw pixels (ROS)
        u, v = np.meshgrid(np.linspace(20, k.width - 20, 7), np.linspace(20, k.height - 20, 5))
        norm = np.stack([(u.ravel() - k.cx) / k.fx, (v.ravel() - k.cy) / k.fy], axis=1)
        raw = distort_points(calib, norm)
        # a bright dot at each raw point, rectified, has its centroid at the rectified point
        img = np.zeros((H, W), np.float32)
        yy, xx = np.mgrid[0:H, 0:W]
        for x, y in raw:
            img += np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * 1.5**2))
        out = rect(img)
        for uc, vc in zip(u.ravel(), v.ravel(), strict=True):
            x0, y0 = int(uc), int(vc)
            win = out[y0 - 5:y0 + 6, x0 - 5:x0 + 6]
            gy, gx = np.mgrid[y0 - 5:y0 + 6, x0 - 5:x0 + 6]
            cu = float((win * (gx + 0.5)).sum() / win.sum())  # pixel centres at +0.5
            cv = float((win * (gy + 0.5)).sum() / win.sum())
            assert abs(cu - uc) < 0.15 and abs(cv - vc) < 0.15, (model, uc, vc, cu, cv)


def test_projection_matrix_is_the_rectified_camera_as_image_proc():
    p = np.array([[240.0, 0, 158.0, 0], [0, 240.0, 121.0, 0], [0, 0, 1, 0]])
    calib = CameraCalibration(W, H, K, "plumb_bob", DISTORTIONS["plumb_bob"], p=p)
    k = rectified_intrinsics(calib)
    assert (k.fx, k.fy, k.cx, k.cy) == (240.0, 240.0, 158.5, 121.5)  # ROS centres at integers → +0.5
    half = rectified_intrinsics(calib, 160)
    assert (half.width, half.height) == (160, 120)
    assert (half.fx, half.cx, half.cy) == (120.0, 158.5 / 2, 121.5 / 2)
    # undistorted, no P: K itself, and nothing to remap
    plain = CameraCalibration(W, H, K)
    assert rectified_intrinsics(plain) == Intrinsics.from_ros_k(K, W, H)
    assert Rectifier(plain).is_identity and not Rectifier(plain, 160).is_identity
    # distorted, no P: alpha 0 (camera_calibration's rule for P) — every rectified pixel sees the raw frame
    for model, d in DISTORTIONS.items():
        rect = Rectifier(CameraCalibration(W, H, K, model, d))
        white = rect(np.full((H, W), 255, np.uint8))
        assert white[1:-1, 1:-1].min() == 255, model


def test_camera_calibration_yaml_round_trip_and_camera_info(tmp_path: Path):
    # the file camera_calibration writes (ost.yaml)
    text = """image_width: 640
image_height: 480
camera_name: narrow_stereo
camera_matrix:
  rows: 3
  cols: 3
  data: [520.8, 0.0, 321.4, 0.0, 519.9, 243.2, 0.0, 0.0, 1.0]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [0.0925, -0.2071, 0.0013, -0.0018, 0.0]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
projection_matrix:
  rows: 3
  cols: 4
  data: [525.1, 0.0, 320.2, 0.0, 0.0, 527.3, 242.1, 0.0, 0.0, 0.0, 1.0, 0.0]
"""
    path = tmp_path / "ost.yaml"
    path.write_text(text)
    calib = CameraCalibration.from_yaml(path)
    assert (calib.width, calib.height, calib.frame_id) == (640, 480, "narrow_stereo")
    assert calib.d == (0.0925, -0.2071, 0.0013, -0.0018, 0.0) and calib.has_projection
    again = tmp_path / "again.yaml"
    again.write_text(yaml.safe_dump(calib.to_yaml_dict()))
    back = CameraCalibration.from_yaml(again)
    assert np.array_equal(back.k, calib.k) and np.array_equal(back.p, calib.p) and back.d == calib.d
    # the same from a CameraInfo-shaped object (rosbags and rclpy messages have these fields)
    msg = SimpleNamespace(width=640, height=480, k=list(calib.k.ravel()), d=list(calib.d), r=[0.0] * 9,
                          p=list(calib.p.ravel()), distortion_model="plumb_bob",
                          header=SimpleNamespace(frame_id="camera_color_optical_frame"))
    info = CameraCalibration.from_camera_info(msg)
    assert info.frame_id == "camera_color_optical_frame" and np.array_equal(info.r, np.eye(3))  # zeroed R: mono
    assert rectified_intrinsics(info) == rectified_intrinsics(calib)


@pytest.mark.parametrize("kwargs, words", [
    ({"k": np.zeros((3, 3))}, "uncalibrated"),
    ({"distortion_model": "kannala_brandt_x"}, "not supported"),
    ({"d": (0.1, 0.0, 0.0, 0.0, 0.0, 0.3)}, "takes 5"),
    ({"k": np.array([[260.0, 2.0, 160], [0, 258, 118], [0, 0, 1]])}, "zero-skew"),
    ({"d": (float("nan"),)}, "finite"),
])
def test_bad_calibrations_say_what_is_wrong(kwargs, words):
    args = {"width": W, "height": H, "k": K, **kwargs}
    with pytest.raises(CalibrationError, match=words):
        CameraCalibration(**args)


def test_missing_yaml_keys_and_frame_size(tmp_path: Path):
    path = tmp_path / "bad.yaml"
    path.write_text("image_width: 320\nimage_height: 240\n")
    with pytest.raises(CalibrationError, match="camera_matrix"):
        CameraCalibration.from_yaml(path)
    rect = Rectifier(CameraCalibration(W, H, K, "plumb_bob", DISTORTIONS["plumb_bob"]))
    with pytest.raises(CalibrationError, match="640×480"):
        rect(np.zeros((480, 640, 3), np.uint8))
    assert output_size(640, 480, 320) == (320, 240) and output_size(640, 480, 1000) == (640, 480)
    assert output_size(640, 360, 270) == (270, 152)
