"""Stored ``sensor_msgs/Image`` and ``sensor_msgs/CompressedImage`` → numpy, for messages read from a bag.

The messages are rosbags' plain dataclasses (``msg.data`` a uint8 array), not rclpy messages: no ROS import.
:func:`decode_colour` gives H×W×3 ``uint8`` RGB, :func:`decode_depth_m` H×W ``float32`` metres (0: no depth); the
encodings each supports, and their units: docs/dataset_tool.md, "What it reads" (Encodings). A depth stream
(:func:`is_depth_message`) is an ``Image`` in ``16UC1``, ``mono16`` or ``32FC1``, or a ``CompressedImage`` whose
format names ``compressedDepth`` or a 16-bit or float source encoding.
"""

from __future__ import annotations

import struct
from typing import Any

import cv2
import numpy as np

IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_TYPE = "sensor_msgs/msg/CompressedImage"
NS_PER_S = 1_000_000_000
MM_PER_M = 1000.0

# encoding → (channels, bytes per channel); lower-case keys
_LAYOUTS = {"rgb8": (3, 1), "bgr8": (3, 1), "rgba8": (4, 1), "bgra8": (4, 1), "mono8": (1, 1), "8uc1": (1, 1),
            "8uc3": (3, 1), "yuv422": (2, 1), "uyvy": (2, 1), "yuv422_yuy2": (2, 1), "yuyv": (2, 1),
            "16uc1": (1, 2), "mono16": (1, 2), "32fc1": (1, 4)}
_TO_RGB = {"rgb8": None, "bgr8": cv2.COLOR_BGR2RGB, "8uc3": cv2.COLOR_BGR2RGB, "rgba8": cv2.COLOR_RGBA2RGB,
           "bgra8": cv2.COLOR_BGRA2RGB, "mono8": cv2.COLOR_GRAY2RGB, "8uc1": cv2.COLOR_GRAY2RGB,
           "yuv422": cv2.COLOR_YUV2RGB_UYVY, "uyvy": cv2.COLOR_YUV2RGB_UYVY,
           "yuv422_yuy2": cv2.COLOR_YUV2RGB_YUYV, "yuyv": cv2.COLOR_YUV2RGB_YUYV}
COLOUR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8", "mono8", "8UC1", "8UC3", "yuv422", "uyvy", "yuv422_yuy2",
                    "yuyv")
DEPTH_ENCODINGS = ("16UC1", "mono16", "32FC1")
_DEPTH_DTYPES = {"16uc1": "u2", "mono16": "u2", "32fc1": "f4"}
_COMPRESSED_DEPTH_HEADER = struct.Struct("<iff")  # compressionFormat (enum, int32), depthParam[2] (float32)


class ImageDecodeError(ValueError):
    """A message whose pixels cannot be decoded (the message says why)."""


def stamp_ns(stamp: Any) -> int:
    """A ``builtin_interfaces/Time`` (``sec``, ``nanosec``; ROS 1 times come as the same in rosbags) → ns."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def format_stamp(ns: int) -> str:
    """Integer nanoseconds → ``"123.000456789"`` seconds with all nine digits (exact)."""
    sign = "-" if ns < 0 else ""
    sec, nsec = divmod(abs(int(ns)), NS_PER_S)
    return f"{sign}{sec}.{nsec:09d}"


def _is_compressed(msgtype: str) -> bool:
    if msgtype == COMPRESSED_TYPE:
        return True
    if msgtype == IMAGE_TYPE:
        return False
    raise ImageDecodeError(f"{msgtype} is not an image message (sensor_msgs/Image or CompressedImage)")


def _format_parts(fmt: str) -> tuple[str, str]:
    """image_transport's ``"<source encoding>; <codec> compressed <encoding>"`` → (source encoding, the rest),
    lower-case; a bare ``"jpeg"`` has no source encoding."""
    text = str(fmt).strip().lower()
    if ";" in text:
        source, rest = text.split(";", 1)
        return source.strip(), rest.strip()
    return "", text


def is_depth_message(msg: Any, msgtype: str) -> bool:
    """Whether a stored image message holds depth (module docstring for the rule)."""
    if _is_compressed(msgtype):
        source, rest = _format_parts(msg.format)
        return "compresseddepth" in rest or source in ("16uc1", "mono16", "32fc1")
    return str(msg.encoding).lower() in _DEPTH_DTYPES


def _raw_pixels(msg: Any) -> tuple[np.ndarray, str]:
    """The pixels of an ``Image`` in their encoding's layout (H×W×C uint8, or H×W of the depth dtype)."""
    enc = str(msg.encoding).lower()
    if enc not in _LAYOUTS:
        raise ImageDecodeError(f"image encoding {msg.encoding!r} is not supported (colour: "
                               f"{', '.join(COLOUR_ENCODINGS)}; depth: {', '.join(DEPTH_ENCODINGS)})")
    channels, size = _LAYOUTS[enc]
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    row = width * channels * size
    if height < 1 or width < 1:
        raise ImageDecodeError(f"empty image {width}×{height}")
    if step < row:
        raise ImageDecodeError(f"step {step} < {row} bytes for a {width} px wide {msg.encoding} row")
    data = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    if data.size < step * height:
        raise ImageDecodeError(f"image data has {data.size} bytes, step·height = {step * height}")
    rows = data[: step * height].reshape(height, step)[:, :row]
    if size == 1:
        return np.ascontiguousarray(rows).reshape(height, width, channels), enc
    dtype = np.dtype(_DEPTH_DTYPES[enc]).newbyteorder(">" if int(msg.is_bigendian) else "<")
    return np.ascontiguousarray(rows).view(dtype).reshape(height, width).astype(dtype.newbyteorder("=")), enc


