"""``sensor_msgs/Image`` ↔ numpy with ``cv_bridge`` semantics, using ``cv_bridge`` when a ROS install has it.

:func:`imgmsg_to_numpy` and :func:`numpy_to_imgmsg`; :data:`BACKEND` names the backend in use (``"cv_bridge"`` or
``"gsrmr"``, same results either way). The backend probe, the supported encodings, the row layout on the wire and the
conversions: docs/architecture.md, "sensor_msgs/Image ↔ numpy". Imports message classes only (no rclpy node) and
numpy; OpenCV is not needed.
"""

from __future__ import annotations

from dataclasses import dataclass
import sys
from typing import Any

from builtin_interfaces.msg import Time
import numpy as np
from sensor_msgs.msg import Image

from gsrmr_common import wire

PASSTHROUGH = "passthrough"
HOST_IS_BIGENDIAN = sys.byteorder == "big"

# OpenCV's 8-bit RGB→grey fixed point (modules/imgproc/src/color.hpp): RY15, GY15, BY15, gray_shift.
_GRAY_R, _GRAY_G, _GRAY_B, _GRAY_SHIFT = 9798, 19235, 3735, 15


@dataclass(frozen=True)
class Encoding:
    """One supported ``sensor_msgs/Image`` encoding.

    ``layout`` names the channels in memory order (``"RGB"``, ``"BGRA"``, ``"L"`` = grey) for the
    colour/mono encodings, ``None`` for plain-number encodings (``16UC1``, ``32FC1``), which
    ``cv_bridge`` never colour-converts. ``bits`` is the bit depth of one channel.
    """

    name: str
    dtype: np.dtype
    channels: int
    layout: str | None
    bits: int

    @property
    def itemsize(self) -> int:
        """Bytes per channel element."""
        return self.dtype.itemsize

    def shape(self, height: int, width: int) -> tuple[int, ...]:
        """The numpy shape of a height×width image: H×W for one channel, H×W×C otherwise."""
        return (height, width) if self.channels == 1 else (height, width, self.channels)


ENCODINGS: dict[str, Encoding] = {e.name: e for e in (
    Encoding("rgb8", np.dtype(np.uint8), 3, "RGB", 8),
    Encoding("bgr8", np.dtype(np.uint8), 3, "BGR", 8),
    Encoding("rgba8", np.dtype(np.uint8), 4, "RGBA", 8),
    Encoding("bgra8", np.dtype(np.uint8), 4, "BGRA", 8),
    Encoding("mono8", np.dtype(np.uint8), 1, "L", 8),
    Encoding("mono16", np.dtype(np.uint16), 1, "L", 16),
    Encoding("16UC1", np.dtype(np.uint16), 1, None, 16),
    Encoding("32FC1", np.dtype(np.float32), 1, None, 32),
)}


def encoding_info(name: str) -> Encoding:
    """The :class:`Encoding` called ``name`` (case-sensitive, as in ROS); ``ValueError`` if unsupported."""
    try:
        return ENCODINGS[name]
    except KeyError:
        raise ValueError(f"unsupported image encoding {name!r} (supported: {', '.join(ENCODINGS)})") from None


def conversion_refusal(src: str, dst: str) -> str | None:
    """Why ``cv_bridge`` refuses to convert encoding ``src`` to ``dst``, or ``None`` if it converts.

    Mirrors ``getConversionCode`` for the supported encodings (both must be known).
    """
    s = encoding_info(src)
    if dst in (PASSTHROUGH, src):
        return None
    d = encoding_info(dst)
    if s.layout is None:
        if d.layout is not None:
            return f"{src} is not a colour or mono encoding but {dst} is; the conversion does not make sense"
        if s.channels != d.channels:
            return f"{src} and {dst} do not have the same number of channels"
        return None
    if d.layout is None and s.channels != d.channels:
        return f"{src} is a colour encoding but {dst} is not, so they must have the same number of channels"
    return None


