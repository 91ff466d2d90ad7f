"""Wire formats shared by the robot, the server and the scheduler (pure: no rclpy import), owned here so the two sides
cannot disagree; :mod:`gsrmr_common.ros_wire` maps them to messages. Topics, types and layouts: README.md, "Wire
layouts" (test/project/test_readme.py holds it to these fields).

Fields in wire order: :class:`ScheduleMsg` ``[first_slot, slot_s, seq, slots]``, then the blocks ``x``, ``power_w`` and,
with the in-slot rule, ``gain_threshold``, which ``layout.dim`` labels after ``meta``; :class:`LedgerRow` ``[slot, x,
scheduled_power_w, bits_sent, gain, power_w, energy_j, upload_all_bits, upload_all_energy_j, frame_stamp_s, round_slot,
held_back, uplink_rate_bps, scene_change, correction_seq]``; :class:`LossSample` ``[slot, a_m, b_m, theta_rad, loss]``;
:class:`ChannelSample` ``[slot, round_slot, gain]``; :class:`MRSlotInfo` ``[slot, source, a_m, b_m, theta_rad,
content_time_s, level]`` (``level`` an index of :data:`COMPOSE_LEVELS`); :class:`MapCorrection`
:data:`MAP_CORRECTION_FIELDS`.

Names that cross a boundary as strings (CSV cells, diagnostics JSON, the demo summary) are enums: :class:`Delivery`,
:class:`RealSource` (``source``: on the wire an index of :data:`REAL_SOURCES`) and :class:`UplinkFault`."""

from __future__ import annotations

from dataclasses import astuple, dataclass
from enum import Enum
import math

import numpy as np

POSE_KEY_BITS = 192
JPEG_FORMAT = "rgb8; jpeg compressed bgr8"  # an uploaded image's format; its frame_id is the camera optical frame
MAP_FRAME = "map"
SCHEDULE_META = ("first_slot", "slot_s", "seq", "slots")
# Refuse uploads whose size or claimed dimensions are absurd before decoding them.
MAX_IMAGE_PIXELS = 4096 * 4096
MAX_COMPRESSED_BYTES = 8 * 1024 * 1024


@dataclass(frozen=True)
class PoseKey:
    """A pose key: robot pose in ``map`` (metres, radians) for absolute slot ``slot``; sent in image slots too, so the
    server can measure the GS loss L_t at that pose."""

    slot: int
    a_m: float
    b_m: float
    theta_rad: float

    def is_valid(self) -> bool:
        """False for NaN or inf components (a corrupt key is never rendered)."""
        return all(math.isfinite(v) for v in (self.a_m, self.b_m, self.theta_rad))


