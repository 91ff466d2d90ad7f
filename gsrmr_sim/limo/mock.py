"""A byte-exact mock LIMO base on a pseudo-terminal, with fault injection and a true pose.

What it accepts, streams and injects, and the in-process API (:class:`MockLimo`): docs/limo.md, "Mock" (the
serial protocol: the reference docs/limo.md cites, §2–§4). The true pose is (x_m, y_m, yaw_rad) of ``base_link``
in ``map``. No rclpy here: the console script is :func:`gsrmr_sim.limo.mock_ros.main`, which also publishes the
true pose (``--no-ros``: the pty base only).
"""

from __future__ import annotations

import argparse
import contextlib
from dataclasses import dataclass
import errno
import math
import os
import random
import select
import sys
import threading
import time
import tty

from gsrmr_common.pose2d import Pose2D, wrap_angle
from gsrmr_robot.limo import kinematics as kin
from gsrmr_robot.limo import protocol as proto
from gsrmr_sim.limo.odometry_errors import OdometryErrorDraw, OdometryErrors

# The mock's true pose (nav_msgs/Odometry, gsrmr_sim.limo.mock_ros), read by the simulated camera, radio and
# route follower. Relative, so that each robot of a fleet has its own (/robot2/sim/ground_truth/odom); a node in
# the root namespace resolves it to /sim/ground_truth/odom.
GROUND_TRUTH_TOPIC = "sim/ground_truth/odom"


@dataclass(frozen=True)
class FaultConfig:
    """Fault injection on the base → host byte stream (rates are probabilities, 0 = off)."""

    garbage_rate: float = 0.0
    bit_flip_rate: float = 0.0
    drop_rate: float = 0.0
    byte_error_rate: float = 0.0
    silence_every_s: float = 0.0
    silence_s: float = 0.0
    reopen_every_s: float = 0.0
    reopen_gap_s: float = 1.0
    seed: int | None = None


