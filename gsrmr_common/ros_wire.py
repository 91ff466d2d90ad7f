"""Conversions between the plain wire records of :mod:`gsrmr_common.wire` and ROS 2 messages, and their QoS.

Imports message classes only (no rclpy node, no executor), so tests, the recorder and tools use it without a running
graph. The rules and layouts live in ``wire``; this module maps fields (``*_to_msg`` / ``*_from_msg``), images
(:mod:`gsrmr_common.image_bridge`, :mod:`gsrmr_common.jpeg`), :class:`~gsrmr_common.camera.Intrinsics` ↔
``CameraInfo`` and stamps ↔ integer nanoseconds. Every ``*_from_msg`` raises ``ValueError`` (or
:class:`gsrmr_common.jpeg.ImageRejected`, a subclass) on an inconsistent message; nothing here logs or swallows
errors.
"""

from __future__ import annotations

from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseStamped, Vector3Stamped
import numpy as np
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

from gsrmr_common import wire
from gsrmr_common.camera import Intrinsics
from gsrmr_common.image_bridge import imgmsg_to_numpy, numpy_to_imgmsg
from gsrmr_common.image_decode import IMAGE_TYPE, ImageDecodeError, decode_colour
from gsrmr_common.jpeg import ImageRejected, decode_jpeg
from gsrmr_common.pose2d import quaternion_from_yaw
from gsrmr_common.slot_clock import SlotClock

NS_PER_S = 1_000_000_000
_INT32_MIN, _INT32_MAX = -(2**31), 2**31 - 1
SCHEDULE_LABELS = ("meta", "x", "power_w")  # + "gain_threshold" when the schedule has an in-slot rule
# the encodings image_bridge converts to rgb8; image_from_msg matches their names case-insensitively
# (image_bridge, like ROS, is case-sensitive)
_RGB_SOURCE_ENCODINGS = frozenset({"rgb8", "bgr8", "rgba8", "bgra8", "mono8", "mono16"})
# YUV 4:2:2 as USB cameras send it (usb_cam, v4l2_camera): UYVY (``yuv422``, ``uyvy``), YUYV (``yuv422_yuy2``,
# ``yuyv``); decoded by :mod:`gsrmr_common.image_decode`, as the dataset tool decodes a recorded frame
_YUV422_ENCODINGS = frozenset({"yuv422", "uyvy", "yuv422_yuy2", "yuyv"})


# QoS of the robot ↔ workstation topics (camera and odometry inputs use the sensor-data profile).
#: pose keys, ledger rows, MR slot infos: reliable, a few seconds of slots queued.
UPLINK_QOS = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
#: loss samples (server → scheduler): reliable, **transient local**, depth 50 (5 s of slots at one sample a slot): a
#: reader that subscribes again — after a flood pause (:mod:`gsrmr_common.ros_admission`) or a restart — gets the
#: samples it missed; the writer's history is its reliable queue of 50 either way. A volatile writer does not match it.
LOSS_SAMPLE_QOS = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
#: JPEG uploads: reliable, depth 10 (each is 5–40 kB).
IMAGE_UPLOAD_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
#: the schedule: latched (reliable, transient local, depth 1): a robot started later gets the newest one.
SCHEDULE_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
#: the robot's relayed calibration: latched, so a server started before or after the robot holds the newest.
CAMERA_INFO_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)

def stamp_to_ns(stamp: Time) -> int:
    """``builtin_interfaces/Time`` → integer nanoseconds since the clock's epoch."""
    if not 0 <= stamp.nanosec < NS_PER_S:
        raise ValueError(f"Time.nanosec must be in [0, 1e9), got {stamp.nanosec}")
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def ns_to_stamp(ns: int) -> Time:
    """Integer nanoseconds → ``builtin_interfaces/Time`` (``sec`` floored, ``nanosec`` in [0, 1e9))."""
    if isinstance(ns, float) or int(ns) != ns:
        raise ValueError(f"time stamp must be integer nanoseconds, got {ns!r}")
    sec, nanosec = divmod(int(ns), NS_PER_S)
    if not _INT32_MIN <= sec <= _INT32_MAX:
        raise ValueError(f"time stamp {ns} ns does not fit builtin_interfaces/Time (int32 seconds)")
    return Time(sec=sec, nanosec=nanosec)


# --------------------------------------------------------------------------------------- pose key

def pose_key_to_msg(key: wire.PoseKey, clock: SlotClock) -> Vector3Stamped:
    """Pose key → ``Vector3Stamped`` (frame ``map``, stamp = start of ``key.slot``)."""
    msg = Vector3Stamped()
    msg.header.stamp = ns_to_stamp(clock.start_ns(key.slot))
    msg.header.frame_id = wire.MAP_FRAME
    msg.vector.x, msg.vector.y, msg.vector.z = float(key.a_m), float(key.b_m), float(key.theta_rad)
    return msg


