"""The robot's camera as it is uploaded, on the graph: the driver's ``camera/camera_info`` in, the rectified pinhole
camera out on ``uplink/camera_info`` (latched, re-published only when it changes), and each frame as it is uploaded.
ROS side of :class:`~gsrmr_robot.camera_rectify.UplinkCamera`."""

from __future__ import annotations

import threading

import numpy as np
from rclpy.node import Node
from rclpy.publisher import Publisher
from sensor_msgs.msg import CameraInfo

from gsrmr_common.calibration import CalibrationError, CameraCalibration
from gsrmr_common.camera import Intrinsics
from gsrmr_common.ros_wire import camera_info_from_intrinsics
from gsrmr_robot.camera_rectify import UplinkCamera


class UplinkCameraPort:
    """Adopts calibrations (an unusable one is refused with one WARN per distinct problem, the last usable one kept)
    and publishes the uplink camera when it changes; ``lock`` guards the camera (the slot reads it)."""

    def __init__(self, node: Node, publisher: Publisher, uplink_width_px: int, lock: threading.Lock) -> None:
        self.node, self.publisher, self._lock = node, publisher, lock
        self.camera = UplinkCamera(uplink_width_px)
        self.problem: str | None = None  # why the last camera_info was refused (None: it was usable)
        self._sent: tuple[Intrinsics, str] | None = None  # (intrinsics, frame_id) last on uplink/camera_info
        self.changes = 0  # uplink/camera_info publications
        self.frames_withheld = 0  # fresh frames not uploaded: no calibration yet, or another size

    def on_camera_info(self, msg: CameraInfo, frame_id: str) -> None:
        """A ``camera/camera_info``: adopted (maps rebuilt only when it changed) or refused."""
        try:
            calib = CameraCalibration.from_camera_info(msg)
        except CalibrationError as err:
            problem = str(err)
            if problem != self.problem:
                with self._lock:
                    kept = self.camera.describe()
                self.node.get_logger().warning(f"camera_info refused ({kept}): {problem}")
            self.problem = problem
            return
        self.problem = None
        with self._lock:
            self.camera.offer(calib)
        self.publish(frame_id)

    def publish(self, frame_id: str) -> None:
        """Publish the uplink camera on ``uplink/camera_info`` when it differs from the last one sent (a new
        calibration, uplink width or ``frame_id``; the stamp alone is no change)."""
        with self._lock:
            intrinsics = self.camera.intrinsics
            if intrinsics is None or (intrinsics, frame_id) == self._sent:
                return
            self._sent = (intrinsics, frame_id)
            self.changes += 1
            described = self.camera.describe()
        self.publisher.publish(camera_info_from_intrinsics(intrinsics, self.node.get_clock().now().nanoseconds,
                                                           frame_id))
        self.node.get_logger().info(f"camera_info → uplink/camera_info: {described}, frame {frame_id!r}")

    def frame(self, raw: np.ndarray) -> np.ndarray | None:
        """The raw frame rectified and sized for the uplink (the very array when it passes through); None (counted)
        when it cannot be: no calibration yet (INFO) or a frame of another size (WARN), both throttled. The caller
        holds ``lock``."""
        try:
            return self.camera.frame(raw)
        except CalibrationError as err:
            self.frames_withheld += 1
            log = self.node.get_logger()
            if self.camera.is_calibrated:
                log.warning(f"frame not uploaded: {err}", throttle_duration_sec=5.0)
            else:
                log.info("frames are not uploaded (pose keys only) until camera/camera_info arrives",
                         throttle_duration_sec=10.0)
            return None

    def problems(self) -> list[str]:
        """What ``/diagnostics`` warns about: no calibration yet, a refused calibration."""
        out = [] if self.camera.is_calibrated else ["waiting for camera_info"]
        return out + ([f"camera_info refused: {self.problem}"] if self.problem is not None else [])
