"""An analytic pattern seen through a pinhole and through a distorted camera (the calibration tests' truth).

A distorted camera is simulated exactly: every raw pixel's centre is undistorted by OpenCV to its normalised ray, and
the pattern is sampled there (:func:`raw_view`); :func:`pinhole_view` is the pattern as an ideal pinhole camera sees
it. Shared by the calibration tests and the robot's rectification tests.
"""

from __future__ import annotations

import cv2
import numpy as np

from gsrmr_common.calibration import CameraCalibration
from gsrmr_common.camera import Intrinsics


def pattern(x_n: np.ndarray, y_n: np.ndarray) -> np.ndarray:
    """A smooth RGB pattern over normalised image coordinates (period ≈ 20 px at these focal lengths)."""
    a = 0.5 + 0.45 * np.sin(33.0 * x_n) * np.cos(29.0 * y_n)
    b = 0.5 + 0.45 * np.cos(21.0 * x_n + 11.0 * y_n)
    return np.stack([a, b, 0.5 * (a + b)], axis=-1).astype(np.float32)


def pinhole_view(k: Intrinsics) -> np.ndarray:
    """The pattern as an ideal pinhole camera ``k`` (0.5-centre convention) sees it."""
    u = (np.arange(k.width) + 0.5 - k.cx) / k.fx
    v = (np.arange(k.height) + 0.5 - k.cy) / k.fy
    return pattern(*np.meshgrid(u, v))


def raw_view(calib: CameraCalibration) -> np.ndarray:
    """The pattern as the distorted camera records it: each raw pixel centre (ROS: integers) → its ray."""
    uu, vv = np.meshgrid(np.arange(calib.width, dtype=np.float64), np.arange(calib.height, dtype=np.float64))
    pts = np.stack([uu.ravel(), vv.ravel()], axis=1).reshape(-1, 1, 2)
    if calib.distortion_model == "equidistant":
        norm = cv2.fisheye.undistortPoints(pts, calib.k, calib.distortion_array().reshape(4))
    else:
        norm = cv2.undistortPoints(pts, calib.k, calib.distortion_array(),
                                   criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12))
    norm = norm.reshape(calib.height, calib.width, 2)
    return pattern(norm[..., 0], norm[..., 1])


def interior(img: np.ndarray, margin: int) -> np.ndarray:
    return img[margin:-margin, margin:-margin]
