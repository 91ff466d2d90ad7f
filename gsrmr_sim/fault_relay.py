"""Fault-injecting uplink relay (``gsrmr-uplink-relay``): robot namespace → server namespace, with faults.

The relay sits between the robot's uplink topics and the server's. It subscribes
``<input_prefix>/uplink/pose_key`` (``geometry_msgs/Vector3Stamped``) and
``<input_prefix>/uplink/image_raw/compressed`` (``sensor_msgs/CompressedImage``) — both reliable,
depth 50/10 like the robot's publishers — and republishes each message on the relative topics
``uplink/pose_key`` and ``uplink/image_raw/compressed`` of its own namespace (the server's), after the
pure :class:`FaultInjector` has decided what happens to it. At most one fault per message, drawn with
the configured per-message probabilities from a seeded RNG (one stream per topic, so the key faults do
not depend on how many images arrived):

============== ===== ===== ==========================================================================
fault          key   image what the server should see
============== ===== ===== ==========================================================================
drop           yes   yes   nothing for that slot → ``missing_key`` / ``missing_image``
duplicate      yes   yes   the message twice → ``duplicate_key`` / ``duplicate_image``
reorder        yes   yes   held until the next message of the topic was sent (one slot later) → ``late``
delay          yes   yes   sent ``delay_slots`` (default 1.5) slots later → ``late``
stale          yes   yes   stamp moved ``stale_slots`` slots back (an old slot index) → ``late``
nan_key        yes   no    one of (a, b, θ) replaced by NaN, +inf or −inf → ``invalid_key``
truncate       no    yes   JPEG cut to half its length → ``corrupt_image``
corrupt        no    yes   one bit of a header marker byte flipped (a bit error the structure walk
                           detects; entropy-data flips decode to a wrong image, which only the MR loss
                           can see — JPEG has no checksum) → ``corrupt_image``
wrong_size     no    yes   re-encoded at half width and height → ``wrong_size``
forged_header  no    yes   frame header (SOF) rewritten to claim 20000×20000 → ``oversized_header``
============== ===== ===== ==========================================================================

Units: stamps and times are integer nanoseconds of the ROS clock; the slot length is ``slot_s``
seconds (must equal the robot's and the server's). Pose keys are (a_m, b_m, theta_rad) in ``map``.

Messages arriving while nothing subscribes to the output topic are discarded before any draw (counted
as ``<kind>.no_subscriber`` under ``mutation_errors``), so every count refers to a message that had a
receiver. Counts of what was injected are published on ``/diagnostics`` once a second (keys ``key.<fault>``,
``image.<fault>``, ``key.forwarded``, …) and written as JSON to ``summary_path`` (and the log) on exit.
The core (:class:`FaultInjector`, the ``*_jpeg`` mutators) has no rclpy import; :class:`FaultRelayNode`
and :func:`main` import rclpy lazily.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field, fields
import json
import math
from pathlib import Path

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


# ------------------------------------------------------------------------------------ ROS node

def _node_class():  # defined lazily: the pure core above imports without rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import Vector3Stamped
    from rcl_interfaces.msg import SetParametersResult
    from rclpy.node import Node
    from sensor_msgs.msg import CompressedImage

    from gsrmr_common.ros_node import declare, diagnostics_msg
    from gsrmr_common.ros_wire import IMAGE_UPLOAD_QOS, UPLINK_QOS, ns_to_stamp, stamp_to_ns

    key_qos, image_qos = UPLINK_QOS, IMAGE_UPLOAD_QOS  # the robot's and the server's profiles

    class FaultRelayNode(Node):
        """Relays the robot's uplink into this node's namespace, injecting faults (see the module doc)."""

        def __init__(self, **node_kwargs) -> None:
            super().__init__("gsrmr_uplink_relay", **node_kwargs)
            prefix = declare(self, "input_prefix", "/robot", "Namespace the robot publishes its uplink in",
                             read_only=True).rstrip("/")
            slot_s = declare(self, "slot_s", 0.1, "Slot length τ [s] (as robot and server)", min_value=0.01,
                             max_value=10.0, read_only=True)
            seed = declare(self, "seed", 0, "Fault RNG seed", min_value=0, max_value=2**31 - 1, read_only=True)
            delay_slots = declare(self, "delay_slots", 1.5, "Delay of a 'delay' fault [slots] (> 1)",
                                  min_value=1.01, max_value=100.0, read_only=True)
            stale_slots = declare(self, "stale_slots", 5, "Stamp shift of a 'stale' fault [slots]", min_value=1,
                                  max_value=1000, read_only=True)
            self.summary_path = declare(self, "summary_path", "", "Write the JSON summary here on exit ('' = log "
                                        "only)", read_only=True)
            default = FaultRates()
            rates = {name: declare(self, f"{name}_rate", float(getattr(default, name)),
                                   f"P({name}) per message", min_value=0.0, max_value=1.0) for name in ALL_FAULTS}
            self.injector = FaultInjector(FaultRates(**rates), seed=seed, slot_s=slot_s, delay_slots=delay_slots,
                                          stale_slots=stale_slots)
            self.add_on_set_parameters_callback(self._validate)
            self._pub = {"key": self.create_publisher(Vector3Stamped, "uplink/pose_key", key_qos),
                         "image": self.create_publisher(CompressedImage, "uplink/image_raw/compressed", image_qos)}
            self._pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
            self.create_subscription(Vector3Stamped, f"{prefix}/uplink/pose_key", self._on_key, key_qos)
            self.create_subscription(CompressedImage, f"{prefix}/uplink/image_raw/compressed", self._on_image,
                                     image_qos)
            self.create_timer(0.002, self._release)
            self.create_timer(1.0, self._publish_diagnostics)
            self.get_logger().info(f"uplink relay {prefix}/uplink → {self.get_namespace()}: seed {seed}, "
                                   f"rates {self.injector.summary()['rates']}")

        def _validate(self, params) -> SetParametersResult:
            current = {n: getattr(self.injector.rates, n) for n in ALL_FAULTS}
            for p in params:
                if p.name.endswith("_rate") and p.name[:-5] in current:
                    current[p.name[:-5]] = float(p.value)
            try:
                rates = FaultRates(**current)
            except ValueError as err:
                return SetParametersResult(successful=False, reason=str(err))
            self.injector.set_rates(rates)
            return SetParametersResult(successful=True)

        def _now(self) -> int:
            return self.get_clock().now().nanoseconds

        def _stamp(self, msg, kind: str) -> int | None:
            if self._pub[kind].get_subscription_count() == 0:  # nobody to deliver to: no draw, no count
                self.injector.errors[f"{kind}.no_subscriber"] += 1
                return None
            try:
                return stamp_to_ns(msg.header.stamp)
            except ValueError:
                self.injector.errors[f"{kind}.malformed_stamp"] += 1
                return None

        def _on_key(self, msg) -> None:
            stamp = self._stamp(msg, "key")
            if stamp is not None:
                v = msg.vector
                up = Upload("key", stamp, (v.x, v.y, v.z), msg.header.frame_id)
                self._send(self.injector.push(up, self._now()))

        def _on_image(self, msg) -> None:
            stamp = self._stamp(msg, "image")
            if stamp is not None:
                self._fmt = msg.format
                self._send(self.injector.push(Upload("image", stamp, bytes(msg.data), msg.header.frame_id),
                                              self._now()))

        def _release(self) -> None:
            self._send(self.injector.due(self._now()))

        def _send(self, uploads: list[Upload]) -> None:
            for up in uploads:
                if up.kind == "key":
                    msg = Vector3Stamped()
                    msg.vector.x, msg.vector.y, msg.vector.z = up.data  # type: ignore[misc]
                else:
                    msg = CompressedImage(format=getattr(self, "_fmt", "jpeg"), data=up.data)
                msg.header.stamp = ns_to_stamp(up.stamp_ns)
                msg.header.frame_id = up.frame_id
                self._pub[up.kind].publish(msg)

        def _publish_diagnostics(self) -> None:
            s = self.injector.summary()
            values = {**s["injected"], "held": s["held"], "mutation_errors": json.dumps(s["mutation_errors"])}
            self._pub_diag.publish(diagnostics_msg(self, name=f"{self.get_name()}: uplink fault relay",
                                                   hardware_id="gsrmr_uplink_relay", values=values,
                                                   message="injecting faults"))

        def on_shutdown(self) -> None:
            """Log and write the JSON summary (called by run_node on exit)."""
            text = json.dumps(self.injector.summary(), indent=1, sort_keys=True)
            self.get_logger().info(f"relay summary: {text}")
            if self.summary_path:
                Path(self.summary_path).write_text(text)

    return FaultRelayNode


def make_node(**node_kwargs):
    """Build a :class:`FaultRelayNode` (rclpy must be initialised)."""
    return _node_class()(**node_kwargs)


def main(args: list[str] | None = None) -> int:
    """Console script ``gsrmr-uplink-relay``."""
    from gsrmr_common.ros_node import run_node

    return run_node(make_node, args)
