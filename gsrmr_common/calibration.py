"""A real camera's calibration and its rectification to the pinhole camera the GS renderer draws.

:class:`CameraCalibration` (``sensor_msgs/CameraInfo``'s fields, ROS conventions), :func:`rectified_intrinsics` (the
one rule for the rectified camera, shared by ``gsrmr-dataset`` and the robot's uplink) and :class:`Rectifier` (the
frames). The conventions, the distortion models, the rule and its scaling to another width: docs/architecture.md,
"A camera's calibration and its rectified camera". Pure numpy and OpenCV, no ROS import.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from gsrmr_common.camera import Intrinsics

PLUMB_BOB = "plumb_bob"
RATIONAL_POLYNOMIAL = "rational_polynomial"
EQUIDISTANT = "equidistant"
#: Distortion model → number of coefficients it takes (ROS names; ``fisheye`` is read as ``equidistant``).
DISTORTION_COEFFS = {PLUMB_BOB: 5, RATIONAL_POLYNOMIAL: 8, EQUIDISTANT: 4}
_ALIASES = {"": PLUMB_BOB, "fisheye": EQUIDISTANT, "radtan": PLUMB_BOB, "pinhole": PLUMB_BOB}


class CalibrationError(ValueError):
    """A calibration that cannot describe a camera (what is wrong is in the message)."""


def _matrix(values: Any, rows: int, cols: int, what: str) -> np.ndarray:
    arr = np.asarray(values, dtype=np.float64)
    if arr.size != rows * cols:
        raise CalibrationError(f"{what} must have {rows * cols} values, got {arr.size}")
    arr = arr.reshape(rows, cols)
    if not np.all(np.isfinite(arr)):
        raise CalibrationError(f"{what} has a non-finite value: {arr.tolist()}")
    return arr


@dataclass(frozen=True)
class CameraCalibration:
    """A camera's calibration as in ``sensor_msgs/CameraInfo`` (ROS conventions; module docstring)."""

    width: int
    height: int
    k: np.ndarray = field(repr=False)
    distortion_model: str = PLUMB_BOB
    d: tuple[float, ...] = ()
    r: np.ndarray = field(default_factory=lambda: np.eye(3), repr=False)
    p: np.ndarray = field(default_factory=lambda: np.zeros((3, 4)), repr=False)
    frame_id: str = ""

    def __post_init__(self) -> None:
        if int(self.width) != self.width or int(self.height) != self.height or self.width < 1 or self.height < 1:
            raise CalibrationError(f"image size must be positive integers, got {self.width}×{self.height}")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        k = _matrix(self.k, 3, 3, "K")
        if not np.any(k):
            raise CalibrationError("K is all zeros: the camera is uncalibrated (run camera_calibration, or give "
                                   "--camera-info FILE)")
        if k[0, 0] <= 0 or k[1, 1] <= 0 or abs(k[0, 1]) > 1e-9 or np.any(k[2] != (0.0, 0.0, 1.0)) or k[1, 0] or k[2, 0]:
            raise CalibrationError(f"K is not a zero-skew pinhole matrix with positive focal lengths: {k.tolist()}")
        model = _ALIASES.get(self.distortion_model, self.distortion_model)
        if model not in DISTORTION_COEFFS:
            raise CalibrationError(f"distortion model {self.distortion_model!r} is not supported (supported: "
                                   f"{', '.join(DISTORTION_COEFFS)})")
        d = tuple(float(v) for v in self.d)
        if not all(math.isfinite(v) for v in d):
            raise CalibrationError(f"distortion coefficients must be finite, got {list(d)}")
        want = DISTORTION_COEFFS[model]
        if len(d) > want and any(d[want:]):
            raise CalibrationError(f"{model} takes {want} coefficients, got {len(d)}: {list(d)}")
        d = (d + (0.0,) * want)[:want]
        r = _matrix(self.r, 3, 3, "R")
        if not np.any(r):
            r = np.eye(3)  # some drivers leave R zeroed: monocular
        if not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
            raise CalibrationError(f"R is not a rotation: {r.tolist()}")
        p = _matrix(self.p, 3, 4, "P")
        object.__setattr__(self, "k", k)
        object.__setattr__(self, "distortion_model", model)
        object.__setattr__(self, "d", d)
        object.__setattr__(self, "r", r)
        object.__setattr__(self, "p", p)

    @property
    def is_distorted(self) -> bool:
        """Whether any distortion coefficient is non-zero."""
        return any(self.d)

    @property
    def has_projection(self) -> bool:
        """Whether P describes a rectified pinhole camera (non-zero fx, fy; zero skew)."""
        p = self.p
        return bool(p[0, 0] > 0 and p[1, 1] > 0 and abs(p[0, 1]) < 1e-9 and p[2, 2] == 1.0)

    @property
    def needs_remap(self) -> bool:
        """Whether frames must be remapped (distortion, a rectification rotation, or P ≠ K)."""
        if self.is_distorted or not np.allclose(self.r, np.eye(3)):
            return True
        return self.has_projection and not np.allclose(self.p[:, :3], self.k, atol=1e-9)

    @classmethod
    def from_camera_info(cls, msg: Any) -> CameraCalibration:
        """From a ``sensor_msgs/CameraInfo`` (or any object with its fields ``width height k d r p
        distortion_model header.frame_id``; rosbags' deserialised messages work too)."""
        header = getattr(msg, "header", None)
        return cls(width=int(msg.width), height=int(msg.height), k=np.asarray(msg.k, dtype=np.float64),
                   distortion_model=str(msg.distortion_model), d=tuple(float(v) for v in msg.d),
                   r=np.asarray(msg.r, dtype=np.float64), p=np.asarray(msg.p, dtype=np.float64),
                   frame_id=str(getattr(header, "frame_id", "")) if header is not None else "")

    @classmethod
    def from_yaml(cls, path: str | Path) -> CameraCalibration:
        """From a ``camera_calibration`` / ``camera_info_manager`` YAML file (``image_width``, ``image_height``,
        ``camera_name``, ``camera_matrix``, ``distortion_model``, ``distortion_coefficients``,
        ``rectification_matrix``, ``projection_matrix``; each matrix ``{rows, cols, data}``)."""
        path = Path(path)
        try:
            doc = yaml.safe_load(path.read_text())
        except (OSError, yaml.YAMLError) as err:
            raise CalibrationError(f"{path}: cannot read the calibration file ({err})") from err
        if not isinstance(doc, dict):
            raise CalibrationError(f"{path}: not a camera_calibration YAML (a mapping is expected)")

        def mat(key: str, rows: int, cols: int, required: bool) -> np.ndarray | None:
            entry = doc.get(key)
            if entry is None:
                if required:
                    raise CalibrationError(f"{path}: no {key!r} (a camera_calibration file has image_width, "
                                           f"image_height, camera_matrix, distortion_model, distortion_coefficients)")
                return None
            data = entry.get("data") if isinstance(entry, dict) else entry
            return _matrix(data, rows, cols, f"{path.name}: {key}")

        for key in ("image_width", "image_height"):
            if key not in doc:
                raise CalibrationError(f"{path}: no {key!r}")
        dist = doc.get("distortion_coefficients") or {}
        d = dist.get("data", []) if isinstance(dist, dict) else dist
        r, p = mat("rectification_matrix", 3, 3, False), mat("projection_matrix", 3, 4, False)
        return cls(width=int(doc["image_width"]), height=int(doc["image_height"]), k=mat("camera_matrix", 3, 3, True),
                   distortion_model=str(doc.get("distortion_model", PLUMB_BOB)), d=tuple(d or ()),
                   r=np.eye(3) if r is None else r, p=np.zeros((3, 4)) if p is None else p,
                   frame_id=str(doc.get("camera_name", "")))

    def to_yaml_dict(self) -> dict:
        """The ``camera_calibration`` YAML layout of this calibration (``yaml.safe_dump`` it)."""
        def m(a: np.ndarray) -> dict:
            return {"rows": a.shape[0], "cols": a.shape[1], "data": [float(v) for v in a.ravel()]}
        return {"image_width": self.width, "image_height": self.height, "camera_name": self.frame_id or "camera",
                "camera_matrix": m(self.k), "distortion_model": self.distortion_model,
                "distortion_coefficients": {"rows": 1, "cols": len(self.d), "data": list(self.d)},
                "rectification_matrix": m(self.r), "projection_matrix": m(self.p)}

    def distortion_array(self) -> np.ndarray:
        """``d`` as OpenCV wants it (1×N float64)."""
        return np.asarray(self.d, dtype=np.float64).reshape(1, -1)


