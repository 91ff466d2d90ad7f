"""sensor_msgs/Image ↔ numpy (gsrmr_common.image_bridge): every encoding against arrays and bytes built by hand.

Messages are assembled byte by byte (explicit ``<``/``>`` dtypes or ``struct``, junk row padding), so a
wrong stride, a missed byte swap or a wrong channel order shows up as a wrong value. Conversion values
are worked out by hand from cv_bridge's rules (see the module docstring); one test also compares the
colour conversions with OpenCV itself (a project dependency through gsrmr_common.jpeg).
"""

from __future__ import annotations

import struct
import sys
import types

from builtin_interfaces.msg import Time
import cv2
from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Image

from gsrmr_common import image_bridge as ib
from gsrmr_common import ros_wire as rw
from gsrmr_common.jpeg import ImageRejected

JUNK = 0xEE
HOST_BIG = sys.byteorder == "big"

# Hand-written pixels, 2 rows × 3 columns, one per encoding. Multi-byte values have distinct high and
# low bytes, so a missing or spurious byte swap changes them.
RGB = np.array([[[255, 0, 0], [0, 255, 0], [0, 0, 255]],
                [[10, 20, 30], [200, 100, 50], [0, 1, 201]]], np.uint8)
HAND: dict[str, np.ndarray] = {
    "rgb8": RGB,
    "bgr8": np.array([[[1, 2, 3], [4, 5, 6], [7, 8, 9]], [[10, 11, 12], [13, 14, 15], [16, 17, 18]]], np.uint8),
    "rgba8": np.array([[[1, 2, 3, 4], [5, 6, 7, 8], [9, 10, 11, 12]],
                       [[13, 14, 15, 16], [17, 18, 19, 20], [21, 22, 23, 24]]], np.uint8),
    "bgra8": np.array([[[31, 32, 33, 34], [35, 36, 37, 38], [39, 40, 41, 42]],
                       [[43, 44, 45, 46], [47, 48, 49, 50], [51, 52, 53, 54]]], np.uint8),
    "mono8": np.array([[0, 1, 127], [128, 254, 255]], np.uint8),
    "mono16": np.array([[0x0102, 0xA0B0, 0xFFFF], [0x0001, 0x0100, 0x8001]], np.uint16),
    "16UC1": np.array([[0x1234, 0x00FF, 0xFF00], [7, 1000, 0xFEDC]], np.uint16),
    "32FC1": np.array([[1.5, -2.25, np.nan], [np.inf, -np.inf, 1e-3]], np.float32),
}
# numpy dtype code and element size per encoding (as written in the ROS encoding table)
CODE = {"rgb8": "u1", "bgr8": "u1", "rgba8": "u1", "bgra8": "u1", "mono8": "u1",
        "mono16": "u2", "16UC1": "u2", "32FC1": "f4"}


def hand_msg(pixels: np.ndarray, encoding: str, *, pad: int = 0, bigendian: bool = False) -> Image:
    """An Image as another driver would send it: rows written in the stated byte order, ``pad`` junk bytes
    after each row, ``step`` = row bytes + pad."""
    order = ">" if bigendian else "<"
    rows = [np.asarray(row, dtype=order + CODE[encoding]).tobytes() + bytes([JUNK]) * pad for row in pixels]
    return Image(height=len(rows), width=pixels.shape[1], encoding=encoding, is_bigendian=int(bigendian),
                 step=len(rows[0]), data=b"".join(rows))


