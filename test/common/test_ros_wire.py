"""Wire records ↔ ROS 2 messages (gsrmr_common.ros_wire): no running graph, messages serialised to CDR."""

from __future__ import annotations

import math

from builtin_interfaces.msg import Time
from geometry_msgs.msg import Vector3Stamped
from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Float64MultiArray

from gsrmr_common import ros_wire as rw
from gsrmr_common import wire
from gsrmr_common.camera import Intrinsics
from gsrmr_common.jpeg import ImageRejected, encode_jpeg
from gsrmr_common.slot_clock import SlotClock

CLOCK = SlotClock(0.1)
SLOT_NS = CLOCK.slot_len_ns


def cdr_round_trip(msg: object) -> object:
    """Serialise with rclpy's typesupport (proves the message is valid) and read it back."""
    data = serialize_message(msg)
    assert len(data) > 4
    return deserialize_message(data, type(msg))


@pytest.mark.parametrize("ns", [0, 1, 999_999_999, 1_000_000_000, 1_763_800_000_123_456_789, -1,
                                -1_500_000_000])
def test_stamp_round_trip(ns: int) -> None:
    stamp = rw.ns_to_stamp(ns)
    assert 0 <= stamp.nanosec < 1_000_000_000
    assert rw.stamp_to_ns(stamp) == ns
    assert rw.stamp_to_ns(cdr_round_trip(stamp)) == ns


def test_stamp_rejects_bad_values() -> None:
    with pytest.raises(ValueError, match="integer"):
        rw.ns_to_stamp(1.5)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="int32"):
        rw.ns_to_stamp(2**31 * 1_000_000_000)
    with pytest.raises(ValueError, match="nanosec"):
        rw.stamp_to_ns(Time(sec=1, nanosec=1_000_000_000))


@settings(max_examples=100, deadline=None)
@given(slot=st.integers(0, 2**31 * 9), a=st.floats(-1e3, 1e3), b=st.floats(-1e3, 1e3),
       theta=st.floats(-math.pi, math.pi))
def test_pose_key_round_trip(slot: int, a: float, b: float, theta: float) -> None:
    key = wire.PoseKey(slot, a, b, theta)
    msg = rw.pose_key_to_msg(key, CLOCK)
    assert msg.header.frame_id == "map"
    assert rw.stamp_to_ns(msg.header.stamp) == slot * SLOT_NS
    assert rw.pose_key_from_msg(cdr_round_trip(msg), CLOCK) == key


def test_pose_key_fields_and_frame() -> None:
    msg = rw.pose_key_to_msg(wire.PoseKey(42, 1.5, -2.0, 0.25), CLOCK)
    assert (msg.vector.x, msg.vector.y, msg.vector.z) == (1.5, -2.0, 0.25)
    # A stamp jittered by a few ms still names the same slot (the wire's nearest-slot rule).
    msg.header.stamp = rw.ns_to_stamp(42 * SLOT_NS + 3_000_000)
    assert rw.pose_key_from_msg(msg, CLOCK).slot == 42
    msg.header.frame_id = "odom"
    with pytest.raises(ValueError, match="map"):
        rw.pose_key_from_msg(msg, CLOCK)


def test_pose_key_nan_survives_for_is_valid() -> None:
    msg = Vector3Stamped()
    msg.header.frame_id = "map"
    msg.vector.x = float("nan")
    assert not rw.pose_key_from_msg(msg, CLOCK).is_valid()


def make_schedule(n: int = 5) -> wire.ScheduleMsg:
    x = (np.arange(n) % 2).astype(np.int8)
    return wire.ScheduleMsg(first_slot=17_638_000_001, slot_s=0.1, seq=9, x=x,
                            power_w=np.linspace(0.01, 0.2, n))


@pytest.mark.parametrize("n", [0, 1, 5, 300])
def test_schedule_round_trip(n: int) -> None:
    sched = make_schedule(n)
    msg = rw.schedule_to_msg(sched)
    assert [(d.label, d.size, d.stride) for d in msg.layout.dim] == [("meta", 4, 4), ("x", n, n),
                                                                      ("power_w", n, n)]
    assert len(msg.data) == 4 + 2 * n
    back = rw.schedule_from_msg(cdr_round_trip(msg))
    assert (back.first_slot, back.slot_s, back.seq) == (sched.first_slot, 0.1, 9)
    np.testing.assert_array_equal(back.x, sched.x)
    np.testing.assert_array_equal(back.power_w, sched.power_w)
    if n:
        assert back.lookup(sched.first_slot + n - 1) == (int(sched.x[-1]), float(sched.power_w[-1]))