# ------------------------------------------------------------------------------------------ backend

def _probe_cv_bridge() -> Any | None:
    """A working ``cv_bridge.CvBridge``, or ``None`` if it is absent or converts the probes wrongly.

    Probes (compact, native-endian messages): rgb8 passthrough, rgb8 → bgr8, rgb8 → mono8 (BT.601 grey),
    mono16 → mono8 (16 → 8 bit scaling) and the ``cv2_to_imgmsg`` direction. Catches every
    ``Exception``: PyPI's ROS 1 ``cv-bridge`` fails in assorted ways under ROS 2 and numpy 2.
    """
    try:
        from cv_bridge import CvBridge  # optional: only a ROS install has it

        bridge = CvBridge()
        rgb = np.array([[[255, 0, 0], [0, 255, 0]], [[0, 0, 255], [10, 20, 30]]], np.uint8)
        msg = bridge.cv2_to_imgmsg(rgb, encoding="rgb8")
        if not isinstance(msg, Image) or (msg.height, msg.width, msg.step, msg.encoding) != (2, 2, 6, "rgb8"):
            return None
        if bytes(msg.data) != rgb.tobytes():
            return None
        expect = {"passthrough": rgb, "bgr8": rgb[:, :, ::-1],
                  "mono8": np.array([[76, 150], [29, 18]], np.uint8)}
        for desired, want in expect.items():
            got = np.asarray(bridge.imgmsg_to_cv2(msg, desired_encoding=desired))
            if got.dtype != want.dtype or not np.array_equal(got, want):
                return None
        mono16 = np.array([[0, 128, 129], [385, 65406, 65535]], np.uint16)
        m16 = Image(height=2, width=3, encoding="mono16", is_bigendian=int(HOST_IS_BIGENDIAN), step=6,
                    data=mono16.tobytes())
        got = np.asarray(bridge.imgmsg_to_cv2(m16, desired_encoding="mono8"))
        if got.dtype != np.uint8 or not np.array_equal(got, [[0, 0, 1], [1, 254, 255]]):
            return None
        return bridge
    except Exception:  # any failure means "no usable cv_bridge"
        return None


_BRIDGE: Any | None = _probe_cv_bridge()
BACKEND: str = "cv_bridge" if _BRIDGE is not None else "gsrmr"


# --------------------------------------------------------------------------------------- msg → numpy

def imgmsg_to_numpy(msg: Image, desired_encoding: str = PASSTHROUGH, *,
                    max_pixels: int = wire.MAX_IMAGE_PIXELS) -> np.ndarray:
    """``sensor_msgs/Image`` → a new, writable, C-contiguous, native-endian numpy array.

    ``desired_encoding = "passthrough"`` (or the message's own encoding) returns the message's layout:
    H×W for one channel, H×W×C otherwise, dtype uint8/uint16/float32 as the encoding says; any other
    supported encoding converts as ``cv_bridge`` does (module docstring). Row padding (``step`` >
    width·channels·itemsize) is dropped and big-endian data (``is_bigendian``) is byte-swapped to the
    host's order, bit-exactly (NaN payloads survive).

    Raises ``ValueError`` on an unsupported encoding, a conversion ``cv_bridge`` refuses, an empty image,
    more than ``max_pixels`` pixels, ``step`` < width·channels·itemsize, ``step`` not a multiple of the
    element size, or ``len(data) != step·height``.
    """
    src = encoding_info(msg.encoding)
    dst = src if desired_encoding in (PASSTHROUGH, msg.encoding) else encoding_info(desired_encoding)
    reason = conversion_refusal(src.name, dst.name)
    if reason is not None:
        raise ValueError(f"cannot convert image encoding {src.name!r} to {dst.name!r}: {reason}")
    pixels = _unpack(msg, src, max_pixels)
    if dst == src:
        return pixels
    if _BRIDGE is not None:
        compact = _pack(pixels, src.name)
        out = np.array(_BRIDGE.imgmsg_to_cv2(compact, desired_encoding=dst.name), order="C", copy=True)
        shape = dst.shape(pixels.shape[0], pixels.shape[1])
        if out.dtype != dst.dtype or out.size != np.prod(shape):
            raise RuntimeError(f"cv_bridge converted {src.name} → {dst.name} to {out.dtype} {out.shape}, "
                               f"expected {dst.dtype} {shape}")
        return out.reshape(shape)
    return _convert(pixels, src, dst)