@dataclass
class ScheduleMsg:
    """A schedule as sent on the wire: slots ``first_slot … first_slot + len(x) − 1`` (``first_slot`` is exact in
    float64 up to 2^53)."""

    first_slot: int
    slot_s: float
    seq: int
    x: np.ndarray  # int8, 1 = image, 0 = pose key (the plan at the expected channel gain)
    power_w: np.ndarray  # float64, watts
    # optional in-slot rule: send an image iff the radio's measured gain g_t ≥ gain_threshold_t
    # (dimensionless |h|²; +inf = always a key, 0 = always an image); None = follow x
    gain_threshold: np.ndarray | None = None

    def lookup(self, slot: int) -> tuple[int, float] | None:
        """(x, power_w) for an absolute slot, or None when the schedule does not cover it."""
        i = slot - self.first_slot
        if 0 <= i < len(self.x):
            return int(self.x[i]), float(self.power_w[i])
        return None

    def threshold(self, slot: int) -> float | None:
        """The gain threshold of an absolute slot (None without an in-slot rule or outside the schedule)."""
        i = slot - self.first_slot
        if self.gain_threshold is not None and 0 <= i < len(self.x):
            return float(self.gain_threshold[i])
        return None

    def to_data(self) -> list[float]:
        """Flat float64 list for ``Float64MultiArray.data`` (+inf thresholds are sent as −1)."""
        n = len(self.x)
        if len(self.power_w) != n:
            raise ValueError("schedule: x and power_w differ in length")
        data = [float(self.first_slot), float(self.slot_s), float(self.seq), float(n),
                *np.asarray(self.x, dtype=np.float64).tolist(), *np.asarray(self.power_w, np.float64).tolist()]
        if self.gain_threshold is not None:
            g = np.asarray(self.gain_threshold, np.float64)
            if g.shape != (n,) or np.any(np.isnan(g)) or np.any(g < 0):
                raise ValueError("schedule: gain_threshold must hold n values ≥ 0 (or +inf)")
            data += np.where(np.isinf(g), -1.0, g).tolist()
        return data

    @classmethod
    def from_data(cls, data: list[float] | np.ndarray) -> ScheduleMsg:
        """Parse ``Float64MultiArray.data``; raises ValueError on any inconsistency."""
        arr = np.asarray(data, dtype=np.float64)
        if arr.size < 4 or not np.all(np.isfinite(arr)):
            raise ValueError("schedule: data must hold 4 finite meta values")
        n = int(arr[3])
        if arr[3] != n or n < 0 or arr.size not in (4 + 2 * n, 4 + 3 * n) or (n == 0 and arr.size != 4):
            raise ValueError(f"schedule: data has {arr.size} values, meta says {arr[3]} slots")
        x = arr[4:4 + n]
        power = arr[4 + n:4 + 2 * n]
        threshold = None
        if arr.size == 4 + 3 * n and n:
            raw = arr[4 + 2 * n:]
            if np.any((raw < 0) & (raw != -1.0)):
                raise ValueError("schedule: gain_threshold must be ≥ 0 (or −1 for +inf)")
            threshold = np.where(raw == -1.0, np.inf, raw)
        if not np.all((x == 0) | (x == 1)):
            raise ValueError("schedule: x must be 0 or 1")
        if np.any(power < 0):
            raise ValueError("schedule: power_w must be >= 0")
        if not arr[1] > 0:
            raise ValueError("schedule: slot_s must be > 0")
        return cls(int(arr[0]), float(arr[1]), int(arr[2]), x.astype(np.int8), power.copy(), threshold)


@dataclass(frozen=True)
class LedgerRow:
    """One slot of the robot's energy ledger, as sent on ``gsrmr/ledger`` (units in the names).

    The wire contract of robot and server: the server records it beside the slot it composed."""

    slot: int
    x: int  # 1: the robot sent an image in the slot; 0: the key only (also when no fresh frame was there to send)
    scheduled_power_w: float
    bits_sent: int
    gain: float
    power_w: float
    energy_j: float
    upload_all_bits: int
    upload_all_energy_j: float
    frame_stamp_s: float = float("nan")  # capture stamp of the camera frame this slot used (NaN: none)
    round_slot: int = -1  # the radio's index of the slot in the round (ChannelSample.round_slot; −1: unknown)
    held_back: int = 0  # 1: an image was asked for and the robot sent the key only (its last image still queued)
    uplink_rate_bps: float = float("nan")  # the robot's estimate of the uplink's throughput from image acks, bit/s
    scene_change: int = 0  # 1: the robot's scene-change test fired on this slot's frame (the view changed suddenly)
    correction_seq: int = 0  # the map → odom correction the slot's key was made with (MapCorrection.seq; 0: none)


# Order of the values in a ``gsrmr/ledger`` Float64MultiArray (one message per slot).
LEDGER_FIELDS = tuple(LedgerRow.__dataclass_fields__)


LOSS_SAMPLE_FIELDS = ("slot", "a_m", "b_m", "theta_rad", "loss")