def pose_key_pose_msg(key: wire.PoseKey, stamp_ns: int) -> PoseStamped:
    """A pose key as the standard ``PoseStamped`` of ``base_link`` in ``map`` (position (a_m, b_m, 0), yaw θ about
    +z) stamped ``stamp_ns`` — what a bag tool reads as a pose topic."""
    msg = PoseStamped()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = wire.MAP_FRAME
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = float(key.a_m), float(key.b_m), 0.0
    q = msg.pose.orientation
    q.x, q.y, q.z, q.w = quaternion_from_yaw(float(key.theta_rad))
    return msg


def pose_key_from_msg(msg: Vector3Stamped, clock: SlotClock) -> wire.PoseKey:
    """``Vector3Stamped`` → pose key; the slot comes from the stamp. Refuses frames other than ``map``.

    The key may still be non-finite: check :meth:`wire.PoseKey.is_valid` before rendering it.
    """
    if msg.header.frame_id != wire.MAP_FRAME:
        raise ValueError(f"pose key must be in frame {wire.MAP_FRAME!r}, got {msg.header.frame_id!r}")
    slot = clock.slot_named(stamp_to_ns(msg.header.stamp))
    return wire.PoseKey(slot, float(msg.vector.x), float(msg.vector.y), float(msg.vector.z))


# --------------------------------------------------------------------------------------- schedule

def schedule_to_msg(schedule: wire.ScheduleMsg) -> Float64MultiArray:
    """Schedule → ``Float64MultiArray`` with ``layout.dim`` = meta(4), x(n), power_w(n)."""
    data = schedule.to_data()
    msg = Float64MultiArray()
    labels, sizes = _schedule_layout(schedule)
    msg.layout.dim = [MultiArrayDimension(label=label, size=size, stride=size)
                      for label, size in zip(labels, sizes, strict=True)]
    msg.layout.data_offset = 0
    msg.data = data
    return msg


def schedule_from_msg(msg: Float64MultiArray) -> wire.ScheduleMsg:
    """``Float64MultiArray`` → schedule; checks the layout labels and sizes against ``data``."""
    if msg.layout.data_offset != 0:
        raise ValueError(f"schedule: layout.data_offset must be 0, got {msg.layout.data_offset}")
    schedule = wire.ScheduleMsg.from_data(np.asarray(msg.data, dtype=np.float64))
    n = len(schedule.x)
    labels = tuple(d.label for d in msg.layout.dim)
    sizes = tuple(int(d.size) for d in msg.layout.dim)
    if (labels, sizes) != _schedule_layout(schedule):
        raise ValueError(f"schedule: layout {list(zip(labels, sizes, strict=True))} does not match "
                         f"meta(4), x({n}), power_w({n})" + (f", gain_threshold({n})"
                                                             if schedule.gain_threshold is not None else ""))
    return schedule


def _schedule_layout(schedule: wire.ScheduleMsg) -> tuple[tuple[str, ...], tuple[int, ...]]:
    n = len(schedule.x)
    if schedule.gain_threshold is None:
        return SCHEDULE_LABELS, (len(wire.SCHEDULE_META), n, n)
    return (*SCHEDULE_LABELS, "gain_threshold"), (len(wire.SCHEDULE_META), n, n, n)


# ------------------------------------------------------------------------------------------ images

def _flat_record_msg(label: str, data: list[float]) -> Float64MultiArray:
    msg = Float64MultiArray()
    msg.layout.dim = [MultiArrayDimension(label=label, size=len(data), stride=len(data))]
    msg.layout.data_offset = 0
    msg.data = data
    return msg


def _check_flat_layout(msg: Float64MultiArray, label: str) -> None:
    dims = [(d.label, int(d.size)) for d in msg.layout.dim]
    if msg.layout.data_offset != 0 or dims not in ([], [(label, len(msg.data))]):
        raise ValueError(f"{label}: layout {dims} (offset {msg.layout.data_offset}) does not match "
                         f"{label}({len(msg.data)})")


def ledger_to_msg(row: wire.LedgerRow) -> Float64MultiArray:
    """Ledger row → ``Float64MultiArray`` (``layout.dim = [ledger(14)]``, fields in ``LEDGER_FIELDS`` order)."""
    return _flat_record_msg("ledger", wire.ledger_row_to_data(row))


def ledger_from_msg(msg: Float64MultiArray) -> wire.LedgerRow:
    """``Float64MultiArray`` → ledger row; ValueError if it does not parse (see ``ledger_row_from_data``)."""
    _check_flat_layout(msg, "ledger")
    return wire.ledger_row_from_data(np.asarray(msg.data, dtype=np.float64))


