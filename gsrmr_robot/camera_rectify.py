"""The camera as the uplink sends it (pure, no ROS): a calibration's rectifier at the uplink width.

:class:`UplinkCamera` rectifies and scales each frame by the one rule of :mod:`gsrmr_common.calibration`, which the
dataset tool that builds the model's training data uses too, so the model, the live render and the uploaded frames
are one pinhole camera. What the robot does with it: ``docs/nodes.md``, "The robot", "Calibration".
"""

from __future__ import annotations

import numpy as np

from gsrmr_common.calibration import CalibrationError, CameraCalibration, Rectifier
from gsrmr_common.camera import Intrinsics

#: What :attr:`UplinkCamera.mode` says when frames pass through untouched.
PASS_THROUGH = "pass-through"


def calibration_key(calib: CameraCalibration) -> tuple:
    """What the rectification of ``calib`` depends on: size, K, distortion model and coefficients, R and P
    (the frame id and a message's stamp are no part of it)."""
    return (calib.width, calib.height, calib.k.tobytes(), calib.distortion_model, calib.d, calib.r.tobytes(),
            calib.p.tobytes())


def check_uplink_width(uplink_width_px: int) -> int:
    """``uplink_width_px`` as an int ≥ 1 (ValueError otherwise)."""
    if int(uplink_width_px) != uplink_width_px or uplink_width_px < 1:
        raise ValueError(f"uplink_width_px must be a positive integer, got {uplink_width_px!r}")
    return int(uplink_width_px)


class UplinkCamera:
    """The calibration → rectifier state of the robot's uplink.

    :meth:`offer` takes the calibration of every ``camera_info`` and builds the maps only when it differs from the
    current one (:func:`calibration_key`); the answer says whether the uplink intrinsics changed (re-publish them).
    :meth:`frame` makes the frame to encode with one ``cv2.remap`` and, when scaling down, one ``cv2.resize``
    ``INTER_AREA``: the same raw array, unchanged, asked for twice is rectified once, and an undistorted camera at or
    below the uplink width passes through untouched (the very array, no copy). Frames narrower than the uplink width
    are not enlarged. The optical frame is OpenCV's (x right, y down, z forward) before and after: for a monocular
    camera (R = I) rectification changes the pixels, not the frame (a stereo camera's R turns the rectified view, as
    ``image_proc`` does). :attr:`intrinsics` has pixel centres at (u + 0.5, v + 0.5)
    (:class:`~gsrmr_common.camera.Intrinsics`; ``ros_k()`` for a CameraInfo).
    """

    def __init__(self, uplink_width_px: int = 320) -> None:
        self.uplink_width_px = check_uplink_width(uplink_width_px)
        self.calibration: CameraCalibration | None = None  # the newest usable calibration, None before the first
        self.rectifier: Rectifier | None = None  # its rectifier at uplink_width_px
        self.rectifiers_built = 0  # how many times maps were computed (once per calibration or width change)
        self._key: tuple | None = None
        self._last_raw: np.ndarray | None = None  # the raw frame of _last_out (identity: the same array)
        self._last_out: np.ndarray | None = None

    @property
    def intrinsics(self) -> Intrinsics | None:
        """The rectified pinhole camera of the uploaded frames (uplink size, 0.5-pixel-centre convention), None
        before the first calibration."""
        return None if self.rectifier is None else self.rectifier.intrinsics

    @property
    def is_calibrated(self) -> bool:
        """Whether a calibration has been adopted (frames can be uploaded)."""
        return self.rectifier is not None

    @property
    def mode(self) -> str:
        """What a frame goes through: ``pass-through``, ``remap``, ``resize`` or ``remap+resize`` (``uncalibrated``
        before the first calibration)."""
        if self.rectifier is None or self.calibration is None:
            return "uncalibrated"
        if self.rectifier.is_identity:
            return PASS_THROUGH
        k, calib = self.rectifier.intrinsics, self.calibration
        steps = (["remap"] if calib.needs_remap else []) + (["resize"] if (k.width, k.height) != (
            calib.width, calib.height) else [])
        return "+".join(steps)

    def offer(self, calib: CameraCalibration) -> bool:
        """Adopt ``calib`` (the camera's calibration, e.g. from each ``camera_info``): the maps are rebuilt when it
        differs from the current one. Returns whether the uplink intrinsics changed (True for the first)."""
        key = calibration_key(calib)
        if key == self._key:
            return False
        self._key, self.calibration = key, calib
        return self._rebuild(calib)

    def set_uplink_width(self, uplink_width_px: int) -> bool:
        """A new uplink width [px]: the maps are rebuilt for it (when calibrated). Returns whether the uplink
        intrinsics changed."""
        width = check_uplink_width(uplink_width_px)
        if width == self.uplink_width_px:
            return False
        self.uplink_width_px = width
        return self.calibration is not None and self._rebuild(self.calibration)

    def _rebuild(self, calib: CameraCalibration) -> bool:
        """Compute the maps of ``calib`` at the uplink width; whether the uplink intrinsics changed."""
        before = self.intrinsics
        self.rectifier = Rectifier(calib, self.uplink_width_px)
        self.rectifiers_built += 1
        self._last_raw = self._last_out = None
        return self.rectifier.intrinsics != before

    def frame(self, raw: np.ndarray) -> np.ndarray:
        """The H×W×3 raw frame as it is uploaded: rectified and sized to :attr:`intrinsics` (``raw`` itself when
        frames pass through). Raises :class:`~gsrmr_common.calibration.CalibrationError` before the first
        calibration and for a frame of another size than the calibration's."""
        if self.rectifier is None:
            raise CalibrationError("no camera_info yet: the frame's camera is unknown")
        if raw is self._last_raw and self._last_out is not None:
            return self._last_out
        out = self.rectifier(raw)
        self._last_raw, self._last_out = raw, out
        return out

    def describe(self) -> str:
        """``640×480 plumb_bob → 320×240 fx=… fy=… cx=… cy=… (remap+resize)`` (pixels, 0.5-centre convention), or
        ``waiting for camera_info``."""
        k, calib = self.intrinsics, self.calibration
        if k is None or calib is None:
            return "waiting for camera_info"
        model = calib.distortion_model if calib.is_distorted else "undistorted"
        return (f"{calib.width}×{calib.height} {model} → {k.width}×{k.height} fx={k.fx:.3f} fy={k.fy:.3f} "
                f"cx={k.cx:.3f} cy={k.cy:.3f} ({self.mode})")