def _unpack(msg: Image, enc: Encoding, max_pixels: int) -> np.ndarray:
    """Validate ``msg``'s geometry and copy its pixels out in ``enc``'s native layout (no conversion)."""
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    if height < 1 or width < 1:
        raise ValueError(f"empty image {width}×{height}")
    if height * width > max_pixels:
        raise ValueError(f"image {width}×{height} exceeds {max_pixels} px")
    row_bytes = width * enc.channels * enc.itemsize
    if step < row_bytes:
        raise ValueError(f"image step {step} < width·channels·bytes = {width}·{enc.channels}·{enc.itemsize}"
                         f" = {row_bytes} for {enc.name}")
    if step % enc.itemsize:
        raise ValueError(f"image step {step} is not a multiple of the {enc.itemsize}-byte {enc.name} element")
    buf = np.frombuffer(msg.data, dtype=np.uint8)
    if buf.size != step * height:
        raise ValueError(f"image data has {buf.size} bytes, step·height = {step}·{height} = {step * height}")
    # (H, W·C, itemsize) bytes; reversing the last axis is an exact byte swap of every element.
    elems = buf.reshape(height, step)[:, :row_bytes].reshape(height, width * enc.channels, enc.itemsize)
    if enc.itemsize > 1 and bool(msg.is_bigendian) != HOST_IS_BIGENDIAN:
        elems = elems[:, :, ::-1]
    out = np.empty(elems.shape, np.uint8)
    out[...] = elems
    return out.view(enc.dtype).reshape(enc.shape(height, width))


# --------------------------------------------------------------------------------------- numpy → msg

def numpy_to_imgmsg(array: np.ndarray, encoding: str, *, stamp: Time | None = None, frame_id: str = "") -> Image:
    """numpy array → ``sensor_msgs/Image`` in ``encoding``, without row padding (step = W·C·itemsize).

    The array must already be in ``encoding``'s layout (``cv_bridge``'s ``cv2_to_imgmsg`` converts
    nothing either): H×W (or H×W×1) for one channel, H×W×C otherwise, dtype exactly as the encoding
    says. Bytes keep the array's byte order: a big-endian array (``>u2``, ``>f4``) gives
    ``is_bigendian = 1``, a native one the host's order. ``stamp`` / ``frame_id`` fill the header.
    Raises ``ValueError`` on an unsupported encoding or an array that does not fit it.
    """
    enc = encoding_info(encoding)
    arr = np.asarray(array)
    if arr.ndim == 3 and enc.channels == 1 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    shape_ok = arr.ndim == 2 if enc.channels == 1 else arr.ndim == 3 and arr.shape[2] == enc.channels
    dtype_ok = arr.dtype.kind == enc.dtype.kind and arr.dtype.itemsize == enc.itemsize
    if not (shape_ok and dtype_ok) or arr.size == 0:
        want = "×".join(["H", "W", *([str(enc.channels)] if enc.channels > 1 else [])])
        raise ValueError(f"encoding {encoding!r} needs a non-empty {want} {enc.dtype} array, "
                         f"got {arr.dtype} {arr.shape}")
    order = arr.dtype.byteorder
    big = enc.itemsize > 1 and (order == ">" or (order == "=" and HOST_IS_BIGENDIAN))
    if _BRIDGE is not None and big == HOST_IS_BIGENDIAN:
        msg = _BRIDGE.cv2_to_imgmsg(np.ascontiguousarray(arr), encoding=encoding)
    else:
        msg = _pack(arr, encoding, bigendian=big)
    if stamp is not None:
        msg.header.stamp = Time(sec=stamp.sec, nanosec=stamp.nanosec)
    msg.header.frame_id = frame_id
    return msg