def _colour_order(rest: str) -> str:
    """'rgb' when the compressed encoding named after 'compressed' is RGB-ordered, else 'bgr'."""
    after = rest.split("compressed", 1)[1].strip() if "compressed" in rest else ""
    return "rgb" if after.startswith("rgb") else "bgr"


def _imdecode(data: Any, what: str) -> np.ndarray:
    buf = np.asarray(data, dtype=np.uint8).reshape(-1)
    if buf.size == 0:
        raise ImageDecodeError(f"{what}: no data")
    out = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    if out is None:
        raise ImageDecodeError(f"{what}: not a JPEG or PNG OpenCV can decode ({buf.size} bytes)")
    return out


def decode_colour(msg: Any, msgtype: str) -> np.ndarray:
    """A stored colour image → H×W×3 ``uint8`` RGB (module docstring for the encodings)."""
    if _is_compressed(msgtype):
        _source, rest = _format_parts(msg.format)
        if "compresseddepth" in rest:
            raise ImageDecodeError(f"compressed format {msg.format!r} is depth, not colour")
        img = _imdecode(msg.data, f"compressed image ({msg.format!r})")
        if img.dtype == np.uint16:
            img = ((img.astype(np.uint32) + 128) // 257).astype(np.uint8)
        if img.dtype != np.uint8:
            raise ImageDecodeError(f"compressed image decodes to {img.dtype}, not 8-bit colour")
        if img.ndim == 2:
            return cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
        rgb_order = _colour_order(rest) == "rgb"
        if img.shape[2] == 4:
            return np.ascontiguousarray(img[:, :, :3]) if rgb_order else cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
        return img if rgb_order else cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    pixels, enc = _raw_pixels(msg)
    if enc not in _TO_RGB:
        raise ImageDecodeError(f"image encoding {msg.encoding!r} is depth, not colour")
    if enc in ("yuv422", "uyvy", "yuv422_yuy2", "yuyv") and pixels.shape[1] % 2:
        raise ImageDecodeError(f"{msg.encoding} needs an even width, got {pixels.shape[1]}")
    code = _TO_RGB[enc]
    if code is None:
        return pixels
    src = pixels[:, :, 0] if pixels.shape[2] == 1 else pixels
    return cv2.cvtColor(src, code)


def _clean_metres(depth: np.ndarray) -> np.ndarray:
    out = np.asarray(depth, dtype=np.float32)
    return np.where(np.isfinite(out) & (out > 0.0), out, np.float32(0.0)).astype(np.float32)


def decode_depth_m(msg: Any, msgtype: str) -> np.ndarray:
    """A stored depth image → H×W ``float32`` metres, 0 where there is no depth (module docstring)."""
    if not _is_compressed(msgtype):
        pixels, enc = _raw_pixels(msg)
        if enc not in _DEPTH_DTYPES:
            raise ImageDecodeError(f"image encoding {msg.encoding!r} is not depth ({', '.join(DEPTH_ENCODINGS)})")
        if enc == "32fc1":
            return _clean_metres(pixels)
        return _clean_metres(pixels.astype(np.float32) / np.float32(MM_PER_M))
    source, rest = _format_parts(msg.format)
    data = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    if "compresseddepth" in rest:
        if "rvl" in rest:
            raise ImageDecodeError(f"compressed depth format {msg.format!r} (RVL) is not supported: record the raw "
                                   "depth Image, or compressedDepth with png")
        if data.size <= _COMPRESSED_DEPTH_HEADER.size:
            raise ImageDecodeError(f"compressedDepth message of {data.size} bytes has no image after its header")
        _fmt, quant_a, quant_b = _COMPRESSED_DEPTH_HEADER.unpack(data[: _COMPRESSED_DEPTH_HEADER.size].tobytes())
        img = _imdecode(data[_COMPRESSED_DEPTH_HEADER.size:], f"compressedDepth ({msg.format!r})")
        if img.dtype != np.uint16 or img.ndim != 2:
            raise ImageDecodeError(f"compressedDepth image decodes to {img.dtype} {img.shape}, not 16-bit grey")
        if source == "32fc1":
            inv = img.astype(np.float32)
            with np.errstate(divide="ignore", invalid="ignore"):
                depth = np.where(img > 0, np.float32(quant_a) / (inv - np.float32(quant_b)), 0.0)
            return _clean_metres(depth)
        return _clean_metres(img.astype(np.float32) / np.float32(MM_PER_M))
    img = _imdecode(data, f"compressed depth ({msg.format!r})")
    if img.dtype != np.uint16 or img.ndim != 2:
        raise ImageDecodeError(f"compressed depth ({msg.format!r}) decodes to {img.dtype} {img.shape}, not 16-bit "
                               "millimetres")
    return _clean_metres(img.astype(np.float32) / np.float32(MM_PER_M))


def image_size(msg: Any, msgtype: str) -> tuple[int, int] | None:
    """(width, height) an ``Image`` declares; ``None`` for a compressed one (known only once decoded)."""
    if _is_compressed(msgtype):
        return None
    return int(msg.width), int(msg.height)