def output_size(width: int, height: int, out_width: int | None) -> tuple[int, int]:
    """(width, height) of a ``width``×``height`` image resized to ``out_width`` (aspect kept, height rounded;
    never larger than the input: ``None`` or a larger width keeps the size)."""
    if out_width is None or out_width >= width:
        return width, height
    if out_width < 1:
        raise CalibrationError(f"output width must be ≥ 1, got {out_width}")
    return int(out_width), max(1, int(round(height * out_width / width)))


def _full_size_ros_k(calib: CameraCalibration) -> np.ndarray:
    """The rectified camera's 3×3 K at the calibration's size, ROS convention (the rule of the module docstring)."""
    if calib.has_projection:
        return calib.p[:, :3].copy()
    if not calib.is_distorted:
        return calib.k.copy()
    size = (calib.width, calib.height)
    if calib.distortion_model == EQUIDISTANT:
        return cv2.fisheye.estimateNewCameraMatrixForUndistortRectify(
            calib.k, calib.distortion_array().reshape(4), size, calib.r, balance=0.0)
    new_k, _roi = cv2.getOptimalNewCameraMatrix(calib.k, calib.distortion_array(), size, 0.0, size)
    return new_k


def rectified_intrinsics(calib: CameraCalibration, out_width: int | None = None) -> Intrinsics:
    """The pinhole camera frames of ``calib`` become once rectified (and resized to ``out_width``, aspect kept,
    never enlarged), in the 0.5-pixel-centre convention of :class:`~gsrmr_common.camera.Intrinsics`.

    The one rule (module docstring): P when given, else K when undistorted, else alpha 0 / balance 0."""
    full = Intrinsics.from_ros_k(_full_size_ros_k(calib), calib.width, calib.height)
    w, h = output_size(calib.width, calib.height, out_width)
    return full if (w, h) == (calib.width, calib.height) else full.scaled(w, h)