class MockLimo:
    """The simulated base. Thread-safe; :meth:`start` runs it in a background thread."""

    def __init__(self, link_path: str, *, motion_mode: int = proto.MotionMode.DIFF,
                 cmd_timeout_s: float = 0.3, rate_hz: float = 50.0, battery_voltage_v: float = 12.3,
                 faults: FaultConfig | None = None,
                 record: bool = False, start_pose: Pose2D = Pose2D(),
                 limits: kin.Limits = kin.DEFAULT_LIMITS, geometry: kin.Geometry = kin.DEFAULT_GEOMETRY,
                 odometry: OdometryErrorDraw | None = None) -> None:
        if rate_hz <= 0 or cmd_timeout_s <= 0:
            raise ValueError("rate_hz and cmd_timeout_s must be > 0")
        self.link_path = os.path.abspath(link_path)
        self.motion_mode = int(motion_mode)
        self.cmd_timeout_s = cmd_timeout_s
        self.rate_hz = rate_hz
        self.battery_voltage_v = battery_voltage_v
        self.faults = faults = faults or FaultConfig()
        self.record = record
        self.limits = limits
        self.geometry = geometry
        self._rng = random.Random(faults.seed)
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._master: int | None = None
        self._slave: int | None = None
        self.slave_name = ""
        host_ids = frozenset({proto.ID_MOTION_COMMAND, proto.ID_CONTROL_MODE})
        self._parser = proto.FrameParser(known_ids=host_ids, confirm_frames=1, check_count=False)
        self._x, self._y, self._yaw = start_pose
        self.odometry = odometry  # what its wheel odometry and IMU get wrong (None: nothing)
        self._imu_offset_rad = 0.0
        self._pose_stamp_ns = 0
        self._tick_late_s: float | None = None  # the latest ticks' lateness (take_tick_lateness_s)
        self._vel = kin.BodyVelocity()
        self._cmd: proto.MotionCommand | None = None
        self._cmd_t = -math.inf
        self._applied = proto.MotionCommand()
        self.control_mode = proto.ControlMode.STANDBY
        self.error_code = 0
        self.commands_received = 0
        self.enables_received = 0
        self.frames_sent = 0
        self.frames_corrupted = 0
        self.reopens = 0
        self.sent_frames: list[tuple[float, bytes, bool]] = []
        self._silent_until = -math.inf
        self._reopen_at: float | None = None
        self._pending_reopen_gap_s: float | None = None
        self._t0 = time.monotonic()
        self._last_silence_t = self._t0
        self._last_reopen_t = self._t0

    # ------------------------------------------------------------------ public API
    def start(self) -> MockLimo:
        """Open the pty, create the symlink and start streaming (returns self)."""
        self._open_pty()
        self._thread = threading.Thread(target=self._run, name="mock-limo", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop the thread, close the pty and remove the symlink."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._close_pty()

    def __enter__(self) -> MockLimo:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def true_pose(self) -> Pose2D:
        """True pose of base_link in map: (x_m, y_m, yaw_rad), yaw unwrapped."""
        with self._lock:
            return Pose2D(self._x, self._y, self._yaw)

    def true_pose_stamped(self) -> tuple[int, Pose2D]:
        """(system time in ns at which the pose is true — the integration tick that made it —, true pose):
        what a motion-capture system would stamp it with (0 before the first tick: the start pose)."""
        with self._lock:
            return self._pose_stamp_ns, Pose2D(self._x, self._y, self._yaw)

    def take_tick_lateness_s(self) -> float | None:
        """The largest lateness [s] of the integration ticks since the last call: how long after its place in the
        ``1/rate_hz`` schedule each tick ran (None: no tick since)."""
        with self._lock:
            late, self._tick_late_s = self._tick_late_s, None
        return late

    def true_velocity(self) -> kin.BodyVelocity:
        """Velocity applied over the current tick (base_link frame)."""
        with self._lock:
            return self._vel

    def is_port_open(self) -> bool:
        """False during a close-and-reopen gap."""
        with self._lock:
            return self._master is not None

    def silence(self, duration_s: float) -> None:
        """Send nothing for ``duration_s`` (commands are still received and obeyed)."""
        with self._lock:
            self._silent_until = time.monotonic() + duration_s

    def reopen(self, gap_s: float) -> None:
        """Close the port (within one loop turn; the link path disappears), reopen a new pty ``gap_s`` later."""
        with self._lock:
            self._pending_reopen_gap_s = gap_s

    # ------------------------------------------------------------------ pty
    def _open_pty(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        name = os.ttyname(slave)
        tmp = f"{self.link_path}.{os.getpid()}.tmp"
        if os.path.lexists(tmp):
            os.unlink(tmp)
        os.symlink(name, tmp)
        os.replace(tmp, self.link_path)  # atomic: the path never points to a stale pty
        with self._lock:
            self._master, self._slave, self.slave_name = master, slave, name
            self._parser.reset()

    def _close_pty(self) -> None:
        with self._lock:
            master, slave = self._master, self._slave
            self._master = self._slave = None
        try:
            if os.path.islink(self.link_path):
                os.unlink(self.link_path)
        except OSError:
            pass
        for fd in (master, slave):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)

    # ------------------------------------------------------------------ main loop
    def _run(self) -> None:
        period = 1.0 / self.rate_hz
        next_t = time.monotonic() + period
        last_t = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            timeout = max(0.0, next_t - now)
            master = self._master
            if master is None:
                self._stop.wait(min(timeout, 0.01))
            else:
                try:
                    ready, _, _ = select.select([master], [], [], timeout)
                except (OSError, ValueError):
                    ready = []
                if ready:
                    self._read_commands(master)
            now = time.monotonic()
            self._scheduled_faults(now)
            if now >= next_t:
                with self._lock:
                    self._tick_late_s = max(self._tick_late_s or 0.0, now - next_t)
                self._tick(now - last_t, now)
                last_t = now
                next_t += period
                if next_t < now - period:
                    next_t = now + period

    def _read_commands(self, master: int) -> None:
        try:
            data = os.read(master, 4096)
        except OSError as exc:
            if exc.errno not in (errno.EAGAIN, errno.EIO, errno.EBADF):  # EIO: nobody has the slave open
                print(f"mock LIMO: pty read failed: {exc}", file=sys.stderr, flush=True)
            return
        now = time.monotonic()
        with self._lock:
            for frame in self._parser.feed(data, now):
                try:
                    msg = proto.decode_message(frame)
                except proto.ProtocolError:
                    continue
                if isinstance(msg, proto.ControlModeConfig):
                    self.enables_received += 1
                    if msg.control_mode in (proto.ControlMode.COMMANDED, proto.ControlMode.UART):
                        self.control_mode = msg.control_mode
                    if msg.mecanum_switch:
                        self.motion_mode = proto.MotionMode.MECANUM
                elif isinstance(msg, proto.MotionCommand):
                    self.commands_received += 1
                    if self.control_mode != proto.ControlMode.STANDBY:
                        self._cmd, self._cmd_t = msg, now

    def _scheduled_faults(self, now: float) -> None:
        f = self.faults
        with self._lock:
            if self._pending_reopen_gap_s is not None:
                self._close_pty()
                self._reopen_at = now + self._pending_reopen_gap_s
                self._pending_reopen_gap_s = None
                self.control_mode = proto.ControlMode.STANDBY
                self._cmd = None
            if self._reopen_at is not None and now >= self._reopen_at:
                self._reopen_at = None
                self._open_pty()
                self.reopens += 1
            due = f.reopen_every_s > 0 and now - self._last_reopen_t >= f.reopen_every_s
            if due and self._master is not None:
                self._last_reopen_t = now
                self.reopen(f.reopen_gap_s)
            if f.silence_every_s > 0 and f.silence_s > 0 and now - self._last_silence_t >= f.silence_every_s:
                self._last_silence_t = now
                self._silent_until = now + f.silence_s

    def _tick(self, dt: float, now: float) -> None:
        with self._lock:
            # 1) integrate the true pose with the velocity applied over the elapsed tick
            v = self._vel
            yaw0 = self._yaw
            self._yaw += v.wz_radps * dt
            ym = 0.5 * (yaw0 + self._yaw)
            self._x += (v.vx_mps * math.cos(ym) - v.vy_mps * math.sin(ym)) * dt
            self._y += (v.vx_mps * math.sin(ym) + v.vy_mps * math.cos(ym)) * dt
            self._pose_stamp_ns = time.time_ns()  # the system (ROS) time this pose is true at
            if self.odometry is not None:
                self._imu_offset_rad = self.odometry.advance(dt)
            # 2) report that velocity and the state
            frames = [self._system_state(), self._motion_state(v), self._euler()]
            # 3) apply the latest command for the next tick (own watchdog: stop when commands stop)
            fresh = self._cmd is not None and now - self._cmd_t <= self.cmd_timeout_s
            if fresh and self.control_mode != proto.ControlMode.STANDBY:
                cmd = self._cmd
                clamp = kin.command_to_wire(proto.MotionMode.MECANUM, cmd.linear_mps, cmd.angular_radps,
                                            cmd.lateral_mps, self.limits, self.geometry)
                steer = max(-self.limits.max_inner_angle_rad, min(self.limits.max_inner_angle_rad,
                            kin.inner_angle_from_raw(cmd.steering_raw, self.geometry)))
                g = self.geometry
                steer_raw = steer / (g.left_angle_scale if steer > 0 else g.right_angle_scale)
                clamped = proto.MotionCommand(clamp.linear_mps, clamp.angular_radps, clamp.lateral_mps,
                                              steer_raw)
                self._vel = kin.wire_to_body(self.motion_mode, clamped, self.geometry)
                self._applied = clamped
            else:
                self._vel = kin.BodyVelocity()
                self._applied = proto.MotionCommand()
            if now < self._silent_until or self._master is None:
                return
            out = bytearray()
            for raw in frames:
                out += self._inject(raw, now)
            try:
                os.write(self._master, bytes(out))
            except OSError as exc:
                if exc.errno not in (errno.EAGAIN, errno.EIO, errno.EBADF):
                    print(f"mock LIMO: pty write failed: {exc}", file=sys.stderr, flush=True)

    def _system_state(self) -> bytes:
        return proto.encode_message(proto.SystemState(
            proto.VehicleState.NORMAL, self.control_mode, self.battery_voltage_v, self.error_code, self.motion_mode))

    def _motion_state(self, v: kin.BodyVelocity) -> bytes:
        applied = self._applied
        if self.motion_mode == proto.MotionMode.ACKERMANN:
            return proto.encode_message(proto.MotionState(v.vx_mps, 0.0, 0.0, applied.steering_raw))
        vx = v.vx_mps if self.odometry is None else self.odometry.errors.reported_speed(v.vx_mps, v.wz_radps)
        return proto.encode_message(proto.MotionState(vx, v.wz_radps, v.vy_mps, 0.0))

    def _euler(self) -> bytes:
        yaw = wrap_angle(self._yaw + self._imu_offset_rad)
        return proto.encode_message(proto.ImuEuler(yaw, 0.0, 0.0))

    def _inject(self, raw: bytes, now: float) -> bytes:
        f = self.faults
        rng = self._rng
        out = bytearray(raw)
        corrupted = False
        if f.bit_flip_rate > 0 and rng.random() < f.bit_flip_rate:
            bit = rng.randrange(8 * len(out))
            out[bit // 8] ^= 1 << (bit % 8)
            corrupted = True
        if f.byte_error_rate > 0:
            for i in range(len(out)):
                if rng.random() < f.byte_error_rate:
                    out[i] ^= 1 << rng.randrange(8)
                    corrupted = True
        if f.drop_rate > 0:
            kept = bytearray(b for b in out if rng.random() >= f.drop_rate)
            corrupted |= len(kept) != len(out)
            out = kept
        if f.garbage_rate > 0 and rng.random() < f.garbage_rate:
            out = bytearray(rng.randrange(256) for _ in range(rng.randint(1, 20))) + out
        self.frames_sent += 1
        self.frames_corrupted += corrupted
        if self.record:
            self.sent_frames.append((now, bytes(raw), corrupted))
        return bytes(out)


# ---------------------------------------------------------------------------------------------- CLI


def build_parser() -> argparse.ArgumentParser:
    """The arguments of ``gsrmr-mock-limo`` (the console script of :mod:`gsrmr_sim.limo.mock_ros`)."""
    p = argparse.ArgumentParser(prog="gsrmr-mock-limo", description=__doc__.split("\n\n")[0])
    p.add_argument("--link", required=True, help="path of the symlink to the pty slave (the 'serial port')")
    p.add_argument("--mode", choices=("diff", "ackermann", "mecanum"), default="diff", help="motion mode")
    p.add_argument("--cmd-timeout-s", type=float, default=0.3,
                   help="own watchdog: stop after this without 0x111")
    p.add_argument("--rate-hz", type=float, default=50.0, help="feedback stream and integration rate")
    p.add_argument("--battery-v", type=float, default=12.3, help="battery voltage reported in 0x211")
    p.add_argument("--garbage-rate", type=float, default=0.0, help="per frame: P(random bytes inserted)")
    p.add_argument("--bit-flip-rate", type=float, default=0.0, help="per frame: P(one of its bits flipped)")
    p.add_argument("--byte-error-rate", type=float, default=0.0, help="per byte: P(one bit flipped)")
    p.add_argument("--drop-rate", type=float, default=0.0, help="per byte: P(byte dropped)")
    p.add_argument("--silence-every-s", type=float, default=0.0,
                   help="start a silence period every … s (0 = off)")
    p.add_argument("--silence-s", type=float, default=0.0, help="length of each silence period")
    p.add_argument("--reopen-every-s", type=float, default=0.0, help="close and reopen the port every … s")
    p.add_argument("--reopen-gap-s", type=float, default=1.0, help="time the port stays closed")
    p.add_argument("--seed", type=int, default=None, help="fault-injection RNG seed")
    p.add_argument("--start-pose", default="0,0,0", type=pose_arg,
                   help="true start pose 'x_m,y_m,yaw_rad' in the map frame")
    p.add_argument("--odometry", default="", type=odometry_arg, metavar="NAME=VALUE,...",
                   help="odometry errors (gsrmr_sim.limo.odometry_errors.OdometryErrors fields; '' = perfect)")
    p.add_argument("--odometry-seed", type=int, default=0, help="seed of the IMU bias and random walk")
    p.add_argument("--truth-log", default="", metavar="CSV",
                   help=f"also write every true pose published on {GROUND_TRUTH_TOPIC} here (stamp_ns,x_m,y_m,yaw_rad,"
                        "tick_late_ms: the ticks' largest lateness since the last row, nan: no tick)")
    p.add_argument("--ros", action=argparse.BooleanOptionalAction, default=True,
                   help=f"publish the true pose on {GROUND_TRUTH_TOPIC} (relative to the node's namespace)")
    return p


def pose_arg(text: str) -> Pose2D:
    """argparse type of ``--start-pose x_m,y_m,yaw_rad``."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"--start-pose: {err}") from err
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError("--start-pose needs three finite numbers x_m,y_m,yaw_rad")
    return Pose2D.of(values)


def odometry_arg(text: str) -> OdometryErrors:
    """argparse type of ``--odometry scale_error=0.03,imu_bias_radps=0.0002,...``."""
    values: dict[str, float] = {}
    try:
        for item in filter(None, (s.strip() for s in text.split(","))):
            name, _, value = item.partition("=")
            values[name.strip()] = float(value)
        return OdometryErrors(**values)
    except (TypeError, ValueError) as err:
        raise argparse.ArgumentTypeError(f"--odometry: {err}") from err


def mock_from_args(ns: argparse.Namespace) -> MockLimo:
    """The :class:`MockLimo` parsed :func:`build_parser` arguments describe (not started)."""
    mode = kin.parse_motion_mode(ns.mode)
    faults = FaultConfig(garbage_rate=ns.garbage_rate, bit_flip_rate=ns.bit_flip_rate, drop_rate=ns.drop_rate,
                         byte_error_rate=ns.byte_error_rate, silence_every_s=ns.silence_every_s,
                         silence_s=ns.silence_s, reopen_every_s=ns.reopen_every_s, reopen_gap_s=ns.reopen_gap_s,
                         seed=ns.seed)
    return MockLimo(ns.link, motion_mode=mode, cmd_timeout_s=ns.cmd_timeout_s, rate_hz=ns.rate_hz,
                    battery_voltage_v=ns.battery_v, faults=faults, start_pose=ns.start_pose,
                    odometry=None if ns.odometry.perfect else OdometryErrorDraw(ns.odometry, ns.odometry_seed))
