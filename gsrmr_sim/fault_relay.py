"""Fault-injecting uplink relay (``gsrmr-uplink-relay``): robot namespace → server namespace, with faults.

This module is the core (:class:`FaultInjector`, the ``*_jpeg`` mutators), without rclpy; the node and its
parameters are :mod:`gsrmr_sim.fault_relay_node`. The faults, what the server should count for each and the
relay's counts: docs/reliability.md, "The fault relay" and "The relay's core".
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field, fields
import math

import cv2
import numpy as np

from gsrmr_common.jpeg import encode_jpeg, jpeg_header

KEY_FAULTS = ("drop", "duplicate", "reorder", "delay", "stale", "nan_key")
IMAGE_FAULTS = ("drop", "duplicate", "reorder", "delay", "stale", "truncate", "corrupt", "wrong_size",
                "forged_header")
ALL_FAULTS = tuple(dict.fromkeys(KEY_FAULTS + IMAGE_FAULTS))
FORGED_SIDE_PX = 20000


@dataclass(frozen=True)
class FaultRates:
    """Per-message probability of each fault (at most one fault per message)."""

    drop: float = 0.10
    duplicate: float = 0.03
    reorder: float = 0.03
    delay: float = 0.03
    stale: float = 0.03
    nan_key: float = 0.03
    truncate: float = 0.03
    corrupt: float = 0.03
    wrong_size: float = 0.03
    forged_header: float = 0.03

    def __post_init__(self) -> None:
        problem = self.problem()
        if problem:
            raise ValueError(problem)

    def problem(self) -> str | None:
        """Why these rates are invalid, or None."""
        for f in fields(self):
            v = getattr(self, f.name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and 0.0 <= v <= 1.0):
                return f"{f.name}_rate must be a probability in [0, 1], got {v!r}"
        for kind, names in (("key", KEY_FAULTS), ("image", IMAGE_FAULTS)):
            total = sum(getattr(self, n) for n in names)
            if total > 1.0 + 1e-12:
                return f"{kind} fault rates sum to {total:.3f} > 1 (at most one fault per message)"
        return None

    @classmethod
    def none(cls) -> FaultRates:
        """All rates zero (a transparent relay)."""
        return cls(**{f.name: 0.0 for f in fields(cls)})


@dataclass
class Upload:
    """One uplink message as plain data: a pose key (a_m, b_m, theta_rad) or JPEG bytes, with its stamp."""

    kind: str  # "key" | "image"
    stamp_ns: int  # header stamp = slot start (see gsrmr_common.wire)
    data: tuple[float, float, float] | bytes
    frame_id: str = ""
    fault: str = ""  # the fault applied ("" = none)


@dataclass(order=True)
class _Held:
    release_ns: int
    seq: int
    upload: Upload = field(compare=False)


# ------------------------------------------------------------------------------------ JPEG mutators

def _header_marker_offsets(data: bytes) -> list[int]:
    """Byte offsets of the 0xFF of every marker segment between SOI and the first SOS (inclusive)."""
    offsets, pos = [], 2
    while pos + 4 <= len(data) and data[pos] == 0xFF:
        marker = data[pos + 1]
        offsets.append(pos)
        if marker == 0xDA:  # SOS: entropy-coded data follows
            break
        pos += 2 + ((data[pos + 2] << 8) | data[pos + 3])
    return offsets


def truncate_jpeg(data: bytes) -> bytes:
    """The first half of the JPEG (no EOI, cut inside the scan or the header)."""
    return bytes(data[: max(2, len(data) // 2)])


def corrupt_jpeg(data: bytes, rng: np.random.Generator) -> bytes:
    """Flip one bit of the 0xFF prefix of a header marker (detectable by a structure walk)."""
    offsets = _header_marker_offsets(data)
    if not offsets:
        raise ValueError("corrupt_jpeg: no marker segments after SOI (not a JPEG?)")
    buf = bytearray(data)
    buf[offsets[int(rng.integers(len(offsets)))]] ^= 1 << int(rng.integers(8))
    return bytes(buf)


def resize_jpeg(data: bytes, factor: float = 0.5, quality: int = 80) -> bytes:
    """Decode, resize by ``factor`` in both axes (area interpolation) and re-encode."""
    bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ValueError("resize_jpeg: not a decodable JPEG")
    h, w = bgr.shape[:2]
    size = (max(1, round(w * factor)), max(1, round(h * factor)))
    small = cv2.resize(bgr, size, interpolation=cv2.INTER_AREA)
    return encode_jpeg(np.ascontiguousarray(small[:, :, ::-1]), quality)


def forge_jpeg_header(data: bytes, width_px: int = FORGED_SIDE_PX, height_px: int = FORGED_SIDE_PX) -> bytes:
    """Rewrite the frame header (SOF) to claim ``width_px`` × ``height_px``; the scan data is unchanged."""
    if not (0 < width_px < 65536 and 0 < height_px < 65536):
        raise ValueError("forge_jpeg_header: JPEG dimensions are 16-bit")
    buf = bytearray(data)
    for off in _header_marker_offsets(data):
        marker = data[off + 1]
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            buf[off + 5:off + 7] = height_px.to_bytes(2, "big")
            buf[off + 7:off + 9] = width_px.to_bytes(2, "big")
            forged = bytes(buf)
            header = jpeg_header(forged)
            assert (header.width, header.height) == (width_px, height_px)
            return forged
    raise ValueError("forge_jpeg_header: no frame header found")


# ------------------------------------------------------------------------------------ the injector

class FaultInjector:
    """Decides, per message, which fault to inject; holds delayed and reordered messages.

    ``push`` returns the uploads to send now; ``due`` returns held uploads whose time has come. Both
    take the current ROS time in nanoseconds. ``injected`` counts ``"<kind>.<fault>"`` and
    ``"<kind>.forwarded"`` (messages sent, duplicates included).
    """

    def __init__(self, rates: FaultRates, *, seed: int = 0, slot_s: float = 0.1, delay_slots: float = 1.5,
                 stale_slots: int = 5, max_reorder_hold_slots: float = 3.0) -> None:
        if not (math.isfinite(slot_s) and slot_s > 0):
            raise ValueError(f"slot_s must be > 0, got {slot_s}")
        if not (math.isfinite(delay_slots) and delay_slots > 1.0):
            raise ValueError(f"delay_slots must exceed 1 (delay beyond a slot), got {delay_slots}")
        if int(stale_slots) != stale_slots or stale_slots < 1:
            raise ValueError(f"stale_slots must be a positive integer, got {stale_slots}")
        self.rates = rates
        self.slot_ns = round(slot_s * 1e9)
        self.delay_ns = round(delay_slots * self.slot_ns)
        self.stale_slots = int(stale_slots)
        self.max_reorder_hold_ns = round(max_reorder_hold_slots * self.slot_ns)
        self._rng = {"key": np.random.default_rng([seed, 0]), "image": np.random.default_rng([seed, 1])}
        self._held: list[_Held] = []
        self._reorder: dict[str, _Held | None] = {"key": None, "image": None}
        self._seq = 0
        self.injected: Counter[str] = Counter()
        self.errors: Counter[str] = Counter()

    def set_rates(self, rates: FaultRates) -> None:
        """Change the rates from the next message on."""
        self.rates = rates

    def _draw(self, kind: str) -> str:
        names = KEY_FAULTS if kind == "key" else IMAGE_FAULTS
        u = float(self._rng[kind].random())
        acc = 0.0
        for name in names:
            acc += getattr(self.rates, name)
            if u < acc:
                return name
        return ""

    def _hold(self, upload: Upload, release_ns: int) -> _Held:
        self._seq += 1
        held = _Held(release_ns, self._seq, upload)
        self._held.append(held)
        return held

    def _mutate(self, up: Upload, fault: str) -> Upload:
        rng = self._rng[up.kind]
        data = up.data
        stamp = up.stamp_ns
        if fault == "stale":
            stamp = up.stamp_ns - self.stale_slots * self.slot_ns
        elif fault == "nan_key":
            vals = list(data)  # type: ignore[arg-type]
            vals[int(rng.integers(3))] = (math.nan, math.inf, -math.inf)[int(rng.integers(3))]
            data = (vals[0], vals[1], vals[2])
        elif fault == "truncate":
            data = truncate_jpeg(data)  # type: ignore[arg-type]
        elif fault == "corrupt":
            data = corrupt_jpeg(data, rng)  # type: ignore[arg-type]
        elif fault == "wrong_size":
            data = resize_jpeg(data)  # type: ignore[arg-type]
        elif fault == "forged_header":
            data = forge_jpeg_header(data)  # type: ignore[arg-type]
        return Upload(up.kind, stamp, data, up.frame_id, fault)

    def push(self, upload: Upload, now_ns: int) -> list[Upload]:
        """A message arrived from the robot: what to send now (possibly nothing, possibly two or three)."""
        if upload.kind not in ("key", "image"):
            raise ValueError(f"unknown upload kind {upload.kind!r}")
        kind = upload.kind
        fault = self._draw(kind)
        previous = self._reorder[kind]
        if fault == "reorder" and previous is not None:
            fault = ""  # one message held for reordering at a time: this one goes through unchanged
        if fault in ("stale", "nan_key", "truncate", "corrupt", "wrong_size", "forged_header"):
            try:
                upload = self._mutate(upload, fault)
            except ValueError:
                self.errors[f"{kind}.{fault}"] += 1  # cannot mutate this payload: forward it as is
                fault = ""
        elif fault:
            upload = Upload(kind, upload.stamp_ns, upload.data, upload.frame_id, fault)
        if fault:
            self.injected[f"{kind}.{fault}"] += 1
        if fault == "drop":
            return []
        if fault == "delay":
            self._hold(upload, now_ns + self.delay_ns)
            return []
        if fault == "reorder":
            self._reorder[kind] = self._hold(upload, now_ns + self.max_reorder_hold_ns)
            return []
        out = [upload, upload] if fault == "duplicate" else [upload]
        if previous is not None:  # the held message goes right after its successor
            self._held.remove(previous)
            self._reorder[kind] = None
            out.append(previous.upload)
        self._count(out)
        return out

    def due(self, now_ns: int) -> list[Upload]:
        """Held (delayed, or reordered without a successor) uploads whose release time has passed."""
        ready = sorted(h for h in self._held if h.release_ns <= now_ns)
        for h in ready:
            self._held.remove(h)
            if self._reorder[h.upload.kind] is h:
                self._reorder[h.upload.kind] = None
        out = [h.upload for h in ready]
        self._count(out)
        return out

    def held(self) -> int:
        """Uploads currently held back."""
        return len(self._held)

    def _count(self, out: list[Upload]) -> None:
        for up in out:
            self.injected[f"{up.kind}.forwarded"] += 1

    def summary(self) -> dict:
        """Counts as a JSON-ready dict."""
        return {"injected": dict(sorted(self.injected.items())), "mutation_errors": dict(self.errors),
                "held": self.held(), "rates": {f.name: getattr(self.rates, f.name) for f in fields(self.rates)}}