def test_schedule_rejects_bad_layout_and_data() -> None:
    msg = rw.schedule_to_msg(make_schedule(3))
    msg.layout.dim[1].label = "images"
    with pytest.raises(ValueError, match="layout"):
        rw.schedule_from_msg(msg)
    msg = rw.schedule_to_msg(make_schedule(3))
    msg.layout.dim[2].size = 2
    with pytest.raises(ValueError, match="layout"):
        rw.schedule_from_msg(msg)
    msg = rw.schedule_to_msg(make_schedule(3))
    msg.layout.data_offset = 1
    with pytest.raises(ValueError, match="data_offset"):
        rw.schedule_from_msg(msg)
    msg = rw.schedule_to_msg(make_schedule(3))
    msg.data = [*msg.data[:-1]]
    with pytest.raises(ValueError):
        rw.schedule_from_msg(msg)
    bare = Float64MultiArray()
    bare.data = rw.schedule_to_msg(make_schedule(2)).data
    with pytest.raises(ValueError, match="layout"):
        rw.schedule_from_msg(bare)


RGB = np.random.default_rng(1).integers(0, 256, (5, 7, 3), dtype=np.uint8)


def test_image_round_trip_rgb8() -> None:
    msg = rw.image_to_msg(RGB, 123_456_789_012, "camera_optical")
    assert (msg.height, msg.width, msg.step, msg.encoding) == (5, 7, 21, "rgb8")
    assert msg.header.frame_id == "camera_optical" and rw.stamp_to_ns(msg.header.stamp) == 123_456_789_012
    back = rw.image_from_msg(cdr_round_trip(msg))
    np.testing.assert_array_equal(back, RGB)
    assert back.flags.writeable and back.flags.c_contiguous


def raw_msg(pixels: np.ndarray, encoding: str, pad: int = 0) -> Image:
    """An Image message built by hand (as another driver would), ``pad`` bytes of junk per row."""
    h, w = pixels.shape[:2]
    rows = pixels.reshape(h, -1)
    padded = np.concatenate([rows, np.full((h, pad), 0xEE, np.uint8)], axis=1)
    return Image(height=h, width=w, encoding=encoding, step=padded.shape[1], data=padded.tobytes())


@pytest.mark.parametrize("pad", [0, 3])
def test_image_from_bgr_mono_rgba_with_padding(pad: int) -> None:
    np.testing.assert_array_equal(rw.image_from_msg(raw_msg(RGB[:, :, ::-1].copy(), "bgr8", pad)), RGB)
    np.testing.assert_array_equal(rw.image_from_msg(raw_msg(RGB, "rgb8", pad)), RGB)
    rgba = np.concatenate([RGB, np.full((5, 7, 1), 9, np.uint8)], axis=2)
    np.testing.assert_array_equal(rw.image_from_msg(raw_msg(rgba, "rgba8", pad)), RGB)
    bgra = np.concatenate([RGB[:, :, ::-1], np.full((5, 7, 1), 9, np.uint8)], axis=2)
    np.testing.assert_array_equal(rw.image_from_msg(raw_msg(bgra, "bgra8", pad)), RGB)
    grey = RGB[:, :, 0].copy()
    out = rw.image_from_msg(cdr_round_trip(raw_msg(grey, "mono8", pad)))
    assert out.shape == (5, 7, 3)
    for c in range(3):
        np.testing.assert_array_equal(out[:, :, c], grey)


@pytest.mark.parametrize(("mutate", "reason"), [
    (lambda m: setattr(m, "encoding", "16UC1"), "encoding"),
    (lambda m: setattr(m, "step", 20), "step"),
    (lambda m: setattr(m, "height", 6), "bytes"),
    (lambda m: setattr(m, "data", m.data[:-1]), "bytes"),
    (lambda m: setattr(m, "width", 0), "empty"),
    (lambda m: setattr(m, "step", 24), "bytes"),
])
def test_image_from_msg_refuses_inconsistent(mutate: object, reason: str) -> None:
    msg = rw.image_to_msg(RGB, 0, "cam")
    mutate(msg)  # type: ignore[operator]
    with pytest.raises(ImageRejected, match=reason):
        rw.image_from_msg(msg)


def test_image_limits() -> None:
    with pytest.raises(ImageRejected, match="exceeds"):
        rw.image_from_msg(rw.image_to_msg(RGB, 0, "cam"), max_pixels=34)
    for bad in (RGB.astype(np.float32), RGB[:, :, 0], np.zeros((0, 3, 3), np.uint8)):
        with pytest.raises(ValueError):
            rw.image_to_msg(bad, 0, "cam")