class Rectifier:
    """Frames of a calibrated camera → the rectified pinhole camera of :func:`rectified_intrinsics`.

    The maps are computed once (here); each frame costs one ``cv2.remap`` at the calibration's size (bilinear,
    skipped when nothing needs remapping) and, when ``out_width`` is smaller, one ``cv2.resize`` with
    ``INTER_AREA`` (the filter the trainer downscales with). Pixels that map outside the raw frame are black.
    """

    def __init__(self, calib: CameraCalibration, out_width: int | None = None) -> None:
        self.calibration = calib
        self.intrinsics = rectified_intrinsics(calib, out_width)
        self._full_k = _full_size_ros_k(calib)
        size = (calib.width, calib.height)
        self._maps: tuple[np.ndarray, np.ndarray] | None = None
        if calib.needs_remap:
            if calib.distortion_model == EQUIDISTANT:
                self._maps = cv2.fisheye.initUndistortRectifyMap(
                    calib.k, calib.distortion_array().reshape(4), calib.r, self._full_k, size, cv2.CV_16SC2)
            else:
                self._maps = cv2.initUndistortRectifyMap(calib.k, calib.distortion_array(), calib.r, self._full_k,
                                                         size, cv2.CV_16SC2)

    @property
    def is_identity(self) -> bool:
        """Whether frames pass through unchanged (no remap, no resize)."""
        k = self.intrinsics
        return self._maps is None and (k.width, k.height) == (self.calibration.width, self.calibration.height)

    def __call__(self, frame: np.ndarray) -> np.ndarray:
        """Rectify (and resize) one H×W[×C] frame of the calibrated size; returns a new array (or ``frame`` itself
        when :attr:`is_identity`)."""
        h, w = frame.shape[:2]
        if (w, h) != (self.calibration.width, self.calibration.height):
            raise CalibrationError(f"frame is {w}×{h}, the calibration is for "
                                   f"{self.calibration.width}×{self.calibration.height}")
        out = frame
        if self._maps is not None:
            out = cv2.remap(frame, self._maps[0], self._maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        k = self.intrinsics
        if (k.width, k.height) != (w, h):
            out = cv2.resize(out, (k.width, k.height), interpolation=cv2.INTER_AREA)
        return out

    def rectify_depth(self, depth: np.ndarray) -> np.ndarray:
        """An aligned depth image (same camera) through the same maps with nearest-neighbour sampling (depths are
        not averaged across edges); resized with nearest too."""
        out = depth
        if self._maps is not None:
            out = cv2.remap(depth, self._maps[0], self._maps[1], cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT)
        k = self.intrinsics
        if (k.width, k.height) != (out.shape[1], out.shape[0]):
            out = cv2.resize(out, (k.width, k.height), interpolation=cv2.INTER_NEAREST)
        return out


def distort_points(calib: CameraCalibration, points_norm: np.ndarray) -> np.ndarray:
    """N×2 normalised pinhole coordinates (x/z, y/z in the camera frame, before R) → N×2 raw pixel coordinates
    (ROS convention) under ``calib``'s distortion and K — the forward model, e.g. for simulating a distorted
    camera from a pinhole render."""
    pts = np.asarray(points_norm, dtype=np.float64).reshape(-1, 1, 2)
    if calib.distortion_model == EQUIDISTANT:
        out = cv2.fisheye.distortPoints(pts, calib.k, calib.distortion_array().reshape(4))
    else:
        obj = np.concatenate([pts.reshape(-1, 2), np.ones((pts.shape[0], 1))], axis=1)
        out, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), calib.k, calib.distortion_array())
    return out.reshape(-1, 2)
