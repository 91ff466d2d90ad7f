"""AgileX LIMO serial protocol (pure: no I/O, no rclpy): 14-byte frames, message codecs, a resynchronising parser.

Reference: ``docs/limo_protocol.md`` in the shared docs (§2 frame format, §3 message catalogue, §7 worked frames).
The frame, the encoding rules and the parser's defences beyond the checksum: ``docs/limo.md``, "Frames and units"
and "Parser and the checksum's blind spots". Multi-byte fields are big-endian; every dataclass field carries its
unit in its name (``_mps`` m/s, ``_radps`` rad/s, ``_rad`` rad, ``_v`` volt, ``_mps2`` m/s², ``_mm`` millimetre).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
import enum
import math
import struct
from typing import ClassVar

HEADER = 0x55
FRAME_LEN = 14
DATA_LEN = 8

ID_MOTION_COMMAND = 0x111
ID_CONTROL_MODE = 0x421
ID_SYSTEM_STATE = 0x211
ID_MOTION_STATE = 0x221
ID_WHEEL_ODOMETRY = 0x311
ID_IMU_ACCEL = 0x321
ID_IMU_GYRO = 0x322
ID_IMU_EULER = 0x323
# IDs defined in limo_protocol.h that this package does not decode (actuator states, §3.5).
ID_ACTUATOR_HS = tuple(range(0x251, 0x255))
ID_ACTUATOR_LS = tuple(range(0x261, 0x265))

INT16_MIN = -32768
INT16_MAX = 32767


class ProtocolError(ValueError):
    """A byte string that is not a valid LIMO frame or message."""


class VehicleState(enum.IntEnum):
    """0x211 d0."""

    NORMAL = 0x00
    EMERGENCY_STOP = 0x01
    EXCEPTION = 0x02


class ControlMode(enum.IntEnum):
    """0x211 d1 and 0x421 d0."""

    STANDBY = 0x00  # RC / app / standby
    COMMANDED = 0x01  # software ("CAN") command mode
    UART = 0x02


class MotionMode(enum.IntEnum):
    """0x211 d6 (``limo_protocol.h`` enum)."""

    DIFF = 0x00  # four-wheel differential (also tracked)
    ACKERMANN = 0x01
    MECANUM = 0x02
    UNKNOWN = 0xFF


# 0x211 d4–d5 error bits (§3.3): bit → short name.
ERROR_BITS: dict[int, str] = {
    0x0001: "battery_low_fault",
    0x0002: "battery_low_warning",
    0x0004: "rc_signal_lost",
    0x0008: "motor1_driver_error",
    0x0010: "motor2_driver_error",
    0x0020: "motor3_driver_error",
    0x0040: "motor4_driver_error",
    0x0080: "steer_encoder_error",
    0x0100: "drive_status_error",
    0x0200: "hl_comm_error",
}


def decode_error_bits(error_code: int) -> list[str]:
    """Names of the set bits of a 0x211 error code (unknown bits as ``bit_0x....``)."""
    names = []
    for bit in range(16):
        mask = 1 << bit
        if error_code & mask:
            names.append(ERROR_BITS.get(mask, f"bit_0x{mask:04x}"))
    return names


def saturate_int16(value: float, scale: float = 1.0) -> int:
    """``round(value * scale)`` clamped to the int16 range; NaN → 0, ±inf → the range ends."""
    x = float(value) * scale
    if math.isnan(x):
        return 0
    if x >= INT16_MAX:
        return INT16_MAX
    if x <= INT16_MIN:
        return INT16_MIN
    return max(INT16_MIN, min(INT16_MAX, round(x)))


def checksum(data: bytes) -> int:
    """Frame checksum: sum of the 8 data bytes, low 8 bits."""
    return sum(data) & 0xFF


def encode_frame(can_id: int, data: bytes, count: int = 0) -> bytes:
    """Wrap 8 data bytes into a 14-byte frame (header, length, big-endian ID, data, count, checksum)."""
    if len(data) != DATA_LEN:
        raise ProtocolError(f"frame data must be {DATA_LEN} bytes, got {len(data)}")
    if not 0 <= can_id <= 0xFFFF:
        raise ProtocolError(f"frame id must fit 16 bits, got {can_id:#x}")
    if not 0 <= count <= 0xFF:
        raise ProtocolError(f"count must fit 8 bits, got {count}")
    return bytes((HEADER, FRAME_LEN, can_id >> 8, can_id & 0xFF, *data, count, checksum(data)))


@dataclass(frozen=True)
class Frame:
    """One received frame. ``t_s``: host receive time of the chunk that completed it [s, caller's clock]."""

    can_id: int
    data: bytes
    count: int = 0
    t_s: float = 0.0

    def to_bytes(self) -> bytes:
        """The 14 wire bytes of this frame."""
        return encode_frame(self.can_id, self.data, self.count)


def decode_frame(raw: bytes) -> Frame:
    """Parse exactly one 14-byte frame; raise :class:`ProtocolError` on a bad header, length or checksum."""
    if len(raw) != FRAME_LEN:
        raise ProtocolError(f"a frame is {FRAME_LEN} bytes, got {len(raw)}")
    if raw[0] != HEADER:
        raise ProtocolError(f"bad header byte {raw[0]:#04x}")
    if raw[1] != FRAME_LEN:
        raise ProtocolError(f"bad length byte {raw[1]:#04x}")
    data = bytes(raw[4:12])
    if checksum(data) != raw[13]:
        raise ProtocolError(f"bad checksum {raw[13]:#04x}, expected {checksum(data):#04x}")
    return Frame((raw[2] << 8) | raw[3], data, raw[12])


# ---------------------------------------------------------------------------------------------
# Messages


@dataclass(frozen=True)
class MotionCommand:
    """0x111 host → base. Velocities of ``base_link`` (REP-103: +x forward, +y left, +z CCW)."""

    ID: ClassVar[int] = ID_MOTION_COMMAND
    linear_mps: float = 0.0
    angular_radps: float = 0.0
    lateral_mps: float = 0.0
    steering_raw: float = 0.0  # inner-wheel angle [rad] / angle scale (Ackermann only)

    def data(self) -> bytes:
        """The 8 data bytes (×1000 each, int16 big-endian, saturated)."""
        return struct.pack(">hhhh", *(saturate_int16(x, 1000) for x in (
            self.linear_mps, self.angular_radps, self.lateral_mps, self.steering_raw)))

    @classmethod
    def from_data(cls, data: bytes) -> MotionCommand:
        """Decode 8 data bytes."""
        v, w, vy, s = struct.unpack(">hhhh", data)
        return cls(v / 1000, w / 1000, vy / 1000, s / 1000)


@dataclass(frozen=True)
class ControlModeConfig:
    """0x421 host → base: ``d0`` control-mode request (0x01 = commanded); ``d2`` = 0x01: go mecanum."""

    ID: ClassVar[int] = ID_CONTROL_MODE
    control_mode: int = ControlMode.COMMANDED
    mecanum_switch: bool = False

    def data(self) -> bytes:
        """The 8 data bytes."""
        return bytes((self.control_mode & 0xFF, 0, 0x01 if self.mecanum_switch else 0, 0, 0, 0, 0, 0))

    @classmethod
    def from_data(cls, data: bytes) -> ControlModeConfig:
        """Decode 8 data bytes."""
        return cls(data[0], data[2] == 0x01)


@dataclass(frozen=True)
class SystemState:
    """0x211 base → host."""

    ID: ClassVar[int] = ID_SYSTEM_STATE
    vehicle_state: int = VehicleState.NORMAL
    control_mode: int = ControlMode.STANDBY
    battery_voltage_v: float = 0.0
    error_code: int = 0
    motion_mode: int = MotionMode.DIFF
    count: int = 0

    def data(self) -> bytes:
        """The 8 data bytes (battery ×10 as uint16, saturated to 0..65535)."""
        volts = self.battery_voltage_v * 10
        deci_v = 0 if math.isnan(volts) else max(0, min(0xFFFF, round(volts)))
        return struct.pack(">BBHHBB", self.vehicle_state & 0xFF, self.control_mode & 0xFF, deci_v,
                           self.error_code & 0xFFFF, self.motion_mode & 0xFF, self.count & 0xFF)

    @classmethod
    def from_data(cls, data: bytes) -> SystemState:
        """Decode 8 data bytes."""
        vs, cm, deci_v, err, mm, count = struct.unpack(">BBHHBB", data)
        return cls(vs, cm, deci_v / 10, err, mm, count)

    @property
    def errors(self) -> list[str]:
        """Names of the set error bits."""
        return decode_error_bits(self.error_code)


@dataclass(frozen=True)
class MotionState:
    """0x221 base → host: measured velocities (same units and layout as 0x111)."""

    ID: ClassVar[int] = ID_MOTION_STATE
    linear_mps: float = 0.0
    angular_radps: float = 0.0
    lateral_mps: float = 0.0
    steering_raw: float = 0.0

    def data(self) -> bytes:
        """The 8 data bytes."""
        return MotionCommand(self.linear_mps, self.angular_radps, self.lateral_mps, self.steering_raw).data()

    @classmethod
    def from_data(cls, data: bytes) -> MotionState:
        """Decode 8 data bytes."""
        v, w, vy, s = struct.unpack(">hhhh", data)
        return cls(v / 1000, w / 1000, vy / 1000, s / 1000)


@dataclass(frozen=True)
class WheelOdometry:
    """0x311 base → host: cumulative wheel travel, int32 big-endian; unit assumed mm (§3.6, [inferred])."""

    ID: ClassVar[int] = ID_WHEEL_ODOMETRY
    left_mm: int = 0
    right_mm: int = 0

    def data(self) -> bytes:
        """The 8 data bytes (int32 saturated)."""
        sat = lambda x: max(-(2**31), min(2**31 - 1, int(x)))  # noqa: E731
        return struct.pack(">ii", sat(self.left_mm), sat(self.right_mm))

    @classmethod
    def from_data(cls, data: bytes) -> WheelOdometry:
        """Decode 8 data bytes."""
        left, right = struct.unpack(">ii", data)
        return cls(left, right)


def _imu_pack(a: float, b: float, c: float, scale: float, count: int) -> bytes:
    return struct.pack(">hhhBB", saturate_int16(a, scale), saturate_int16(b, scale), saturate_int16(c, scale),
                       0, count & 0xFF)


@dataclass(frozen=True)
class ImuAccel:
    """0x321: linear acceleration, wire ×0.01 (treated as m/s², §3.7 notes the unit is unconfirmed)."""

    ID: ClassVar[int] = ID_IMU_ACCEL
    x_mps2: float = 0.0
    y_mps2: float = 0.0
    z_mps2: float = 0.0
    count: int = 0

    def data(self) -> bytes:
        """The 8 data bytes."""
        return _imu_pack(self.x_mps2, self.y_mps2, self.z_mps2, 100, self.count)

    @classmethod
    def from_data(cls, data: bytes) -> ImuAccel:
        """Decode 8 data bytes."""
        x, y, z, _, count = struct.unpack(">hhhBB", data)
        return cls(x / 100, y / 100, z / 100, count)


_DEG = math.pi / 180


@dataclass(frozen=True)
class ImuGyro:
    """0x322: angular rate; wire ×0.01 deg/s, fields here in rad/s."""

    ID: ClassVar[int] = ID_IMU_GYRO
    x_radps: float = 0.0
    y_radps: float = 0.0
    z_radps: float = 0.0
    count: int = 0

    def data(self) -> bytes:
        """The 8 data bytes."""
        return _imu_pack(self.x_radps, self.y_radps, self.z_radps, 100 / _DEG, self.count)

    @classmethod
    def from_data(cls, data: bytes) -> ImuGyro:
        """Decode 8 data bytes."""
        x, y, z, _, count = struct.unpack(">hhhBB", data)
        return cls(x / 100 * _DEG, y / 100 * _DEG, z / 100 * _DEG, count)


@dataclass(frozen=True)
class ImuEuler:
    """0x323: Euler angles, wire order **yaw, pitch, roll**, ×0.01 deg; fields here in rad."""

    ID: ClassVar[int] = ID_IMU_EULER
    yaw_rad: float = 0.0
    pitch_rad: float = 0.0
    roll_rad: float = 0.0
    count: int = 0

    def data(self) -> bytes:
        """The 8 data bytes."""
        return _imu_pack(self.yaw_rad, self.pitch_rad, self.roll_rad, 100 / _DEG, self.count)

    @classmethod
    def from_data(cls, data: bytes) -> ImuEuler:
        """Decode 8 data bytes."""
        y, p, r, _, count = struct.unpack(">hhhBB", data)
        return cls(y / 100 * _DEG, p / 100 * _DEG, r / 100 * _DEG, count)


Message = (MotionCommand | ControlModeConfig | SystemState | MotionState | WheelOdometry | ImuAccel | ImuGyro
           | ImuEuler)

MESSAGE_TYPES: dict[int, type] = {cls.ID: cls for cls in (MotionCommand, ControlModeConfig, SystemState,
                                                           MotionState, WheelOdometry, ImuAccel, ImuGyro,
                                                           ImuEuler)}
# Every ID of limo_protocol.h: known (not counted as unknown) even when not decoded.
KNOWN_IDS = frozenset(MESSAGE_TYPES) | frozenset(ID_ACTUATOR_HS) | frozenset(ID_ACTUATOR_LS)


def encode_message(msg: Message, count: int = 0) -> bytes:
    """The 14-byte frame of a message."""
    return encode_frame(msg.ID, msg.data(), count)


def decode_message(frame: Frame) -> Message | None:
    """Decode a frame's payload by ID; None for IDs without a codec (e.g. actuator states).

    Raises :class:`ProtocolError` when the payload is implausible (an unknown enum value or a
    physical value far outside the LIMO's range): such a frame passed its checksum only by accident.
    """
    cls = MESSAGE_TYPES.get(frame.can_id)
    if cls is None:
        return None
    msg = cls.from_data(frame.data)
    _check_plausible(msg)
    return msg


# Plausibility bounds: generous, several times the LIMO's specification (1 m/s, 0.49 rad steering).
MAX_PLAUSIBLE_SPEED_MPS = 5.0
MAX_PLAUSIBLE_RATE_RADPS = 20.0
MAX_PLAUSIBLE_STEERING_RAW = 1.0
MAX_PLAUSIBLE_BATTERY_V = 30.0


def _check_plausible(msg: Message) -> None:
    if isinstance(msg, (MotionState, MotionCommand)):
        if (abs(msg.linear_mps) > MAX_PLAUSIBLE_SPEED_MPS or abs(msg.lateral_mps) > MAX_PLAUSIBLE_SPEED_MPS
                or abs(msg.angular_radps) > MAX_PLAUSIBLE_RATE_RADPS
                or abs(msg.steering_raw) > MAX_PLAUSIBLE_STEERING_RAW):
            raise ProtocolError(f"implausible velocities {msg}")
    elif isinstance(msg, SystemState):
        if (msg.vehicle_state not in VehicleState.__members__.values()
                or msg.control_mode not in ControlMode.__members__.values()
                or msg.motion_mode not in MotionMode.__members__.values()
                or msg.battery_voltage_v > MAX_PLAUSIBLE_BATTERY_V):
            raise ProtocolError(f"implausible system state {msg}")
    elif isinstance(msg, ImuEuler):
        if abs(msg.yaw_rad) > math.pi + 1e-9 or abs(msg.pitch_rad) > math.pi / 2 + 1e-9 \
                or abs(msg.roll_rad) > math.pi + 1e-9:
            raise ProtocolError(f"implausible Euler angles {msg}")
    elif isinstance(msg, ControlModeConfig) and msg.control_mode not in ControlMode.__members__.values():
        raise ProtocolError(f"implausible control mode {msg}")


# ---------------------------------------------------------------------------------------------
# Stream parser


@dataclass
class ParserStats:
    """Counters of a :class:`FrameParser` (every byte and frame outcome is counted once)."""

    bytes_in: int = 0
    frames_ok: int = 0  # frames returned to the caller
    skipped_bytes: int = 0  # bytes discarded while hunting for a header (garbage, lost sync)
    bad_length: int = 0  # 0x55 followed by a byte other than 0x0E
    bad_checksum: int = 0
    unknown_id: int = 0  # valid checksum, ID not in the LIMO catalogue (dropped)
    unconfirmed_id: int = 0  # valid checksum, known ID not (yet) seen as a stream (dropped)
    count_mismatch: int = 0  # valid checksum, count byte inconsistent with that ID's stream (dropped)
    unknown_ids: dict[int, int] = field(default_factory=dict)  # unknown ID → times seen

    def errors(self) -> int:
        """Total rejected frames (not counting skipped bytes)."""
        return (self.bad_length + self.bad_checksum + self.unknown_id + self.unconfirmed_id
                + self.count_mismatch)

    def as_dict(self) -> dict[str, int]:
        """Scalar counters as a dict (for diagnostics)."""
        return {k: v for k, v in self.__dict__.items() if isinstance(v, int)}


class FrameParser:
    """Byte-stream → frames. Resynchronises on any input; never raises on data.

    Algorithm: keep a buffer; find the next 0x55; if the next byte is not 0x0E, drop only the 0x55 (so
    the length byte itself is examined as a possible header); once 14 bytes are buffered, verify the
    checksum; on failure drop only the header byte and hunt again (a real header hidden inside a
    corrupted frame is not lost). Valid frames then pass the ID, confirmation and count checks
    (``docs/limo.md``, "Parser and the checksum's blind spots"): an ID is dispatched once seen
    ``confirm_frames`` times within ``confirm_window_s``, this frame included — a real stream (≥ 10 Hz)
    confirms within 0.1–0.4 s and stays confirmed, while a single-bit ID corruption such as 0x221 → 0x321
    appears as isolated frames; per ID the count byte must follow the step learnt from that ID's stream, 0
    (constant, as every known transmitter sends) or +1 (rolling), and a stream re-locks after
    ``relock_frames`` mutually consistent frames.

    ``confirm_frames=1`` disables ID confirmation; ``check_count=False`` disables the count check.
    """

    def __init__(self, *, known_ids: frozenset[int] | None = KNOWN_IDS, confirm_frames: int = 5,
                 confirm_window_s: float = 1.0, check_count: bool = True, relock_frames: int = 3) -> None:
        if confirm_frames < 1:
            raise ValueError("confirm_frames must be ≥ 1")
        self.known_ids = known_ids
        self.confirm_frames = confirm_frames
        self.confirm_window_s = confirm_window_s
        self.check_count = check_count
        self.relock_frames = max(1, relock_frames)
        self.stats = ParserStats()
        self._buf = bytearray()
        self._seen: dict[int, deque[float]] = {}
        self._count_ref: dict[int, int] = {}
        self._count_cand: dict[int, tuple[int, int]] = {}
        self._count_step: dict[int, int] = {}

    def reset(self) -> None:
        """Forget buffered bytes and per-ID stream state (after a reconnect); counters are kept."""
        self._buf.clear()
        self._seen.clear()
        self._count_ref.clear()
        self._count_cand.clear()
        self._count_step.clear()

    def feed(self, data: bytes, t_s: float = 0.0) -> list[Frame]:
        """Consume bytes received at host time ``t_s`` [s]; return the frames completed and accepted."""
        self.stats.bytes_in += len(data)
        buf = self._buf
        buf += data
        out: list[Frame] = []
        pos = 0
        n = len(buf)
        while True:
            start = buf.find(HEADER, pos)
            if start < 0:
                self.stats.skipped_bytes += n - pos
                pos = n
                break
            self.stats.skipped_bytes += start - pos
            pos = start
            if n - pos < 2:
                break
            if buf[pos + 1] != FRAME_LEN:
                self.stats.bad_length += 1
                pos += 1  # re-examine the length byte as a header
                continue
            if n - pos < FRAME_LEN:
                break
            data8 = bytes(buf[pos + 4:pos + 12])
            if checksum(data8) != buf[pos + 13]:
                self.stats.bad_checksum += 1
                pos += 1
                continue
            frame = Frame((buf[pos + 2] << 8) | buf[pos + 3], data8, buf[pos + 12], t_s)
            pos += FRAME_LEN
            if self._admit(frame):
                self.stats.frames_ok += 1
                out.append(frame)
        del buf[:pos]
        return out

    def _admit(self, frame: Frame) -> bool:
        cid = frame.can_id
        if self.known_ids is not None and cid not in self.known_ids:
            self.stats.unknown_id += 1
            self.stats.unknown_ids[cid] = self.stats.unknown_ids.get(cid, 0) + 1
            return False
        if self.confirm_frames > 1:
            seen = self._seen.setdefault(cid, deque(maxlen=self.confirm_frames))
            seen.append(frame.t_s)
            if len(seen) < self.confirm_frames or frame.t_s - seen[0] > self.confirm_window_s:
                self.stats.unconfirmed_id += 1
                return False
        if self.check_count:
            c = frame.count
            ref = self._count_ref.get(cid)
            step = self._count_step.get(cid)
            if ref is not None:
                d = (c - ref) & 0xFF
                ok = d == step if step is not None else d in (0, 1)
                if not ok:
                    cand, run = self._count_cand.get(cid, (None, 0))
                    run = run + 1 if cand is not None and (c - cand) & 0xFF in (0, 1) else 1
                    if run < self.relock_frames:
                        self._count_cand[cid] = (c, run)
                        self.stats.count_mismatch += 1
                        return False
                    d = (c - cand) & 0xFF  # re-lock on relock_frames consistent frames
                self._count_step[cid] = d
            self._count_ref[cid] = c
            self._count_cand.pop(cid, None)
        return True