def test_compressed_round_trip() -> None:
    img = np.zeros((24, 32, 3), np.uint8)
    img[:, :16] = (200, 40, 30)
    data = encode_jpeg(img, 90)
    msg = rw.compressed_to_msg(data, 5 * SLOT_NS, "camera_optical")
    assert msg.format == wire.JPEG_FORMAT == "rgb8; jpeg compressed bgr8"
    back_msg = cdr_round_trip(msg)
    assert bytes(back_msg.data) == data and rw.stamp_to_ns(back_msg.header.stamp) == 5 * SLOT_NS
    out = rw.compressed_from_msg(back_msg, expected_shape=(24, 32))
    assert np.abs(out.astype(int) - img).mean() < 3
    with pytest.raises(ImageRejected, match="expected"):
        rw.compressed_from_msg(back_msg, expected_shape=(32, 24))
    png = CompressedImage(format="rgb8; png compressed bgr8", data=data)
    with pytest.raises(ImageRejected, match="not JPEG"):
        rw.compressed_from_msg(png)


def test_camera_info_ros_convention_and_round_trip() -> None:
    intr = Intrinsics(fx=500.0, fy=510.0, cx=320.0, cy=240.0, width=640, height=480)
    msg = rw.camera_info_from_intrinsics(intr, 7 * SLOT_NS, "camera_optical")
    assert isinstance(msg, CameraInfo)
    assert (msg.width, msg.height, msg.distortion_model) == (640, 480, "plumb_bob")
    assert list(msg.d) == [0.0] * 5
    # ROS/OpenCV put pixel centres at integers: principal point is 0.5 px smaller than ours.
    np.testing.assert_array_equal(np.reshape(msg.k, (3, 3)),
                                  [[500.0, 0.0, 319.5], [0.0, 510.0, 239.5], [0.0, 0.0, 1.0]])
    np.testing.assert_array_equal(np.reshape(msg.p, (3, 4)),
                                  [[500.0, 0.0, 319.5, 0.0], [0.0, 510.0, 239.5, 0.0], [0.0, 0.0, 1.0, 0.0]])
    np.testing.assert_array_equal(np.reshape(msg.r, (3, 3)), np.eye(3))
    assert rw.intrinsics_from_camera_info(cdr_round_trip(msg)) == intr


def test_camera_info_refusals() -> None:
    with pytest.raises(ValueError, match="uncalibrated"):
        rw.intrinsics_from_camera_info(CameraInfo(width=4, height=4))
    msg = rw.camera_info_from_intrinsics(Intrinsics.from_fov(64, 48, 1.2), 0, "cam")
    msg.d = [0.1, 0.0, 0.0, 0.0, 0.0]
    with pytest.raises(ValueError, match="distortion"):
        rw.intrinsics_from_camera_info(msg)
    assert rw.intrinsics_from_camera_info(msg, ignore_distortion=True).width == 64
    msg.k[1] = 0.5
    with pytest.raises(ValueError, match="skew"):
        rw.intrinsics_from_camera_info(msg)


@settings(max_examples=300, deadline=None)
@given(height=st.integers(0, 6), width=st.integers(0, 6), step=st.integers(0, 30),
       encoding=st.sampled_from(["rgb8", "bgr8", "rgba8", "bgra8", "mono8", "RGB8", "yuv422", ""]),
       data=st.binary(max_size=200))
def test_fuzz_image_from_msg_rejects_or_returns_rgb(height: int, width: int, step: int, encoding: str,
                                                    data: bytes) -> None:
    msg = Image(height=height, width=width, step=step, encoding=encoding, data=data)
    try:
        out = rw.image_from_msg(msg)
    except ImageRejected:
        return
    channels = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1, "yuv422": 2}[encoding.lower()]
    assert len(data) == step * height and step >= width * channels
    assert out.shape == (height, width, 3) and out.dtype == np.uint8
    assert encoding != "yuv422" or width % 2 == 0