def same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal shape, dtype and bytes (so NaN == NaN, payload included)."""
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


def test_backend_is_reported() -> None:
    assert ib.BACKEND in ("cv_bridge", "gsrmr")
    assert (ib.BACKEND == "cv_bridge") == (ib._BRIDGE is not None)


# ------------------------------------------------------------------------------------- passthrough

def pads_for(encoding: str) -> list[int]:
    """No padding, a whole element of padding, and (1-byte encodings) padding that is not a whole pixel."""
    size = int(CODE[encoding][1])
    return [0, size, 3 * size] + ([1] if size == 1 else [])


@pytest.mark.parametrize(("encoding", "pad", "bigendian"),
                         [(e, p, big) for e in HAND for p in pads_for(e) for big in (False, True)])
def test_passthrough_every_encoding(encoding: str, pad: int, bigendian: bool) -> None:
    msg = hand_msg(HAND[encoding], encoding, pad=pad, bigendian=bigendian)
    assert msg.step == HAND[encoding][0].size * int(CODE[encoding][1]) + pad
    out = ib.imgmsg_to_numpy(msg)
    assert out.dtype.isnative and out.flags.c_contiguous and out.flags.writeable
    assert same_bits(out, HAND[encoding])
    assert same_bits(ib.imgmsg_to_numpy(msg, encoding), HAND[encoding])  # desired == own encoding
    out[...] = 0  # a copy: the message is untouched
    assert same_bits(ib.imgmsg_to_numpy(msg), HAND[encoding])


def test_passthrough_multibyte_values_with_struct() -> None:
    # mono16 big-endian, 2 px per row + 2 junk bytes: 0x0102 is [1, 2] big-endian, 258 as a number.
    junk = bytes([JUNK, JUNK])
    be = Image(height=2, width=2, encoding="mono16", is_bigendian=1, step=6,
               data=struct.pack(">HH", 0x0102, 0xA0B0) + junk + struct.pack(">HH", 3, 0xFF00) + junk)
    np.testing.assert_array_equal(ib.imgmsg_to_numpy(be), [[258, 41136], [3, 65280]])
    le = Image(height=2, width=2, encoding="16UC1", is_bigendian=0, step=4,
               data=struct.pack("<HHHH", 0x0102, 0xA0B0, 3, 0xFF00))
    np.testing.assert_array_equal(ib.imgmsg_to_numpy(le), [[258, 41136], [3, 65280]])
    # 32FC1, one row of 3 floats + 4 junk bytes, both byte orders
    for fmt, flag in ((">fffI", 1), ("<fffI", 0)):
        msg = Image(height=1, width=3, encoding="32FC1", is_bigendian=flag, step=16,
                    data=struct.pack(fmt, 0.25, -1024.0, float("inf"), 0xDEADBEEF))
        np.testing.assert_array_equal(ib.imgmsg_to_numpy(msg), np.array([[0.25, -1024.0, np.inf]], np.float32))


def test_passthrough_keeps_nan_payloads_bit_exact() -> None:
    bits = np.array([[0x7FC00123, 0xFFC00000, 0x7F800000, 0x3F800000]], np.uint32)  # qNaN+payload, -NaN, inf, 1
    for big in (False, True):
        msg = Image(height=1, width=4, encoding="32FC1", is_bigendian=int(big), step=16,
                    data=bits.astype(">u4" if big else "<u4").tobytes())
        assert ib.imgmsg_to_numpy(msg).view(np.uint32).tolist() == bits.tolist()


# ---------------------------------------------------------------------------------- numpy → message

@pytest.mark.parametrize("encoding", list(HAND))
def test_round_trip_every_encoding(encoding: str) -> None:
    pixels = HAND[encoding]
    msg = ib.numpy_to_imgmsg(pixels, encoding, stamp=Time(sec=12, nanosec=345), frame_id="cam_optical")
    size = int(CODE[encoding][1])
    assert (msg.height, msg.width, msg.encoding) == (2, 3, encoding)
    assert msg.step == pixels[0].size * size  # no padding
    assert msg.is_bigendian == int(HOST_BIG)
    assert bytes(msg.data) == pixels.astype(("<", ">")[HOST_BIG] + CODE[encoding]).tobytes()
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id) == (12, 345, "cam_optical")
    assert same_bits(ib.imgmsg_to_numpy(msg), pixels)


@pytest.mark.parametrize("encoding", ["mono16", "16UC1", "32FC1"])
def test_big_endian_array_gives_big_endian_message(encoding: str) -> None:
    pixels = HAND[encoding].astype(">" + CODE[encoding])
    msg = ib.numpy_to_imgmsg(pixels, encoding)
    assert msg.is_bigendian == 1
    assert bytes(msg.data) == HAND[encoding].astype(">" + CODE[encoding]).tobytes()
    assert same_bits(ib.imgmsg_to_numpy(msg), HAND[encoding])


def test_round_trip_keeps_float_specials() -> None:
    bits = np.array([[0x7FC00123, 0xFFC00000], [0x7F800000, 0xFF800000]], np.uint32)  # NaN, -NaN, inf, -inf
    depth = bits.view(np.float32)
    back = ib.imgmsg_to_numpy(ib.numpy_to_imgmsg(depth, "32FC1"))
    assert back.view(np.uint32).tolist() == bits.tolist()


def test_single_channel_accepts_trailing_axis_and_non_contiguous_input() -> None:
    grey = HAND["mono8"]
    msg = ib.numpy_to_imgmsg(grey[:, :, None], "mono8")
    assert (msg.step, bytes(msg.data)) == (3, bytes([0, 1, 127, 128, 254, 255]))
    msg = ib.numpy_to_imgmsg(RGB[:, ::-1], "rgb8")  # negative stride
    assert same_bits(ib.imgmsg_to_numpy(msg), RGB[:, ::-1].copy())


def test_cdr_round_trip_padded_big_endian_mono16() -> None:
    msg = hand_msg(HAND["mono16"], "mono16", pad=4, bigendian=True)
    msg.header.frame_id = "camera_optical_frame"
    back = deserialize_message(serialize_message(msg), Image)
    assert (back.step, back.is_bigendian, bytes(back.data)) == (10, 1, bytes(msg.data))
    assert same_bits(ib.imgmsg_to_numpy(back), HAND["mono16"])
    # hand-checked bytes of row 0: 0x0102, 0xA0B0, 0xFFFF big-endian, then 4 junk bytes
    assert bytes(back.data[:10]) == bytes([0x01, 0x02, 0xA0, 0xB0, 0xFF, 0xFF, JUNK, JUNK, JUNK, JUNK])


# ------------------------------------------------------------------------------ colour conversions

# BT.601 grey of RGB in OpenCV's fixed point, (9798 R + 19235 G + 3735 B + 16384) >> 15, worked out by hand:
# (255,0,0) → 2514874>>15 = 76; (0,255,0) → 4921309>>15 = 150; (0,0,255) → 968809>>15 = 29;
# (10,20,30) → 611114>>15 = 18; (200,100,50) → 4089034>>15 = 124; (0,1,201) → 786354>>15 = 23
# (0.299·0 + 0.587·1 + 0.114·201 = 23.501 would round to 24: OpenCV's 15-bit weights give 23).
GREY_OF_RGB = np.array([[76, 150, 29], [18, 124, 23]], np.uint8)


@pytest.mark.parametrize("pad", [0, 1])
def test_colour_to_mono8(pad: int) -> None:
    alpha = np.full((2, 3, 1), 77, np.uint8)
    cases = {"rgb8": RGB, "bgr8": RGB[:, :, ::-1], "rgba8": np.concatenate([RGB, alpha], axis=2),
             "bgra8": np.concatenate([RGB[:, :, ::-1], alpha], axis=2)}
    for encoding, pixels in cases.items():
        out = ib.imgmsg_to_numpy(hand_msg(pixels, encoding, pad=pad), "mono8")
        assert out.dtype == np.uint8
        np.testing.assert_array_equal(out, GREY_OF_RGB, err_msg=encoding)


def test_colour_reorders_and_alpha() -> None:
    msg = hand_msg(RGB, "rgb8", pad=2)
    np.testing.assert_array_equal(ib.imgmsg_to_numpy(msg, "bgr8")[1], [[30, 20, 10], [50, 100, 200], [201, 1, 0]])
    np.testing.assert_array_equal(ib.imgmsg_to_numpy(msg, "rgba8")[1],
                                  [[10, 20, 30, 255], [200, 100, 50, 255], [0, 1, 201, 255]])
    np.testing.assert_array_equal(ib.imgmsg_to_numpy(msg, "bgra8")[0],
                                  [[0, 0, 255, 255], [0, 255, 0, 255], [255, 0, 0, 255]])
    bgra = hand_msg(HAND["bgra8"], "bgra8", pad=3)  # B, G, R, A = 31, 32, 33, 34 …
    np.testing.assert_array_equal(ib.imgmsg_to_numpy(bgra, "rgba8")[0, 0], [33, 32, 31, 34])  # alpha kept
    np.testing.assert_array_equal(ib.imgmsg_to_numpy(bgra, "rgb8")[1, 2], [53, 52, 51])
    np.testing.assert_array_equal(ib.imgmsg_to_numpy(bgra, "bgr8")[1, 2], [51, 52, 53])
    rgba = hand_msg(HAND["rgba8"], "rgba8")
    np.testing.assert_array_equal(ib.imgmsg_to_numpy(rgba, "bgr8")[0, 1], [7, 6, 5])
    np.testing.assert_array_equal(ib.imgmsg_to_numpy(rgba, "bgra8")[0, 1], [7, 6, 5, 8])
    bgr = hand_msg(HAND["bgr8"], "bgr8")
    np.testing.assert_array_equal(ib.imgmsg_to_numpy(bgr, "rgb8")[1, 0], [12, 11, 10])


def test_mono8_to_colour_replicates() -> None:
    msg = hand_msg(HAND["mono8"], "mono8", pad=1)
    np.testing.assert_array_equal(ib.imgmsg_to_numpy(msg, "rgb8")[1], [[128] * 3, [254] * 3, [255] * 3])
    np.testing.assert_array_equal(ib.imgmsg_to_numpy(msg, "bgr8")[0, 2], [127, 127, 127])
    np.testing.assert_array_equal(ib.imgmsg_to_numpy(msg, "rgba8")[0, 1], [1, 1, 1, 255])
    np.testing.assert_array_equal(ib.imgmsg_to_numpy(msg, "bgra8")[0, 0], [0, 0, 0, 255])


# 16 → 8 bit is convertTo with alpha 255/65535, rounded to nearest: v/257 → 0, 0.498, 0.502, 1.498,
# 1.502, 254.498, 254.502, 255
MONO16_RAMP = np.array([[0, 128, 129, 385], [386, 65406, 65407, 65535]], np.uint16)
MONO16_RAMP_AS_8 = np.array([[0, 0, 1, 1], [2, 254, 255, 255]], np.uint8)


@pytest.mark.parametrize("bigendian", [False, True])
def test_mono16_to_8_bit_is_scaled(bigendian: bool) -> None:
    msg = hand_msg(MONO16_RAMP, "mono16", pad=2, bigendian=bigendian)
    np.testing.assert_array_equal(ib.imgmsg_to_numpy(msg, "mono8"), MONO16_RAMP_AS_8)
    rgb = ib.imgmsg_to_numpy(msg, "rgb8")
    assert rgb.shape == (2, 4, 3) and rgb.dtype == np.uint8
    for c in range(3):
        np.testing.assert_array_equal(rgb[:, :, c], MONO16_RAMP_AS_8)
    np.testing.assert_array_equal(ib.imgmsg_to_numpy(msg, "bgra8")[1, 3], [255, 255, 255, 255])
    np.testing.assert_array_equal(ib.imgmsg_to_numpy(msg, "rgba8")[0, 2], [1, 1, 1, 255])


def test_8_to_16_bit_is_scaled_by_257() -> None:
    mono = hand_msg(np.array([[0, 1, 255]], np.uint8), "mono8")
    np.testing.assert_array_equal(ib.imgmsg_to_numpy(mono, "mono16"), [[0, 257, 65535]])
    np.testing.assert_array_equal(ib.imgmsg_to_numpy(mono, "16UC1"), [[0, 257, 65535]])  # cv_bridge scales here too
    assert ib.imgmsg_to_numpy(mono, "mono16").dtype == np.uint16
    rgb = hand_msg(RGB, "rgb8")
    np.testing.assert_array_equal(ib.imgmsg_to_numpy(rgb, "mono16"), GREY_OF_RGB.astype(np.int64) * 257)


def test_depth_encodings() -> None:
    mono8 = hand_msg(np.array([[0, 7, 255]], np.uint8), "mono8")
    out = ib.imgmsg_to_numpy(mono8, "32FC1")
    assert out.dtype == np.float32 and out.tolist() == [[0.0, 7.0, 255.0]]  # no scaling to float
    mono16 = hand_msg(np.array([[0, 1000, 65535]], np.uint16), "mono16", bigendian=True)
    assert ib.imgmsg_to_numpy(mono16, "16UC1").tolist() == [[0, 1000, 65535]]
    assert ib.imgmsg_to_numpy(mono16, "32FC1").tolist() == [[0.0, 1000.0, 65535.0]]
    depth_mm = hand_msg(np.array([[0, 1234, 65535]], np.uint16), "16UC1", pad=2)
    out = ib.imgmsg_to_numpy(depth_mm, "32FC1")
    assert out.dtype == np.float32 and out.tolist() == [[0.0, 1234.0, 65535.0]]
    depth_m = np.array([[np.nan, -1.0, 0.5, 1.5, 2.5, 65534.6, 70000.0, np.inf, -np.inf]], np.float32)
    out = ib.imgmsg_to_numpy(hand_msg(depth_m, "32FC1", bigendian=True), "16UC1")
    assert out.dtype == np.uint16
    assert out.tolist() == [[0, 0, 0, 2, 2, 65535, 65535, 65535, 0]]  # half to even, saturated, NaN → 0


@pytest.mark.parametrize(("src", "dst"), [
    ("16UC1", "rgb8"), ("16UC1", "mono8"), ("16UC1", "mono16"), ("16UC1", "bgra8"),
    ("32FC1", "rgb8"), ("32FC1", "mono8"), ("32FC1", "mono16"),
    ("rgb8", "16UC1"), ("bgr8", "32FC1"), ("rgba8", "16UC1"), ("bgra8", "32FC1"),
])
def test_conversions_cv_bridge_refuses(src: str, dst: str) -> None:
    msg = hand_msg(HAND[src], src)
    with pytest.raises(ValueError, match=f"{src}.*{dst}"):
        ib.imgmsg_to_numpy(msg, dst)
    assert ib.conversion_refusal(src, dst) is not None


def test_allowed_conversion_table() -> None:
    allowed = {(s, d) for s in ib.ENCODINGS for d in ib.ENCODINGS if ib.conversion_refusal(s, d) is None}
    colour = ["rgb8", "bgr8", "rgba8", "bgra8", "mono8", "mono16"]
    expected = {(s, d) for s in colour for d in colour}
    expected |= {(s, d) for s in ("mono8", "mono16") for d in ("16UC1", "32FC1")}
    expected |= {(s, d) for s in ("16UC1", "32FC1") for d in ("16UC1", "32FC1")}
    assert allowed == expected
    assert ib.conversion_refusal("16UC1", ib.PASSTHROUGH) is None


def test_colour_conversions_match_opencv() -> None:
    """Every colour pair against cv2.cvtColor, on random pixels (cv_bridge's toCvCopyImpl uses it)."""
    codes = {("rgb8", "mono8"): cv2.COLOR_RGB2GRAY, ("bgr8", "mono8"): cv2.COLOR_BGR2GRAY,
             ("rgba8", "mono8"): cv2.COLOR_RGBA2GRAY, ("bgra8", "mono8"): cv2.COLOR_BGRA2GRAY,
             ("mono8", "rgb8"): cv2.COLOR_GRAY2RGB, ("mono8", "bgr8"): cv2.COLOR_GRAY2BGR,
             ("mono8", "rgba8"): cv2.COLOR_GRAY2RGBA, ("mono8", "bgra8"): cv2.COLOR_GRAY2BGRA,
             ("rgb8", "bgr8"): cv2.COLOR_RGB2BGR, ("rgb8", "rgba8"): cv2.COLOR_RGB2RGBA,
             ("rgb8", "bgra8"): cv2.COLOR_RGB2BGRA, ("bgr8", "rgb8"): cv2.COLOR_BGR2RGB,
             ("bgr8", "rgba8"): cv2.COLOR_BGR2RGBA, ("bgr8", "bgra8"): cv2.COLOR_BGR2BGRA,
             ("rgba8", "rgb8"): cv2.COLOR_RGBA2RGB, ("rgba8", "bgr8"): cv2.COLOR_RGBA2BGR,
             ("rgba8", "bgra8"): cv2.COLOR_RGBA2BGRA, ("bgra8", "rgb8"): cv2.COLOR_BGRA2RGB,
             ("bgra8", "bgr8"): cv2.COLOR_BGRA2BGR, ("bgra8", "rgba8"): cv2.COLOR_BGRA2RGBA}
    rng = np.random.default_rng(7)
    for (src, dst), code in codes.items():
        pixels = rng.integers(0, 256, ib.ENCODINGS[src].shape(64, 97), dtype=np.uint8)
        out = ib.imgmsg_to_numpy(hand_msg(pixels, src, pad=5), dst)
        np.testing.assert_array_equal(out, cv2.cvtColor(pixels, code), err_msg=f"{src} → {dst}")
    ramp = np.arange(65536, dtype=np.uint16).reshape(256, 256)
    np.testing.assert_array_equal(ib.imgmsg_to_numpy(hand_msg(ramp, "mono16"), "mono8"),
                                  cv2.convertScaleAbs(ramp, alpha=255.0 / 65535.0))


# ----------------------------------------------------------------------------------------- refusals

@pytest.mark.parametrize(("mutate", "reason"), [
    (lambda m: setattr(m, "encoding", "yuv422"), "unsupported image encoding 'yuv422'"),
    (lambda m: setattr(m, "encoding", "MONO16"), "unsupported image encoding 'MONO16'"),  # ROS is case-sensitive
    (lambda m: setattr(m, "encoding", "8UC1"), "unsupported image encoding"),
    (lambda m: setattr(m, "step", 11), r"step 11 is not a multiple of the 2-byte mono16 element"),
    (lambda m: setattr(m, "step", 7), r"step 7 < width·channels·bytes = 4·1·2 = 8"),
    (lambda m: setattr(m, "step", 9), r"step 9 is not a multiple of the 2-byte mono16 element"),
    (lambda m: setattr(m, "data", bytes(m.data)[:-1]), r"19 bytes, step·height = 10·2 = 20"),
    (lambda m: setattr(m, "data", bytes(m.data) + b"\0\0"), r"22 bytes, step·height = 10·2 = 20"),
    (lambda m: setattr(m, "height", 3), r"20 bytes, step·height = 10·3 = 30"),
    (lambda m: setattr(m, "width", 0), "empty image"),
    (lambda m: setattr(m, "height", 0), "empty image"),
])
def test_inconsistent_message_refused(mutate: object, reason: str) -> None:
    msg = hand_msg(MONO16_RAMP, "mono16", pad=2)  # width 4, step 10, 20 bytes
    ib.imgmsg_to_numpy(msg)  # valid as built
    mutate(msg)  # type: ignore[operator]
    with pytest.raises(ValueError, match=reason):
        ib.imgmsg_to_numpy(msg)


def test_step_must_be_whole_float_elements() -> None:
    msg = hand_msg(np.zeros((2, 2), np.float32), "32FC1", pad=4)
    assert ib.imgmsg_to_numpy(msg).shape == (2, 2)
    msg.step, msg.data = 10, bytes(20)
    with pytest.raises(ValueError, match="multiple of the 4-byte 32FC1 element"):
        ib.imgmsg_to_numpy(msg)


def test_unknown_desired_encoding_and_max_pixels() -> None:
    msg = hand_msg(RGB, "rgb8")
    with pytest.raises(ValueError, match="unsupported image encoding 'hsv'"):
        ib.imgmsg_to_numpy(msg, "hsv")
    with pytest.raises(ValueError, match="exceeds 5 px"):
        ib.imgmsg_to_numpy(msg, max_pixels=5)
    assert ib.imgmsg_to_numpy(msg, max_pixels=6).shape == (2, 3, 3)


@pytest.mark.parametrize(("array", "encoding"), [
    (RGB.astype(np.float32), "rgb8"),
    (RGB[:, :, :2], "rgb8"),
    (RGB, "rgba8"),
    (RGB, "mono8"),
    (HAND["mono16"].astype(np.int16), "mono16"),
    (HAND["mono16"], "32FC1"),
    (HAND["32FC1"].astype(np.float64), "32FC1"),
    (np.zeros((0, 3), np.uint16), "16UC1"),
    (np.zeros((2, 3, 2), np.uint16), "16UC1"),
    (np.zeros(5, np.uint8), "mono8"),
])
def test_numpy_to_imgmsg_refuses_mismatched_arrays(array: np.ndarray, encoding: str) -> None:
    with pytest.raises(ValueError, match=f"encoding '{encoding}' needs"):
        ib.numpy_to_imgmsg(array, encoding)


def test_numpy_to_imgmsg_refuses_unknown_encoding() -> None:
    with pytest.raises(ValueError, match="unsupported image encoding '8UC3'"):
        ib.numpy_to_imgmsg(RGB, "8UC3")
    with pytest.raises(ValueError, match="unsupported image encoding 'passthrough'"):
        ib.numpy_to_imgmsg(RGB, "passthrough")


# ------------------------------------------------------------------------------- ros_wire delegation

@pytest.mark.parametrize("bigendian", [False, True])
def test_ros_wire_image_from_mono16(bigendian: bool) -> None:
    out = rw.image_from_msg(hand_msg(MONO16_RAMP, "mono16", pad=2, bigendian=bigendian))
    assert out.shape == (2, 4, 3) and out.dtype == np.uint8
    np.testing.assert_array_equal(out[:, :, 1], MONO16_RAMP_AS_8)


@pytest.mark.parametrize("encoding", ["16UC1", "32FC1"])
def test_ros_wire_refuses_depth_with_reason(encoding: str) -> None:
    with pytest.raises(ImageRejected, match=f"{encoding}.*rgb8.*not a colour"):
        rw.image_from_msg(hand_msg(HAND[encoding], encoding))


def test_ros_wire_keeps_case_insensitive_names() -> None:
    msg = hand_msg(RGB[:, :, ::-1], "bgr8", pad=1)
    msg.encoding = "BGR8"
    np.testing.assert_array_equal(rw.image_from_msg(msg), RGB)
    assert msg.encoding == "BGR8"  # the caller's message is not modified


# -------------------------------------------------------------------------------- property-based

@settings(max_examples=200, deadline=None)
@given(encoding=st.sampled_from(list(HAND)), height=st.integers(1, 5), width=st.integers(1, 5),
       pad_elems=st.integers(0, 3), bigendian=st.booleans(), seed=st.integers(0, 2**32 - 1))
def test_fuzz_passthrough_and_round_trip(encoding: str, height: int, width: int, pad_elems: int, bigendian: bool,
                                         seed: int) -> None:
    enc = ib.ENCODINGS[encoding]
    raw = np.random.default_rng(seed).integers(0, 256, (*enc.shape(height, width), enc.itemsize), dtype=np.uint8)
    pixels = raw.view(enc.dtype).reshape(enc.shape(height, width))  # any bit pattern, NaNs included
    msg = hand_msg(pixels, encoding, pad=pad_elems * enc.itemsize, bigendian=bigendian)
    assert same_bits(ib.imgmsg_to_numpy(msg), pixels)
    assert same_bits(ib.imgmsg_to_numpy(ib.numpy_to_imgmsg(pixels, encoding)), pixels)


# ------------------------------------------------------------------------------ cv_bridge probing

class _FakeBridge:
    """A stand-in CvBridge built on the fallback; ``scale16`` False mimics old cv_bridge (16 → 8 bit not
    scaled, the "@todo Should do scaling" of ROS 1's toCvCopyImpl)."""

    def __init__(self, scale16: bool = True) -> None:
        self.scale16 = scale16
        self.seen: list[Image] = []

    def cv2_to_imgmsg(self, cvim: np.ndarray, encoding: str = "passthrough") -> Image:
        return ib._pack(np.asarray(cvim), encoding)

    def imgmsg_to_cv2(self, img_msg: Image, desired_encoding: str = "passthrough") -> np.ndarray:
        self.seen.append(img_msg)
        src = ib.ENCODINGS[img_msg.encoding]
        pixels = ib._unpack(img_msg, src, 10**6)
        if desired_encoding in ("passthrough", img_msg.encoding):
            return pixels
        dst = ib.ENCODINGS[desired_encoding]
        if not self.scale16 and src.bits == 16 and dst.bits == 8:
            return np.clip(pixels, 0, 255).astype(np.uint8)
        return ib._convert(pixels, src, dst)


def _fake_module(make: object) -> types.ModuleType:
    module = types.ModuleType("cv_bridge")
    if make is not None:
        module.CvBridge = make  # type: ignore[attr-defined]
    return module


def test_probe_rejects_broken_cv_bridge(monkeypatch: pytest.MonkeyPatch) -> None:
    def raising() -> None:
        raise AttributeError("module 'numpy' has no attribute 'float'")  # how ROS 1 cv_bridge dies on numpy 2

    for make in (None, raising, lambda: _FakeBridge(scale16=False)):
        monkeypatch.setitem(sys.modules, "cv_bridge", _fake_module(make))
        assert ib._probe_cv_bridge() is None
    monkeypatch.setitem(sys.modules, "cv_bridge", None)  # not installed: import raises ImportError
    assert ib._probe_cv_bridge() is None


def test_probe_accepts_correct_bridge_and_conversions_go_through_it(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "cv_bridge", _fake_module(_FakeBridge))
    bridge = ib._probe_cv_bridge()
    assert isinstance(bridge, _FakeBridge)
    monkeypatch.setattr(ib, "_BRIDGE", bridge)
    bridge.seen.clear()
    msg = hand_msg(MONO16_RAMP, "mono16", pad=2, bigendian=not HOST_BIG)
    np.testing.assert_array_equal(ib.imgmsg_to_numpy(msg, "mono8"), MONO16_RAMP_AS_8)
    (handed,) = bridge.seen  # cv_bridge got a compact, host-order copy, not the padded foreign-order message
    assert (handed.step, handed.is_bigendian, handed.encoding) == (8, int(HOST_BIG), "mono16")
    assert same_bits(ib.imgmsg_to_numpy(msg), MONO16_RAMP)  # passthrough never needs cv_bridge
    assert len(bridge.seen) == 1
    out = ib.numpy_to_imgmsg(RGB, "rgb8", frame_id="cam")
    assert (out.step, out.header.frame_id, bytes(out.data)) == (9, "cam", RGB.tobytes())