def loss_sample_to_msg(sample: wire.LossSample) -> Float64MultiArray:
    """Loss sample → ``Float64MultiArray`` (``layout.dim = [loss_sample(5)]``: slot, a_m, b_m, theta_rad, loss)."""
    return _flat_record_msg("loss_sample", sample.to_data())


def loss_sample_from_msg(msg: Float64MultiArray) -> wire.LossSample:
    """``Float64MultiArray`` → loss sample; ValueError if it does not parse."""
    _check_flat_layout(msg, "loss_sample")
    return wire.LossSample.from_data(np.asarray(msg.data, dtype=np.float64))


def channel_sample_to_msg(sample: wire.ChannelSample) -> Float64MultiArray:
    """Channel sample → ``Float64MultiArray`` (``layout.dim = [channel_sample(3)]``: slot, round_slot, gain)."""
    return _flat_record_msg("channel_sample", sample.to_data())


def channel_sample_from_msg(msg: Float64MultiArray) -> wire.ChannelSample:
    """``Float64MultiArray`` → channel sample; ValueError if it does not parse."""
    _check_flat_layout(msg, "channel_sample")
    return wire.ChannelSample.from_data(np.asarray(msg.data, dtype=np.float64))


def map_correction_to_msg(correction: wire.MapCorrection) -> Float64MultiArray:
    """Map correction → ``Float64MultiArray`` (``layout.dim = [map_correction(8)]``,
    :data:`gsrmr_common.wire.MAP_CORRECTION_FIELDS` order)."""
    return _flat_record_msg("map_correction", correction.to_data())


def map_correction_from_msg(msg: Float64MultiArray) -> wire.MapCorrection:
    """``Float64MultiArray`` → map correction; ValueError if it does not parse."""
    _check_flat_layout(msg, "map_correction")
    return wire.MapCorrection.from_data(np.asarray(msg.data, dtype=np.float64))


def mr_slot_info_to_msg(info: wire.MRSlotInfo) -> Float64MultiArray:
    """MR slot info → ``Float64MultiArray`` (``layout.dim = [mr_slot_info(6)]``: slot, source, a_m, b_m, theta_rad,
    content_time_s; see :class:`gsrmr_common.wire.MRSlotInfo`)."""
    return _flat_record_msg("mr_slot_info", info.to_data())


def mr_slot_info_from_msg(msg: Float64MultiArray) -> wire.MRSlotInfo:
    """``Float64MultiArray`` → MR slot info; ValueError if it does not parse."""
    _check_flat_layout(msg, "mr_slot_info")
    return wire.MRSlotInfo.from_data(np.asarray(msg.data, dtype=np.float64))


def image_to_msg(rgb: np.ndarray, stamp_ns: int, frame_id: str) -> Image:
    """H×W×3 ``uint8`` RGB → ``sensor_msgs/Image`` (``rgb8``, no row padding)."""
    img = np.asarray(rgb)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3 or 0 in img.shape:
        raise ValueError(f"image_to_msg: expected H×W×3 uint8 RGB, got {img.dtype} {img.shape}")
    return numpy_to_imgmsg(img, "rgb8", stamp=ns_to_stamp(stamp_ns), frame_id=frame_id)


def image_from_msg(msg: Image, *, max_pixels: int = wire.MAX_IMAGE_PIXELS) -> np.ndarray:
    """``sensor_msgs/Image`` → H×W×3 ``uint8`` RGB (a new array), as ``cv_bridge`` converts to ``rgb8``.

    Supports ``rgb8``, ``bgr8``, ``rgba8``, ``bgra8`` (alpha dropped), ``mono8`` (replicated to three
    channels), ``mono16`` (replicated and scaled to 8 bit, ``(v + 128) // 257``) and YUV 4:2:2 — ``yuv422``/``uyvy``
    (UYVY) and ``yuv422_yuy2``/``yuyv`` (YUYV), even widths, BT.601 video range as OpenCV converts it (what USB
    cameras send); the encoding name is matched case-insensitively, ``step`` may include row padding,
    ``is_bigendian`` is honoured. Raises
    :class:`ImageRejected` on any other encoding (``16UC1``/``32FC1`` hold plain numbers, which
    ``cv_bridge`` refuses to turn into colour), an empty or oversized image, ``step`` <
    width·channels·bytes, or ``len(data) != step·height``.
    """
    enc = msg.encoding.lower()
    if enc in _YUV422_ENCODINGS:
        return _yuv422_to_rgb(msg, max_pixels)
    if enc in _RGB_SOURCE_ENCODINGS and enc != msg.encoding:
        msg = Image(header=msg.header, height=msg.height, width=msg.width, encoding=enc,
                    is_bigendian=msg.is_bigendian, step=msg.step, data=msg.data)
    try:
        return imgmsg_to_numpy(msg, "rgb8", max_pixels=max_pixels)
    except ValueError as exc:
        raise ImageRejected(str(exc)) from exc