@dataclass(frozen=True)
class LossSample:
    """The GS loss L_t measured by the server in image slot ``slot`` at the reported pose (map, m, rad)."""

    slot: int
    a_m: float
    b_m: float
    theta_rad: float
    loss: float

    def to_data(self) -> list[float]:
        """Flat float64 list for ``Float64MultiArray.data`` (:data:`LOSS_SAMPLE_FIELDS` order)."""
        return [float(v) for v in astuple(self)]

    @classmethod
    def from_data(cls, data: list[float] | np.ndarray) -> LossSample:
        """Parse ``Float64MultiArray.data``; ValueError unless 5 finite values with a loss ≥ 0."""
        arr = np.asarray(data, dtype=np.float64)
        if arr.shape != (len(LOSS_SAMPLE_FIELDS),) or not np.all(np.isfinite(arr)) or arr[4] < 0:
            raise ValueError(f"loss sample: expected {len(LOSS_SAMPLE_FIELDS)} finite values {LOSS_SAMPLE_FIELDS} "
                             "with loss ≥ 0")
        return cls(int(arr[0]), float(arr[1]), float(arr[2]), float(arr[3]), float(arr[4]))


MR_SLOT_INFO_FIELDS = ("slot", "source", "a_m", "b_m", "theta_rad", "content_time_s", "level")
#: The server's composition levels, best first (``level`` of :class:`MRSlotInfo`; gsrmr_server.compose_levels).
COMPOSE_LEVELS = ("full", "half", "quarter")
#: Topic (relative: in the server's namespace) of the per-slot :class:`MRSlotInfo`, published after ``mr/image``.
MR_SLOT_INFO_TOPIC = "mr/slot_info"


@dataclass(frozen=True)
class MRSlotInfo:
    """What the server composed slot ``slot``'s MR image from: where r̂ came from, the pose it was composed at (map,
    m, rad: the slot's key or the fallback estimate; NaN ×3 for source ``none``) and the MR content time, seconds
    since the first composed slot. With the model, the MR content, the mount and the intrinsics a monitor can rebuild
    the slot's v and d (:class:`gsrmr_server.scoring.SlotScorer`)."""

    slot: int
    source: RealSource
    a_m: float
    b_m: float
    theta_rad: float
    content_time_s: float
    level: int = 0  # composition level: an index of COMPOSE_LEVELS (0 = the full-size render)

    @classmethod
    def of(cls, slot: int, source: RealSource, pose: PoseKey | None, content_time_s: float,
           level: int = 0) -> MRSlotInfo:
        """The record of a slot composed from ``source`` at ``pose`` (None: no pose), ``content_time_s`` and
        composition ``level``."""
        a, b, th = (pose.a_m, pose.b_m, pose.theta_rad) if pose is not None else (math.nan,) * 3
        return cls(int(slot), RealSource(source), float(a), float(b), float(th), float(content_time_s), int(level))

    @property
    def pose(self) -> PoseKey | None:
        """The pose the MR image was composed at, as a key of this slot (None when there was none)."""
        key = PoseKey(self.slot, self.a_m, self.b_m, self.theta_rad)
        return key if key.is_valid() else None

    def to_data(self) -> list[float]:
        """Flat float64 list for ``Float64MultiArray.data`` (:data:`MR_SLOT_INFO_FIELDS` order)."""
        return [float(self.slot), float(REAL_SOURCES.index(self.source)), self.a_m, self.b_m, self.theta_rad,
                self.content_time_s, float(self.level)]

    @classmethod
    def from_data(cls, data: list[float] | np.ndarray) -> MRSlotInfo:
        """Parse ``Float64MultiArray.data``; ValueError unless 7 values (6: a server without levels, level 0) with
        a finite slot, a known source, a finite content time, a pose that is finite (NaN ×3 only for source
        ``none``) and a level of :data:`COMPOSE_LEVELS`."""
        arr = np.asarray(data, dtype=np.float64)
        if arr.shape == (len(MR_SLOT_INFO_FIELDS) - 1,):
            arr = np.append(arr, 0.0)
        if arr.shape != (len(MR_SLOT_INFO_FIELDS),) or not np.all(np.isfinite(arr[[0, 1, 5]])):
            raise ValueError(f"MR slot info: expected {len(MR_SLOT_INFO_FIELDS)} values {MR_SLOT_INFO_FIELDS} "
                             "with a finite slot, source and content time")
        if arr[6] not in range(len(COMPOSE_LEVELS)):
            raise ValueError(f"MR slot info: level {arr[6]} is not an index of {list(COMPOSE_LEVELS)}")
        if arr[1] not in range(len(REAL_SOURCES)):
            raise ValueError(f"MR slot info: source {arr[1]} is not an index of {[str(s) for s in REAL_SOURCES]}")
        source = REAL_SOURCES[int(arr[1])]
        pose = arr[2:5]
        if not (np.all(np.isfinite(pose)) or (source == RealSource.NONE and np.all(np.isnan(pose)))):
            raise ValueError("MR slot info: the pose must be finite (NaN ×3 only for source none)")
        return cls(int(arr[0]), source, float(pose[0]), float(pose[1]), float(pose[2]), float(arr[5]), int(arr[6]))