def test_image_from_msg_takes_yuv422_as_usb_cameras_send_it() -> None:
    """UYVY (``yuv422``, ``uyvy``) and YUYV (``yuv422_yuy2``, ``yuyv``) → RGB exactly as OpenCV converts them (the
    live robot as the dataset tool: real USB cameras send these); odd widths, short data and oversize refused."""
    import cv2

    rng = np.random.default_rng(0)
    uyvy = rng.integers(0, 256, (6, 8, 2), np.uint8)
    yuyv = uyvy[:, :, ::-1].copy()
    for encoding, packed, code in (("yuv422", uyvy, cv2.COLOR_YUV2RGB_UYVY), ("UYVY", uyvy, cv2.COLOR_YUV2RGB_UYVY),
                                   ("yuv422_yuy2", yuyv, cv2.COLOR_YUV2RGB_YUYV),
                                   ("yuyv", yuyv, cv2.COLOR_YUV2RGB_YUYV)):
        padded = np.zeros((6, 20), np.uint8)  # 4 bytes of row padding
        padded[:, :16] = packed.reshape(6, 16)
        msg = Image(height=6, width=8, step=20, encoding=encoding, data=padded.tobytes())
        out = rw.image_from_msg(msg)
        assert out.shape == (6, 8, 3) and np.array_equal(out, cv2.cvtColor(packed, code)), encoding
    with pytest.raises(ImageRejected, match="even width"):
        rw.image_from_msg(Image(height=2, width=3, step=6, encoding="yuv422", data=bytes(12)))
    with pytest.raises(ImageRejected, match="bytes"):
        rw.image_from_msg(Image(height=2, width=4, step=8, encoding="yuv422", data=bytes(15)))
    with pytest.raises(ImageRejected, match="exceeds"):
        rw.image_from_msg(Image(height=2, width=4, step=8, encoding="yuv422", data=bytes(16)), max_pixels=7)


# ------------------------------------------------------------------ ledger row, loss sample, wire names


def _row(**changes: float) -> wire.LedgerRow:
    fields = dict(slot=17_000_000_123, x=1, scheduled_power_w=0.02, bits_sent=64_000, gain=3e-7, power_w=0.021,
                  energy_j=0.0021, upload_all_bits=64_000, upload_all_energy_j=0.0021, frame_stamp_s=1.7e9 + 0.25,
                  held_back=1, uplink_rate_bps=2.5e6)
    fields.update(changes)
    return wire.LedgerRow(**fields)


def test_ledger_row_round_trips_through_cdr_with_its_layout():
    row = _row()
    msg = rw.ledger_to_msg(row)
    assert [(d.label, d.size) for d in msg.layout.dim] == [("ledger", len(wire.LEDGER_FIELDS))]
    assert rw.ledger_from_msg(cdr_round_trip(msg)) == row
    dead = _row(x=0, energy_j=math.inf, power_w=math.inf, frame_stamp_s=math.nan)  # a slot that carried nothing
    back = rw.ledger_from_msg(cdr_round_trip(rw.ledger_to_msg(dead)))
    assert math.isinf(back.energy_j) and math.isnan(back.frame_stamp_s) and back.slot == dead.slot
    assert rw.ledger_from_msg(Float64MultiArray(data=wire.ledger_row_to_data(row))) == row  # empty layout: fine


@pytest.mark.parametrize("data", [[1.0] * 9, [math.nan, *[1.0] * 9], [1.0, math.inf, *[1.0] * 8],
                                  [1.0, 1.0, 1.0, math.nan, *[1.0] * 6]])
def test_ledger_row_refuses_a_wrong_length_or_a_non_finite_count(data):
    with pytest.raises(ValueError, match="ledger row"):
        rw.ledger_from_msg(Float64MultiArray(data=data))


def test_loss_sample_round_trips_and_refuses_bad_data():
    sample = wire.LossSample(17_000_000_123, 1.25, -0.5, 3.0, 0.042)
    msg = rw.loss_sample_to_msg(sample)
    assert rw.loss_sample_from_msg(cdr_round_trip(msg)) == sample
    for bad in ([1.0, 2.0, 3.0, 4.0], [1.0, 2.0, 3.0, 4.0, math.nan], [1.0, 2.0, 3.0, 4.0, -0.1]):
        with pytest.raises(ValueError, match="loss sample"):
            rw.loss_sample_from_msg(Float64MultiArray(data=bad))
    wrong_layout = rw.loss_sample_to_msg(sample)
    wrong_layout.layout.dim[0].label = "ledger"
    with pytest.raises(ValueError, match="layout"):
        rw.loss_sample_from_msg(wrong_layout)


def test_wire_names_are_their_string_values():
    """CSV cells, diagnostics JSON and comparisons see the plain value, on Python 3.10 as on 3.11+."""
    import json

    assert str(wire.UplinkFault.LATE) == f"{wire.UplinkFault.LATE}" == "late" == wire.UplinkFault.LATE
    assert json.dumps({wire.UplinkFault.LATE: 1, "s": wire.RealSource.NONE}) == '{"late": 1, "s": "none"}'
    assert ";".join([wire.UplinkFault.LATE, wire.UplinkFault.WRONG_SIZE]) == "late;wrong_size"
    assert [d.value for d in wire.Delivery] == ["image", "key", "none"]
    assert len({f.value for f in wire.UplinkFault}) == len(wire.UplinkFault)