def _yuv422_to_rgb(msg: Image, max_pixels: int) -> np.ndarray:
    """A YUV 4:2:2 frame → RGB (OpenCV's BT.601 video-range conversion), as strict about its geometry as
    :func:`gsrmr_common.image_bridge.imgmsg_to_numpy` is about the others."""
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    if height * width > max_pixels:
        raise ImageRejected(f"image {width}×{height} exceeds {max_pixels} px")
    if len(msg.data) != step * height:
        raise ImageRejected(f"image data has {len(msg.data)} bytes, step·height = {step}·{height} = {step * height}")
    try:
        return decode_colour(msg, IMAGE_TYPE)
    except ImageDecodeError as exc:
        raise ImageRejected(str(exc)) from exc


def compressed_to_msg(jpeg_data: bytes, stamp_ns: int, frame_id: str) -> CompressedImage:
    """JPEG bytes → ``sensor_msgs/CompressedImage`` with ``format = wire.JPEG_FORMAT``."""
    msg = CompressedImage()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.format = wire.JPEG_FORMAT
    msg.data = bytes(jpeg_data)
    return msg


def compressed_from_msg(msg: CompressedImage, *, max_pixels: int = wire.MAX_IMAGE_PIXELS,
                        max_bytes: int = wire.MAX_COMPRESSED_BYTES,
                        expected_shape: tuple[int, int] | None = None) -> np.ndarray:
    """``CompressedImage`` → H×W×3 ``uint8`` RGB via :func:`gsrmr_common.jpeg.decode_jpeg`.

    ``format`` must name JPEG (``"jpeg"`` or ``"… jpeg compressed …"``; an empty format is JPEG by the
    image_transport convention). ``expected_shape`` is (height, width). Raises :class:`ImageRejected`.
    """
    fmt = msg.format.lower()
    if fmt and "jpeg" not in fmt and "jpg" not in fmt:
        raise ImageRejected(f"compressed image format {msg.format!r} is not JPEG")
    if len(msg.data) > max_bytes:  # before copying the payload
        raise ImageRejected(f"JPEG of {len(msg.data)} bytes exceeds the {max_bytes}-byte limit")
    return decode_jpeg(bytes(msg.data), max_pixels=max_pixels, max_bytes=max_bytes,
                       expected_shape=expected_shape)


# ------------------------------------------------------------------------------------- camera info

def camera_info_from_intrinsics(intrinsics: Intrinsics, stamp_ns: int, frame_id: str) -> CameraInfo:
    """Intrinsics → ``sensor_msgs/CameraInfo`` (K, P in the ROS integer-pixel-centre convention).

    ``distortion_model = "plumb_bob"`` with ``d`` = five zeros, ``r`` = identity, ``p = [K | 0]``
    (monocular), no binning, full-image ROI.
    """
    k = intrinsics.ros_k()
    msg = CameraInfo()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.width, msg.height = int(intrinsics.width), int(intrinsics.height)
    msg.distortion_model = "plumb_bob"
    msg.d = [0.0] * 5
    msg.k = k.reshape(-1).tolist()
    msg.r = np.eye(3).reshape(-1).tolist()
    msg.p = np.hstack([k, np.zeros((3, 1))]).reshape(-1).tolist()
    return msg


def intrinsics_from_camera_info(msg: CameraInfo, *, ignore_distortion: bool = False) -> Intrinsics:
    """``sensor_msgs/CameraInfo`` → :class:`Intrinsics` (principal point shifted +0.5 px).

    Uses ``k`` (the raw camera's matrix). Refuses non-zero distortion coefficients unless
    ``ignore_distortion`` (our pinhole model cannot represent them), a K with skew, and an
    uncalibrated (all-zero) K; raises ``ValueError``.
    """
    k = np.asarray(msg.k, dtype=np.float64).reshape(3, 3)
    if not np.any(k):
        raise ValueError("CameraInfo is uncalibrated (K is all zeros)")
    if k[0, 1] != 0.0 or k[1, 0] != 0.0 or k[2, 0] != 0.0 or k[2, 1] != 0.0 or k[2, 2] != 1.0:
        raise ValueError(f"CameraInfo K is not a zero-skew pinhole matrix: {k.tolist()}")
    if not ignore_distortion and np.any(np.asarray(msg.d, dtype=np.float64)):
        raise ValueError(f"CameraInfo has non-zero distortion {list(msg.d)} ({msg.distortion_model})")
    return Intrinsics.from_ros_k(k, int(msg.width), int(msg.height))


def intrinsics_or_problem(msg: CameraInfo) -> tuple[Intrinsics | None, str | None]:
    """:func:`intrinsics_from_camera_info`, or None and why the calibration is unusable (never raises)."""
    try:
        return intrinsics_from_camera_info(msg), None
    except ValueError as err:
        return None, str(err)