def _pack(arr: np.ndarray, encoding: str, *, bigendian: bool = HOST_IS_BIGENDIAN) -> Image:
    """An unpadded ``Image`` holding ``arr``'s bytes as stored (``bigendian`` must describe them)."""
    height, width = int(arr.shape[0]), int(arr.shape[1])
    data = np.ascontiguousarray(arr).tobytes()
    return Image(height=height, width=width, encoding=encoding, is_bigendian=int(bigendian),
                 step=len(data) // height, data=data)


# ------------------------------------------------------------------------------ fallback conversion

def _convert(pixels: np.ndarray, src: Encoding, dst: Encoding) -> np.ndarray:
    """``cv_bridge``'s ``toCvCopyImpl`` for an allowed ``src`` → ``dst`` pair (see the module docstring):
    ``cvtColor`` at the source depth when the channel layouts differ, then ``convertTo`` to the target
    depth (8 ↔ 16 bit scaled)."""
    out = pixels
    if src.layout is not None and dst.layout is not None and src.layout != dst.layout:
        out = _cvt_color(out, src.layout, dst.layout)
    if out.dtype != dst.dtype:
        out = _convert_depth(out, src.bits, dst)
    return np.ascontiguousarray(out)


def _cvt_color(pixels: np.ndarray, src: str, dst: str) -> np.ndarray:
    """OpenCV ``cvtColor`` between channel layouts ``src`` and ``dst`` ("RGB", "BGRA", "L", …), same dtype.

    Grey → colour replicates; a missing alpha becomes the dtype's maximum; colour → grey is the BT.601
    15-bit fixed-point sum (8-bit only, the only depth with colour encodings here).
    """
    if src == "L":
        planes = {"R": pixels, "G": pixels, "B": pixels}
    else:
        planes = {name: pixels[:, :, i] for i, name in enumerate(src)}
    if dst == "L":
        if pixels.dtype != np.uint8:
            raise ValueError(f"colour → grey is only defined here for uint8, got {pixels.dtype}")
        r, g, b = (planes[c].astype(np.int32) for c in "RGB")
        grey = (_GRAY_R * r + _GRAY_G * g + _GRAY_B * b + (1 << (_GRAY_SHIFT - 1))) >> _GRAY_SHIFT
        return grey.astype(np.uint8)
    top = np.iinfo(pixels.dtype).max
    out = np.empty((*pixels.shape[:2], len(dst)), pixels.dtype)
    for i, name in enumerate(dst):
        out[:, :, i] = planes.get(name, top)
    return out


def _convert_depth(pixels: np.ndarray, src_bits: int, dst: Encoding) -> np.ndarray:
    """OpenCV ``convertTo`` as ``cv_bridge`` calls it: alpha 65535/255 for 8 → 16 bit, 255/65535 for
    16 → 8 bit (round to nearest), no scaling otherwise (float → int rounds half to even, saturates,
    NaN → 0)."""
    if src_bits == 8 and dst.bits == 16:
        return pixels.astype(np.uint16) * np.uint16(257)
    if src_bits == 16 and dst.bits == 8:
        return ((pixels.astype(np.uint32) + 128) // 257).astype(np.uint8)
    if dst.dtype.kind == "f":
        return pixels.astype(dst.dtype)
    info = np.iinfo(dst.dtype)
    if pixels.dtype.kind == "f":
        rounded = np.rint(np.where(np.isnan(pixels), 0.0, pixels))
        return np.clip(rounded, info.min, info.max).astype(dst.dtype)
    return np.clip(pixels, info.min, info.max).astype(dst.dtype)