MAP_CORRECTION_FIELDS = ("seq", "stamp_s", "a_m", "b_m", "theta_rad", "var_a_m2", "var_b_m2", "var_theta_rad2")
#: Topic (relative: in the robot's namespace) of the server's :class:`MapCorrection`, latched.
MAP_CORRECTION_TOPIC = "gsrmr/map_correction"


@dataclass(frozen=True)
class MapCorrection:
    """The server's correction of the robot's ``map → odom``: the robot's ``map_from_odom`` parameter M₀ becomes
    ``X ∘ M₀`` with X = (a_m, b_m, theta_rad) in ``map``; absolute (not relative to the previous one), numbered by
    ``seq`` (≥ 1, growing), its variances [m², m², rad²], ``stamp_s`` the time of the newest fix it holds."""

    seq: int
    stamp_s: float
    a_m: float
    b_m: float
    theta_rad: float
    var_a_m2: float
    var_b_m2: float
    var_theta_rad2: float

    def to_data(self) -> list[float]:
        """Flat float64 list for ``Float64MultiArray.data`` (:data:`MAP_CORRECTION_FIELDS` order)."""
        return [float(v) for v in astuple(self)]

    @classmethod
    def from_data(cls, data: list[float] | np.ndarray) -> MapCorrection:
        """Parse ``Float64MultiArray.data``; ValueError unless 8 finite values, a whole ``seq`` ≥ 1, variances ≥ 0."""
        arr = np.asarray(data, dtype=np.float64)
        if arr.shape != (len(MAP_CORRECTION_FIELDS),) or not np.all(np.isfinite(arr)) or arr[0] < 1 \
                or arr[0] != int(arr[0]) or np.any(arr[5:] < 0):
            raise ValueError(f"map correction: expected {len(MAP_CORRECTION_FIELDS)} finite values "
                             f"{MAP_CORRECTION_FIELDS}, seq a whole number ≥ 1, variances ≥ 0")
        return cls(int(arr[0]), *(float(v) for v in arr[1:]))


CHANNEL_SAMPLE_FIELDS = ("slot", "round_slot", "gain")
#: Topic (relative, so it lands in the robot's namespace) of the radio's per-slot channel measurement.
CHANNEL_TOPIC = "radio/channel_gain"


@dataclass(frozen=True)
class ChannelSample:
    """The uplink channel power gain g = |h|² (dimensionless) measured for absolute slot ``slot``.

    On the robot this comes from the radio (a driver publishing on :data:`CHANNEL_TOPIC` at the start
    of each slot, e.g. from the pilot or ACK of the link layer); in simulation from ``gsrmr-sim-channel``,
    which owns the true channel. ``round_slot`` is the slot's index since the round started (−1 before it;
    the simulator seeds the fading by it, so runs with one ``channel_seed`` see the same channel).
    """

    slot: int
    round_slot: int
    gain: float

    def to_data(self) -> list[float]:
        """Flat float64 list for ``Float64MultiArray.data`` (:data:`CHANNEL_SAMPLE_FIELDS` order)."""
        return [float(self.slot), float(self.round_slot), float(self.gain)]

    @classmethod
    def from_data(cls, data: list[float] | np.ndarray) -> ChannelSample:
        """Parse ``Float64MultiArray.data``; ValueError unless 3 finite values with a gain > 0."""
        arr = np.asarray(data, dtype=np.float64)
        if arr.shape != (len(CHANNEL_SAMPLE_FIELDS),) or not np.all(np.isfinite(arr)) or not arr[2] > 0:
            raise ValueError(f"channel sample: expected {len(CHANNEL_SAMPLE_FIELDS)} finite values "
                             f"{CHANNEL_SAMPLE_FIELDS} with gain > 0")
        return cls(int(arr[0]), int(arr[1]), float(arr[2]))


