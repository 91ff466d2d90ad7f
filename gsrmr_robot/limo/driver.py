"""LIMO base driver over pyserial (no rclpy): enable, stream commands, watchdog, odometry, reconnect.

Its io and tx threads, the watchdog and the reconnect: ``docs/limo.md``, "Driver"; the ROS node around it:
:mod:`gsrmr_robot.limo.node`. Times are host monotonic seconds (``clock``); all public methods are thread-safe.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
import contextlib
from dataclasses import dataclass, field
import threading
import time
from typing import Any

import serial

from gsrmr_common.pose2d import Pose2D
from gsrmr_robot.limo import kinematics as kin
from gsrmr_robot.limo import protocol as proto
from gsrmr_robot.limo.odometry import Odometry2D

DEFAULT_PORT = "/dev/ttyTHS1"
DEFAULT_BAUD = 460800

EventCallback = Callable[[str, str], None]  # (level: "info"|"warn"|"error", text)
FrameObserver = Callable[[proto.Frame, Any], None]


@dataclass
class ImuSample:
    """Latest IMU readings (SI): accel m/s² (unit unconfirmed on hardware), gyro rad/s, Euler rad."""

    t_s: float
    accel: proto.ImuAccel | None
    gyro: proto.ImuGyro | None
    euler: proto.ImuEuler


@dataclass
class LinkStatus:
    """Serial link state; ``connects`` counts successful opens, ``disconnects`` lost links."""

    port: str
    connected: bool = False
    connects: int = 0
    disconnects: int = 0
    failed_opens: int = 0
    last_error: str = ""
    last_rx_t_s: float | None = None
    next_retry_in_s: float = 0.0


@dataclass
class DriverSnapshot:
    """Everything the ROS node publishes, copied under the driver lock."""

    t_s: float
    pose: Pose2D
    velocity: kin.BodyVelocity
    pose_covariance: list[float]
    twist_covariance: list[float]
    heading_from_imu: bool
    motion_mode: int  # the mode used for commands and feedback (MotionMode, UNKNOWN before 0x211 in auto)
    motion_mode_param: str
    system_state: proto.SystemState | None
    imu: ImuSample | None
    wheel_odometry: proto.WheelOdometry | None
    link: LinkStatus
    parser: dict[str, int]
    unknown_ids: dict[int, int]
    implausible_frames: int
    frames_by_id: dict[int, int]
    commands_sent: int
    command_active: bool  # a fresh (not timed-out) command is being streamed
    last_command: proto.MotionCommand
    enables_sent: int
    events: list[tuple[float, str, str]] = field(default_factory=list)
    write_timeouts: int = 0


class LimoDriver:
    """Serial driver of one LIMO base. Use :meth:`start`, :meth:`set_command`, :meth:`close`."""

    def __init__(self, port: str = DEFAULT_PORT, baudrate: int = DEFAULT_BAUD, *,
                 command_rate_hz: float = 50.0, cmd_timeout_s: float = 0.5, motion_mode: str = "auto",
                 heading_source: str = "imu",
                 limits: kin.Limits = kin.DEFAULT_LIMITS, geometry: kin.Geometry = kin.DEFAULT_GEOMETRY,
                 reconnect_min_s: float = 0.1, reconnect_max_s: float = 1.0, read_timeout_s: float = 0.02,
                 reenable_period_s: float = 1.0, max_odom_gap_s: float = 0.25,
                 clock: Callable[[], float] = time.monotonic, on_event: EventCallback | None = None,
                 frame_observer: FrameObserver | None = None,
                 parser_factory: Callable[[], proto.FrameParser] = proto.FrameParser) -> None:
        if command_rate_hz <= 0 or cmd_timeout_s <= 0:
            raise ValueError("command_rate_hz and cmd_timeout_s must be > 0")
        if not 0 < reconnect_min_s <= reconnect_max_s:
            raise ValueError("need 0 < reconnect_min_s <= reconnect_max_s")
        self.port_url = port
        self.baudrate = int(baudrate)
        self.command_rate_hz = float(command_rate_hz)
        self.cmd_timeout_s = float(cmd_timeout_s)
        self.motion_mode_param = motion_mode
        self._forced_mode = kin.parse_motion_mode(motion_mode)
        self.limits = limits
        self.geometry = geometry
        self.reconnect_min_s = reconnect_min_s
        self.reconnect_max_s = reconnect_max_s
        self.read_timeout_s = read_timeout_s
        self.reenable_period_s = reenable_period_s
        self._clock = clock
        self.on_event = on_event
        self.frame_observer = frame_observer
        # Callbacks run in the io thread; keep them short.
        self.on_odometry: Callable[[DriverSnapshot], None] | None = None
        self.on_imu: Callable[[ImuSample], None] | None = None

        self._lock = threading.RLock()
        self._port_lock = threading.Lock()
        self._stop = threading.Event()
        self._write_failed = threading.Event()
        self._port: serial.SerialBase | None = None
        self._parser = parser_factory()
        self._odom = Odometry2D(heading_source, max_gap_s=max_odom_gap_s)
        self._link = LinkStatus(port)
        self._events: deque[tuple[float, str, str]] = deque(maxlen=50)
        self._cmd: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._cmd_t: float | None = None
        self._last_wire = proto.MotionCommand()
        self._commands_sent = 0
        self._enables_sent = 0
        self._last_enable_t = -1e9
        self._system: proto.SystemState | None = None
        self._accel: proto.ImuAccel | None = None
        self._gyro: proto.ImuGyro | None = None
        self._imu: ImuSample | None = None
        self._wheels: proto.WheelOdometry | None = None
        self._implausible = 0
        self._frames_by_id: dict[int, int] = {}
        self._threads: list[threading.Thread] = []
        self.callback_errors = 0
        self.write_timeouts = 0
        self._write_timeouts_in_row = 0
        self._feedback_ready = False  # a 0x221 has been accepted on the current connection

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> LimoDriver:
        """Start the io and tx threads (returns self). Opening happens in the background."""
        if self._threads:
            return self
        self._stop.clear()
        self._threads = [threading.Thread(target=self._io_loop, name="limo-io", daemon=True),
                         threading.Thread(target=self._tx_loop, name="limo-tx", daemon=True)]
        for t in self._threads:
            t.start()
        return self

    def close(self, stop_frames: int = 3) -> None:
        """Send a few zero commands if connected, stop the threads, close the port."""
        with self._lock:
            self._cmd_t = None
        for _ in range(stop_frames):
            self._write(proto.encode_message(proto.MotionCommand()))
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2.0)
        self._threads = []
        self._drop_port("closed by driver", report=False)

    def __enter__(self) -> LimoDriver:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ commands
    def set_command(self, vx_mps: float, wz_radps: float, vy_mps: float = 0.0) -> None:
        """Latest body-velocity command (base_link, REP-103); valid for ``cmd_timeout_s``."""
        with self._lock:
            self._cmd = (float(vx_mps), float(wz_radps), float(vy_mps))
            self._cmd_t = self._clock()

    def stop_motion(self) -> None:
        """Forget the command: zeros are streamed from the next tick."""
        with self._lock:
            self._cmd_t = None

    def set_motion_mode(self, name: str) -> None:
        """'auto' | 'diff' | 'ackermann' | 'mecanum' (ValueError otherwise); takes effect at the next tick."""
        forced = kin.parse_motion_mode(name)
        with self._lock:
            self._forced_mode = forced
            self.motion_mode_param = name

    def set_heading_source(self, name: str) -> None:
        """'imu' | 'gyro_integration' (ValueError otherwise)."""
        with self._lock:
            self._odom.set_heading_source(name)

    def motion_mode(self) -> int:
        """The mode used now: the forced mode, or 0x211 d6 in 'auto' (UNKNOWN before the first 0x211)."""
        with self._lock:
            return self._effective_mode()

    def _effective_mode(self) -> int:
        if self._forced_mode is not None:
            return self._forced_mode
        if self._system is None or self._system.motion_mode not in (0, 1, 2):
            return proto.MotionMode.UNKNOWN
        return self._system.motion_mode

    def wire_command(self, now_s: float | None = None) -> tuple[proto.MotionCommand, bool]:
        """(0x111 to send now, command_active). Zero when timed out, absent, the mode is unknown, or no
        0x221 has been accepted yet on this connection (so odometry never misses the start of a motion)."""
        now = self._clock() if now_s is None else now_s
        with self._lock:
            active = self._cmd_t is not None and now - self._cmd_t <= self.cmd_timeout_s
            if not active or not self._feedback_ready:
                return proto.MotionCommand(), active
            vx, wz, vy = self._cmd
            return kin.command_to_wire(self._effective_mode(), vx, wz, vy, self.limits, self.geometry), True

    # ------------------------------------------------------------------ state
    def snapshot(self) -> DriverSnapshot:
        """A consistent copy of the driver state."""
        now = self._clock()
        with self._lock:
            active = self._cmd_t is not None and now - self._cmd_t <= self.cmd_timeout_s
            link = LinkStatus(**self._link.__dict__)
            return DriverSnapshot(
                t_s=now, pose=self._odom.pose, velocity=self._odom.velocity,
                pose_covariance=self._odom.pose_covariance(), twist_covariance=self._odom.twist_covariance(),
                heading_from_imu=self._odom.using_imu, motion_mode=self._effective_mode(),
                motion_mode_param=self.motion_mode_param, system_state=self._system, imu=self._imu,
                wheel_odometry=self._wheels, link=link, parser=self._parser.stats.as_dict(),
                unknown_ids=dict(self._parser.stats.unknown_ids), implausible_frames=self._implausible,
                frames_by_id=dict(self._frames_by_id), commands_sent=self._commands_sent,
                command_active=active,
                last_command=self._last_wire, enables_sent=self._enables_sent, events=list(self._events),
                write_timeouts=self.write_timeouts)

    def reset_odometry(self, pose: Pose2D | None = None) -> None:
        """Restart odometry at ``pose``."""
        with self._lock:
            self._odom.reset(pose or Pose2D())

    # ------------------------------------------------------------------ internals
    def _event(self, level: str, text: str) -> None:
        self._events.append((self._clock(), level, text))
        if self.on_event is not None:
            with contextlib.suppress(Exception):  # a logging callback must not kill the io thread
                self.on_event(level, text)

    def _open(self) -> serial.SerialBase:
        port = serial.serial_for_url(self.port_url, do_not_open=True, baudrate=self.baudrate,
                                     bytesize=serial.EIGHTBITS, parity=serial.PARITY_NONE,
                                     stopbits=serial.STOPBITS_ONE, rtscts=False, xonxoff=False, dsrdtr=False,
                                     timeout=self.read_timeout_s, write_timeout=0.5)
        if "://" not in self.port_url:
            port.exclusive = True  # flock: a second driver on the same device fails to open (and retries)
        port.open()
        with contextlib.suppress(serial.SerialException, OSError, NotImplementedError):
            port.reset_input_buffer()
        return port

    def _drop_port(self, reason: str, report: bool = True) -> None:
        with self._port_lock:
            port, self._port = self._port, None
        if port is None:
            return
        with contextlib.suppress(serial.SerialException, OSError):
            port.close()
        with self._lock:
            self._feedback_ready = False
            self._link.connected = False
            self._link.last_error = reason
            if report:
                self._link.disconnects += 1
        if report:
            self._event("error", f"LIMO link lost on {self.port_url}: {reason}; reconnecting")

    def _write(self, data: bytes) -> bool:
        with self._port_lock:
            port = self._port
            if port is None:
                return False
            try:
                port.write(data)
                self._write_timeouts_in_row = 0
                return True
            except serial.SerialTimeoutException as exc:
                # pyserial also raises this when the thread was merely descheduled past the timeout after
                # the bytes went out (loaded CPU): only a run of them means a stuck link
                with self._lock:
                    self.write_timeouts += 1
                    self._write_timeouts_in_row += 1
                    stuck = self._write_timeouts_in_row >= 5
                    if stuck:
                        self._link.last_error = f"write: {exc} ×5"
                if stuck:
                    self._write_failed.set()
                return False
            except (serial.SerialException, OSError) as exc:
                with self._lock:
                    self._link.last_error = f"write: {exc}"
                self._write_failed.set()
                return False

    def _send_enable(self) -> None:
        ok = self._write(proto.encode_message(proto.ControlModeConfig(proto.ControlMode.COMMANDED)))
        if ok and self._forced_mode == proto.MotionMode.MECANUM:
            ok = self._write(proto.encode_message(proto.ControlModeConfig(proto.ControlMode.COMMANDED, True)))
        if ok:
            with self._lock:
                self._enables_sent += 1
                self._last_enable_t = self._clock()

    def _io_loop(self) -> None:
        backoff = self.reconnect_min_s
        fails_in_row = reported_max = 0
        while not self._stop.is_set():
            try:
                port = self._open()
            except (serial.SerialException, OSError, ValueError) as exc:
                with self._lock:
                    self._link.failed_opens += 1
                    self._link.last_error = f"open: {exc}"
                    self._link.next_retry_in_s = backoff
                    fails_in_row += 1
                # report the first failure, the first at full backoff, then every 10th
                at_max = backoff >= self.reconnect_max_s
                reported_max += at_max
                if fails_in_row == 1 or (at_max and reported_max % 10 == 1):
                    self._event("warn", f"cannot open {self.port_url} ({exc}); retry in {backoff:.2f} s")
                self._stop.wait(backoff)
                backoff = min(2 * backoff, self.reconnect_max_s)
                continue
            backoff = self.reconnect_min_s
            fails_in_row = reported_max = 0
            self._write_failed.clear()
            with self._lock:
                self._parser.reset()
                self._link.connected = True
                self._link.connects += 1
                self._link.next_retry_in_s = 0.0
                n = self._link.connects
            with self._port_lock:
                self._port = port
            self._event("info", f"LIMO link up on {self.port_url} (connection #{n}); enabling command mode")
            self._send_enable()
            self._read_until_failure(port)

    def _read_until_failure(self, port: serial.SerialBase) -> None:
        while not self._stop.is_set():
            if self._write_failed.is_set():
                self._drop_port(self._link.last_error or "write failed")
                return
            try:
                waiting = port.in_waiting
                data = port.read(waiting if waiting > 0 else 1)
            except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
                # TypeError/AttributeError: pyserial internals after a concurrent close.
                self._drop_port(f"read: {exc}")
                return
            if data:
                self._on_bytes(data, self._clock())

    def _on_bytes(self, data: bytes, t_s: float) -> None:
        odom_snapshot = False
        imu_sample: ImuSample | None = None
        observed: list[tuple[proto.Frame, Any]] = []
        reenable = False
        with self._lock:
            self._link.last_rx_t_s = t_s
            for frame in self._parser.feed(data, t_s):
                try:
                    msg = proto.decode_message(frame)
                except proto.ProtocolError:
                    self._implausible += 1
                    continue
                self._frames_by_id[frame.can_id] = self._frames_by_id.get(frame.can_id, 0) + 1
                observed.append((frame, msg))
                if isinstance(msg, proto.MotionState):
                    self._feedback_ready = True
                    vel = kin.feedback_to_body(self._effective_mode(), msg, self.geometry)
                    self._odom.update_velocity(vel, t_s)
                    odom_snapshot = True
                elif isinstance(msg, proto.ImuEuler):
                    self._odom.update_imu_yaw(msg.yaw_rad)
                    self._imu = imu_sample = ImuSample(t_s, self._accel, self._gyro, msg)
                elif isinstance(msg, proto.ImuGyro):
                    self._gyro = msg
                elif isinstance(msg, proto.ImuAccel):
                    self._accel = msg
                elif isinstance(msg, proto.SystemState):
                    if self._system is None or self._system.motion_mode != msg.motion_mode:
                        self._events.append((t_s, "info", f"base motion mode {msg.motion_mode:#04x}"))
                    self._system = msg
                    if (msg.control_mode != proto.ControlMode.COMMANDED
                            and t_s - self._last_enable_t >= self.reenable_period_s):
                        reenable = True
                elif isinstance(msg, proto.WheelOdometry):
                    self._wheels = msg
        if reenable:
            self._send_enable()
        if self.frame_observer is not None:
            for frame, msg in observed:
                self._callback(self.frame_observer, frame, msg)
        if imu_sample is not None and self.on_imu is not None:
            self._callback(self.on_imu, imu_sample)
        if odom_snapshot and self.on_odometry is not None:
            self._callback(self.on_odometry, self.snapshot())

    def _callback(self, fn: Callable[..., Any], *args: Any) -> None:
        """Run a user callback; an exception in it is reported, never allowed to kill the io thread."""
        try:
            fn(*args)
        except Exception as exc:
            with self._lock:
                self.callback_errors += 1
                first = self.callback_errors == 1
            if first:
                self._event("error", f"callback {getattr(fn, '__name__', fn)} raised {exc!r} (reported once)")

    def _tx_loop(self) -> None:
        period = 1.0 / self.command_rate_hz
        next_t = time.monotonic()
        while not self._stop.is_set():
            cmd, _ = self.wire_command()
            if self._write(proto.encode_message(cmd)):
                with self._lock:
                    self._commands_sent += 1
                    self._last_wire = cmd
            next_t += period
            delay = next_t - time.monotonic()
            if delay < -period:  # fell behind (suspended, overloaded): do not burst
                next_t = time.monotonic()
                delay = 0.0
            self._stop.wait(max(0.0, delay))
