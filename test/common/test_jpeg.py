"""JPEG encode / header parse / guarded decode (gsrmr_common.jpeg), no ROS needed."""

from __future__ import annotations

import itertools
import struct

import cv2
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
import numpy as np
import pytest

from gsrmr_common import jpeg, wire
from gsrmr_common.jpeg import (
    ImageRejected,
    check_jpeg_structure,
    decode_jpeg,
    encode_jpeg,
    jpeg_dimensions,
    jpeg_header,
)
from gsrmr_common.metrics import psnr


def scene(height: int = 96, width: int = 128, seed: int = 0) -> np.ndarray:
    """A natural-ish RGB test image: smooth gradients, a few hard edges and mild texture (uint8)."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:height, 0:width] / np.array([height, width]).reshape(2, 1, 1)
    img = np.stack([0.2 + 0.6 * u, 0.3 + 0.4 * v, 0.5 + 0.3 * np.sin(6 * u + 3 * v)], axis=-1)
    img[height // 4: height // 2, width // 5: width // 2] = (0.9, 0.2, 0.1)
    img[(u - 0.7) ** 2 + (v - 0.6) ** 2 < 0.02] = (0.1, 0.1, 0.8)
    img += 0.02 * rng.standard_normal(img.shape)
    return np.rint(np.clip(img, 0, 1) * 255).astype(np.uint8)


def sof_offset(data: bytes) -> int:
    """Offset of the first SOF0/SOF2 marker (test helper: plain byte search is fine for cv2 output)."""
    offsets = [data.find(m) for m in (b"\xff\xc0", b"\xff\xc2")]
    return min(o for o in offsets if o >= 0)


def with_size(data: bytes, width: int, height: int) -> bytes:
    """A copy of ``data`` whose frame header claims ``width``×``height``."""
    at = sof_offset(data) + 5  # FF Cn, length(2), precision(1), then height, width
    return data[:at] + struct.pack(">HH", height, width) + data[at + 4:]


IMG = scene()
BASELINE = encode_jpeg(IMG, 75)
PROGRESSIVE = encode_jpeg(IMG, 75, progressive=True)


def test_round_trip_close_to_original() -> None:
    out = decode_jpeg(BASELINE)
    assert out.shape == IMG.shape and out.dtype == np.uint8
    assert psnr(out / 255.0, IMG / 255.0) > 27.0
    # Channel order survives: the red rectangle is still red after the BGR detour through OpenCV.
    patch = out[30:40, 40:50].reshape(-1, 3).mean(axis=0)
    assert patch[0] > 180 and patch[1] < 90 and patch[2] < 90


def test_size_and_fidelity_increase_with_quality() -> None:
    qualities = [5, 20, 40, 60, 80, 95, 100]
    sizes, psnrs = [], []
    for q in qualities:
        data = encode_jpeg(IMG, q)
        sizes.append(len(data))
        psnrs.append(psnr(decode_jpeg(data) / 255.0, IMG / 255.0))
    assert all(a < b for a, b in itertools.pairwise(sizes)), sizes
    assert all(a < b for a, b in itertools.pairwise(psnrs)), psnrs
    assert sizes[-1] > 4 * sizes[0]


def test_float_input_matches_uint8() -> None:
    assert encode_jpeg(IMG / 255.0, 60) == encode_jpeg(IMG, 60)
    assert encode_jpeg(np.full((8, 8, 3), 2.0), 60) == encode_jpeg(np.full((8, 8, 3), 255, np.uint8), 60)


@pytest.mark.parametrize(("rgb", "quality"), [
    (np.zeros((4, 4)), 50), (np.zeros((4, 4, 4), np.uint8), 50), (np.zeros((0, 4, 3), np.uint8), 50),
    (np.zeros((4, 4, 3), np.int32), 50), (np.full((4, 4, 3), np.nan), 50),
    (IMG, 0), (IMG, 101), (IMG, 50.5), (IMG, True),
])
def test_encode_rejects_bad_input(rgb: np.ndarray, quality: int) -> None:
    with pytest.raises(ValueError):
        encode_jpeg(rgb, quality)


@pytest.mark.parametrize("data", [BASELINE, PROGRESSIVE], ids=["baseline", "progressive"])
def test_dimensions_baseline_and_progressive(data: bytes) -> None:
    assert jpeg_dimensions(data) == (IMG.shape[1], IMG.shape[0], 3)
    assert decode_jpeg(data).shape == IMG.shape


def test_progressive_really_is_progressive() -> None:
    assert b"\xff\xc2" in PROGRESSIVE[:sof_offset(PROGRESSIVE) + 2]
    assert PROGRESSIVE.count(b"\xff\xda") > 1  # several scans
    assert BASELINE[sof_offset(BASELINE) + 1] == 0xC0


def test_dimensions_with_fill_bytes_and_standalone_markers() -> None:
    # Insert fill bytes before the first marker after SOI and a standalone TEM marker (FF 01).
    data = BASELINE[:2] + b"\xff\x01" + b"\xff\xff\xff" + BASELINE[2:]
    assert jpeg_dimensions(data) == (128, 96, 3)
    assert decode_jpeg(data).shape == IMG.shape


def test_dimensions_of_odd_sizes_and_grey() -> None:
    odd = encode_jpeg(scene(37, 301), 50)
    assert jpeg_dimensions(odd) == (301, 37, 3)
    _, grey = cv2.imencode(".jpg", scene()[:, :, 0])
    assert jpeg_dimensions(grey.tobytes()) == (128, 96, 1)


@pytest.mark.parametrize(("data", "reason"), [
    (b"", "SOI"), (b"\x89PNG\r\n\x1a\n", "SOI"), (b"\xff\xd8", "SOI"),
    (b"\xff\xd8\xff\xd9", "before any frame header"),
    (b"\xff\xd8\xff\xda\x00\x02", "before any frame header"),
    (b"\xff\xd8\xff\xe0\x00\x10JFIF", "runs past"),
    (b"\xff\xd8\xff\xe0\x00", "length field"),
    (b"\xff\xd8\xff\xe0\x00\x01", "length 1"),
    (b"\xff\xd8\xff\xff\xff", "fill bytes"),
    (b"\xff\xd8\xff\x00\x00\x00", "stuffed"),
    (b"\xff\xd8\x12\x34", "expected a marker"),
    (b"\xff\xd8\xff\xc0\x00\x08\x08\x00\x00\x00\x10\x03", "shorter than its component list"),
    (b"\xff\xd8\xff\xc0\x00\x0b\x08\x00\x00\x00\x10\x01\x01\x11\x00", "DNL"),
])
def test_dimensions_refuses_garbage(data: bytes, reason: str) -> None:
    with pytest.raises(ImageRejected, match=reason):
        jpeg_dimensions(data)


def _no_decoder(*args: object, **kwargs: object) -> None:
    raise AssertionError("cv2.imdecode must not be called for a refused header")


def test_forged_20000_header_refused_before_decoding(monkeypatch: pytest.MonkeyPatch) -> None:
    forged = with_size(BASELINE, 20000, 20000)
    assert jpeg_dimensions(forged) == (20000, 20000, 3)
    monkeypatch.setattr(jpeg.cv2, "imdecode", _no_decoder)
    with pytest.raises(ImageRejected, match="20000×20000"):
        decode_jpeg(forged)
    # A bare header with no image data at all is refused the same way.
    bare = b"\xff\xd8\xff\xc0\x00\x11\x08" + struct.pack(">HH", 20000, 20000) + b"\x03" + b"\x01\x22\x00" * 3
    with pytest.raises(ImageRejected, match="limit"):
        decode_jpeg(bare)


def test_limits_and_expected_shape_checked_before_decoding(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(jpeg.cv2, "imdecode", _no_decoder)
    with pytest.raises(ImageRejected, match="byte limit"):
        decode_jpeg(BASELINE, max_bytes=len(BASELINE) - 1)
    with pytest.raises(ImageRejected, match="px > limit"):
        decode_jpeg(BASELINE, max_pixels=128 * 96 - 1)
    with pytest.raises(ImageRejected, match="expected 96×128"):
        decode_jpeg(BASELINE, expected_shape=(128, 96))
    _, grey = cv2.imencode(".jpg", IMG[:, :, 0])
    with pytest.raises(ImageRejected, match="1 components"):
        decode_jpeg(grey.tobytes())
    with pytest.raises(ImageRejected, match="bytes"):
        decode_jpeg("not bytes")  # type: ignore[arg-type]


def test_limits_are_inclusive() -> None:
    out = decode_jpeg(BASELINE, max_pixels=128 * 96, max_bytes=len(BASELINE), expected_shape=(96, 128))
    assert out.shape == (96, 128, 3)
    assert wire.MAX_IMAGE_PIXELS >= 4096 * 4096


def test_exif_orientation_is_ignored() -> None:
    # An APP1 Exif segment with Orientation = 6 (rotate 90°): OpenCV would rotate by default.
    tiff = b"II*\x00" + struct.pack("<I", 8) + struct.pack("<H", 1)
    tiff += struct.pack("<HHII", 0x0112, 3, 1, 6) + struct.pack("<I", 0)
    app1 = b"Exif\x00\x00" + tiff
    data = BASELINE[:2] + b"\xff\xe1" + struct.pack(">H", len(app1) + 2) + app1 + BASELINE[2:]
    assert decode_jpeg(data).shape == (96, 128, 3)


def test_trailing_garbage_and_zero_padding() -> None:
    assert decode_jpeg(BASELINE + b"\x00" * 16).shape == IMG.shape
    with pytest.raises(ImageRejected, match="after EOI"):
        decode_jpeg(BASELINE + b"junk")


SMALL = encode_jpeg(scene(16, 24, seed=3), 90)
SMALL_PROGRESSIVE = encode_jpeg(scene(16, 24, seed=3), 90, progressive=True)


@pytest.mark.parametrize("data", [SMALL, SMALL_PROGRESSIVE], ids=["baseline", "progressive"])
def test_every_truncation_is_rejected(data: bytes) -> None:
    check_jpeg_structure(data)
    for n in range(len(data) - 1):
        with pytest.raises(ImageRejected):  # by our own walk, whatever the OpenCV build tolerates
            check_jpeg_structure(data[:n])
        with pytest.raises(ImageRejected):
            decode_jpeg(data[:n])


def test_structure_walk_accepts_valid_and_names_the_problem() -> None:
    for data in (BASELINE, PROGRESSIVE, BASELINE[:2] + b"\xff\x01\xff\xff" + BASELINE[2:]):
        check_jpeg_structure(data)
    sos = BASELINE.find(b"\xff\xda")
    with pytest.raises(ImageRejected, match="without EOI"):
        check_jpeg_structure(BASELINE[:-2])
    with pytest.raises(ImageRejected, match="second SOI"):
        check_jpeg_structure(BASELINE[:sos] + b"\xff\xd8" + BASELINE[sos:])
    with pytest.raises(ImageRejected, match="more than one frame header"):
        at = sof_offset(BASELINE)
        sof_len = struct.unpack(">H", BASELINE[at + 2: at + 4])[0]
        check_jpeg_structure(BASELINE[:sos] + BASELINE[at: at + 2 + sof_len] + BASELINE[sos:])
    with pytest.raises(ImageRejected, match="EOI before any scan"):
        check_jpeg_structure(BASELINE[:sos] + b"\xff\xd9")


def test_header_fields_and_precision_refused() -> None:
    header = jpeg_header(PROGRESSIVE)
    assert (header.width, header.height, header.components, header.precision_bits, header.sof_marker) == \
        (128, 96, 3, 8, 0xC2)
    at = sof_offset(BASELINE) + 4
    twelve_bit = BASELINE[:at] + b"\x0c" + BASELINE[at + 1:]
    assert jpeg_header(twelve_bit).precision_bits == 12
    with pytest.raises(ImageRejected, match="12-bit"):
        decode_jpeg(twelve_bit)


def _decode_or_reject(data: bytes) -> None:
    """The contract under fuzzing: ImageRejected, or an RGB image whose size the header announced."""
    try:
        out = decode_jpeg(data)
    except ImageRejected:
        return
    w, h, c = jpeg_dimensions(data)
    assert out.shape == (h, w, 3) and out.dtype == np.uint8 and c == 3


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.sampled_from([SMALL, SMALL_PROGRESSIVE]),
       flips=st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 7)), min_size=1, max_size=4))
def test_fuzz_bit_flips_never_crash(data: bytes, flips: list[tuple[int, int]]) -> None:
    buf = bytearray(data)
    for index, bit in flips:
        buf[index % len(buf)] ^= 1 << bit
    _decode_or_reject(bytes(buf))


@settings(max_examples=200, deadline=None)
@given(data=st.sampled_from([SMALL, SMALL_PROGRESSIVE]), cut=st.integers(0, 10**6),
       tail=st.binary(max_size=64))
def test_fuzz_truncated_plus_junk_never_crash(data: bytes, cut: int, tail: bytes) -> None:
    _decode_or_reject(data[: cut % len(data)] + tail)


@settings(max_examples=200, deadline=None)
@given(body=st.binary(max_size=256))
def test_fuzz_random_bytes_after_soi(body: bytes) -> None:
    _decode_or_reject(b"\xff\xd8" + body)