def ledger_row_to_data(row: LedgerRow) -> list[float]:
    """A ledger row as ``Float64MultiArray.data`` (:data:`LEDGER_FIELDS` order)."""
    return [float(getattr(row, f)) for f in LEDGER_FIELDS]


def ledger_row_from_data(data: list[float] | np.ndarray) -> LedgerRow:
    """Parse ``gsrmr/ledger`` data; ValueError on a wrong length or a non-finite slot, x or bits_sent
    (energies and gains may be inf/NaN: a slot that could not carry its upload)."""
    arr = np.asarray(data, dtype=np.float64)
    if arr.shape != (len(LEDGER_FIELDS),):
        raise ValueError(f"ledger row: expected {len(LEDGER_FIELDS)} values {LEDGER_FIELDS}, got {arr.size}")
    row = dict(zip(LEDGER_FIELDS, arr.tolist(), strict=True))
    integers = ("slot", "x", "bits_sent", "upload_all_bits", "round_slot", "held_back", "scene_change",
                "correction_seq")
    if not all(math.isfinite(row[k]) for k in integers):
        raise ValueError(f"ledger row: {', '.join(integers)} must be finite")
    for k in integers:
        row[k] = int(row[k])
    return LedgerRow(**row)


class WireName(str, Enum):
    """A name that crosses a boundary as its string value: ``str(name)``, f-strings, JSON and ``==`` with
    the plain string all give the value (Python 3.10 has no ``StrEnum``)."""

    def __str__(self) -> str:
        return str(self.value)

    def __format__(self, spec: str) -> str:
        return format(str(self.value), spec)


class Delivery(WireName):
    """What reached the server for a slot: the image, only the pose key, or nothing in time."""

    IMAGE = "image"
    KEY = "key"
    NONE = "none"


class RealSource(WireName):
    """Where the server's real-view estimate r̂_t came from (the ``source`` column of ``slots.csv``)."""

    IMAGE = "image"  # the uploaded JPEG, decoded
    RENDER = "render"  # the GS render at the slot's pose key
    FALLBACK = "fallback"  # the GS render at the best pose estimate (upload missing, late or refused)
    NONE = "none"  # no pose ever received: the background colour


#: The sources in their wire order (the ``source`` index of :class:`MRSlotInfo`).
REAL_SOURCES = tuple(RealSource)


class UplinkFault(WireName):
    """The server's fault counters (``/diagnostics`` key ``faults``, ``slots.csv`` column ``faults``)."""

    DUPLICATE_KEY = "duplicate_key"
    DUPLICATE_IMAGE = "duplicate_image"
    INVALID_KEY = "invalid_key"  # NaN or inf
    LATE = "late"  # arrived after its slot was composed
    FUTURE = "future"  # more than max_future_slots ahead of the slot clock
    EVICTED = "evicted"  # pending uploads over the memory bound
    MISSING_KEY = "missing_key"
    MISSING_IMAGE = "missing_image"  # the schedule said x = 1 and no image came
    CORRUPT_IMAGE = "corrupt_image"  # unreadable or truncated JPEG
    WRONG_SIZE = "wrong_size"  # a readable JPEG of another size than the camera's
    OVERSIZED_HEADER = "oversized_header"  # a JPEG header claiming more than MAX_IMAGE_PIXELS
    OVERSIZED_IMAGE = "oversized_image"  # a payload over MAX_COMPRESSED_BYTES
    MALFORMED_KEY = "malformed_key"  # wrong frame or an invalid stamp
    MALFORMED_IMAGE = "malformed_image"  # an invalid stamp
    MALFORMED_LEDGER = "malformed_ledger"  # a ledger row that does not parse
    SKIPPED_SLOTS = "skipped_slots"  # the server fell more than max_backlog_slots behind and skipped ahead
