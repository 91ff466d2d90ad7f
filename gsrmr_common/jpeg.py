"""JPEG encoding, header inspection and guarded decoding (pure: numpy + OpenCV, no rclpy).

An upload must never crash the server or make it allocate a huge buffer, so :func:`decode_jpeg` checks the compressed
size, then the frame header's claimed size (:func:`jpeg_header`, before OpenCV sees a byte), then the structure of
every segment up to EOI (:func:`check_jpeg_structure`: truncation and most header corruption, which libjpeg only
warns about and pads with grey), and only then decodes (EXIF orientation ignored: the pixel grid is what the SOF
says). Every refusal is an :class:`ImageRejected`. What no decoder can catch (JPEG has no checksum):
docs/reliability.md, "The fault relay". Images are H×W×3 ``uint8`` RGB; the JPEG holds BGR-ordered components as
OpenCV writes them, hence :data:`gsrmr_common.wire.JPEG_FORMAT`.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from gsrmr_common import wire

# Start-of-frame markers that carry the image size: C0–C3, C5–C7, C9–CB, CD–CF
# (C4 = DHT, C8 = JPG extension, CC = DAC are not frame headers).
_SOF_MARKERS = frozenset({0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF})
# Markers without a length field: TEM and RST0–RST7 (SOI/EOI handled explicitly).
_STANDALONE = frozenset({0x01, *range(0xD0, 0xD8)})
_SOI, _EOI, _SOS = 0xD8, 0xD9, 0xDA


class ImageRejected(ValueError):  # noqa: N818 - name fixed by the node suite's API
    """An uploaded image was refused (too big, truncated, corrupt, wrong size or channel count)."""


def encode_jpeg(rgb: np.ndarray, quality: int, *, progressive: bool = False) -> bytes:
    """Encode an H×W×3 RGB image as JPEG bytes (4:2:0 chroma, OpenCV/libjpeg defaults).

    ``rgb`` is ``uint8`` (0–255) or floating point in [0, 1] (clipped, then rounded to 8 bits).
    ``quality`` is the libjpeg quality factor 1..100. Raises ``ValueError`` on bad input.
    """
    img = np.asarray(rgb)
    if img.ndim != 3 or img.shape[2] != 3 or img.shape[0] < 1 or img.shape[1] < 1:
        raise ValueError(f"encode_jpeg: expected an H×W×3 RGB image, got shape {img.shape}")
    if isinstance(quality, bool) or int(quality) != quality or not 1 <= quality <= 100:
        raise ValueError(f"encode_jpeg: quality must be an integer in 1..100, got {quality!r}")
    if img.dtype == np.uint8:
        u8 = img
    elif np.issubdtype(img.dtype, np.floating):
        if not np.all(np.isfinite(img)):
            raise ValueError("encode_jpeg: float image contains NaN or inf")
        u8 = np.rint(np.clip(img, 0.0, 1.0) * 255.0).astype(np.uint8)
    else:
        raise ValueError(f"encode_jpeg: dtype must be uint8 or float in [0, 1], got {img.dtype}")
    params = [cv2.IMWRITE_JPEG_QUALITY, int(quality), cv2.IMWRITE_JPEG_PROGRESSIVE, int(progressive)]
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(u8[:, :, ::-1]), params)
    if not ok:  # pragma: no cover - OpenCV only fails here on allocation errors
        raise ValueError("encode_jpeg: cv2.imencode failed")
    return buf.tobytes()


def _next_marker(data: bytes, pos: int) -> tuple[int, int]:
    """At ``data[pos]`` expect 0xFF (plus optional 0xFF fill bytes) and a marker code.

    Returns ``(marker, position after the marker code)``.
    """
    n = len(data)
    if pos >= n:
        raise ImageRejected("truncated JPEG: no marker where one was expected")
    if data[pos] != 0xFF:
        raise ImageRejected(f"corrupt JPEG: expected a marker at byte {pos}, found 0x{data[pos]:02X}")
    while pos < n and data[pos] == 0xFF:  # fill bytes (B.1.1.2) may precede any marker
        pos += 1
    if pos >= n:
        raise ImageRejected("truncated JPEG: data ends inside marker fill bytes")
    marker = data[pos]
    if marker == 0x00:
        raise ImageRejected(f"corrupt JPEG: stuffed byte 0xFF00 outside entropy-coded data at byte {pos}")
    return marker, pos + 1


def _segment_end(data: bytes, pos: int, marker: int) -> int:
    """End (exclusive) of the marker segment whose 2-byte length field starts at ``pos``."""
    if pos + 2 > len(data):
        raise ImageRejected(f"truncated JPEG: length field of marker 0x{marker:02X} missing")
    length = (data[pos] << 8) | data[pos + 1]
    if length < 2:
        raise ImageRejected(f"corrupt JPEG: marker 0x{marker:02X} has length {length} < 2")
    end = pos + length
    if end > len(data):
        raise ImageRejected(f"truncated JPEG: marker 0x{marker:02X} segment runs past the end of data")
    return end


@dataclass(frozen=True)
class JpegHeader:
    """What a JPEG frame header (SOF segment) claims, read without decoding."""

    width: int  # pixels
    height: int  # pixels
    components: int  # 1 = grey, 3 = colour (YCbCr), 4 = CMYK/YCCK
    precision_bits: int  # sample precision, 8 for ordinary JPEG
    sof_marker: int  # 0xC0 baseline, 0xC1 extended, 0xC2 progressive, …


def _parse_sof(data: bytes, pos: int, end: int, marker: int) -> JpegHeader:
    """Frame header from a SOF segment payload starting at ``pos``."""
    if end - pos < 6:
        raise ImageRejected(f"corrupt JPEG: SOF 0x{marker:02X} segment too short")
    height = (data[pos + 1] << 8) | data[pos + 2]
    width = (data[pos + 3] << 8) | data[pos + 4]
    components = data[pos + 5]
    if end - pos < 6 + 3 * components:
        raise ImageRejected("corrupt JPEG: SOF shorter than its component list")
    if width == 0 or height == 0:
        raise ImageRejected(f"JPEG frame header claims {width}×{height} (DNL-defined height unsupported)")
    if components == 0:
        raise ImageRejected("corrupt JPEG: frame header declares 0 components")
    return JpegHeader(width, height, components, data[pos], marker)


def jpeg_dimensions(data: bytes) -> tuple[int, int, int]:
    """``(width, height, components)`` from a JPEG's frame header, without decoding any pixels.

    See :func:`jpeg_header`; raises :class:`ImageRejected`.
    """
    header = jpeg_header(data)
    return header.width, header.height, header.components


def jpeg_header(data: bytes) -> JpegHeader:
    """The frame header of a JPEG, without decoding any pixels.

    Walks SOI, then marker segments (skipping fill bytes and standalone markers) until the first SOF
    (baseline C0, extended C1, progressive C2, lossless/arithmetic variants). Raises
    :class:`ImageRejected` if the data is not a JPEG, is truncated before the frame header, or reaches
    a scan or EOI before any frame header.
    """
    data = bytes(data)
    if len(data) < 4 or data[0] != 0xFF or data[1] != _SOI:
        raise ImageRejected("not a JPEG: missing SOI marker 0xFFD8")
    pos = 2
    while True:
        marker, pos = _next_marker(data, pos)
        if marker in _STANDALONE:
            continue
        if marker in (_SOI, _EOI, _SOS):
            raise ImageRejected(f"corrupt JPEG: marker 0x{marker:02X} before any frame header")
        end = _segment_end(data, pos, marker)
        if marker in _SOF_MARKERS:
            return _parse_sof(data, pos + 2, end, marker)
        pos = end


def _skip_entropy_coded(data: bytes, pos: int) -> int:
    """Position of the first real marker (0xFF not followed by 0x00/RSTn/0xFF) after entropy data."""
    n = len(data)
    while True:
        pos = data.find(b"\xff", pos)
        if pos < 0 or pos + 1 >= n:
            raise ImageRejected("truncated JPEG: scan data ends without EOI")
        nxt = data[pos + 1]
        if nxt == 0x00 or 0xD0 <= nxt <= 0xD7:  # stuffed 0xFF or restart marker: still in the scan
            pos += 2
        elif nxt == 0xFF:  # fill byte before a marker
            pos += 1
        else:
            return pos


def check_jpeg_structure(data: bytes) -> None:
    """Walk every segment from SOI to EOI; raise :class:`ImageRejected` on truncation or corruption.

    Checks: a frame header precedes the first scan, every segment length fits, each scan is followed
    by a marker, and the data ends with EOI (nothing but zero padding after it). This does not decode
    pixels (entropy-coded data is skipped with ``bytes.find``).
    """
    data = bytes(data)
    if len(data) < 4 or data[0] != 0xFF or data[1] != _SOI:
        raise ImageRejected("not a JPEG: missing SOI marker 0xFFD8")
    pos, seen_sof, seen_sos = 2, False, False
    while True:
        marker, pos = _next_marker(data, pos)
        if marker == _EOI:
            if not seen_sos:
                raise ImageRejected("corrupt JPEG: EOI before any scan")
            if data[pos:].strip(b"\x00"):
                raise ImageRejected(f"corrupt JPEG: {len(data) - pos} unexpected bytes after EOI")
            return
        if marker in _STANDALONE:
            continue
        if marker == _SOI:
            raise ImageRejected("corrupt JPEG: second SOI marker")
        end = _segment_end(data, pos, marker)
        if marker in _SOF_MARKERS:
            if seen_sof:
                raise ImageRejected("corrupt JPEG: more than one frame header")
            _parse_sof(data, pos + 2, end, marker)
            seen_sof = True
            pos = end
        elif marker == _SOS:
            if not seen_sof:
                raise ImageRejected("corrupt JPEG: scan before frame header")
            seen_sos = True
            pos = _skip_entropy_coded(data, end)
        else:
            pos = end


def decode_jpeg(data: bytes, *, max_pixels: int = wire.MAX_IMAGE_PIXELS,
                max_bytes: int = wire.MAX_COMPRESSED_BYTES,
                expected_shape: tuple[int, int] | None = None) -> np.ndarray:
    """Decode an uploaded JPEG to an H×W×3 ``uint8`` RGB array, refusing anything suspicious.

    ``expected_shape`` is ``(height, width)`` in pixels (numpy order); when given, any other size is
    refused. The frame-header size is checked against ``max_pixels`` (width·height) and
    ``expected_shape`` *before* any pixel is decoded, so a forged header claiming 20000×20000 costs
    microseconds. Only 3-component (colour) JPEGs are accepted. Raises :class:`ImageRejected`.
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ImageRejected(f"JPEG data must be bytes, got {type(data).__name__}")
    data = bytes(data)
    if len(data) > max_bytes:
        raise ImageRejected(f"JPEG of {len(data)} bytes exceeds the {max_bytes}-byte limit")
    header = jpeg_header(data)
    width, height, components = header.width, header.height, header.components
    if width * height > max_pixels:
        raise ImageRejected(f"JPEG claims {width}×{height} = {width * height} px > limit {max_pixels} px")
    if expected_shape is not None and (height, width) != tuple(expected_shape):
        raise ImageRejected(f"JPEG is {width}×{height} (W×H), expected "
                            f"{expected_shape[1]}×{expected_shape[0]}")
    if components != 3:
        raise ImageRejected(f"JPEG has {components} components, expected 3 (colour)")
    if header.precision_bits != 8:
        raise ImageRejected(f"JPEG has {header.precision_bits}-bit samples, expected 8")
    check_jpeg_structure(data)
    try:
        bgr = cv2.imdecode(np.frombuffer(data, dtype=np.uint8),
                           cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    except cv2.error as exc:  # pragma: no cover - imdecode reports failure by returning None
        raise ImageRejected(f"JPEG decoder error: {exc}") from exc
    if bgr is None:
        raise ImageRejected("corrupt JPEG: OpenCV could not decode it")
    if bgr.shape != (height, width, 3):
        raise ImageRejected(f"decoded image has shape {bgr.shape}, header said {(height, width, 3)}")
    return np.ascontiguousarray(bgr[:, :, ::-1])
