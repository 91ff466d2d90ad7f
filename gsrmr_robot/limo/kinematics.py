"""LIMO kinematics (pure): body-velocity command → 0x111 fields, and 0x221 feedback → body velocities.

Frames and signs follow REP-103 for ``base_link``: +x forward, +y left, +z up, positive yaw rate counter-clockwise
(left turn), positive steering = left; velocities in m/s and rad/s. The fields per motion mode, the limits and the
Ackermann feedback model: ``docs/limo.md``, "Kinematics".
"""

from __future__ import annotations

from dataclasses import dataclass
import math

from gsrmr_robot.limo.protocol import MotionCommand, MotionMode, MotionState

WHEELBASE_M = 0.200
TRACK_M = 0.172
MAX_INNER_ANGLE_RAD = 0.48869  # 28°
ANGLE_SCALE = 2.47  # R2 (all branches): inner-wheel angle [rad] = raw × 2.47 for both signs
MAX_LINEAR_MPS = 1.0  # LIMO manual: no-load top speed


@dataclass(frozen=True)
class Limits:
    """Command limits applied before encoding. ``max_angular_radps`` defaults to the wheel-speed bound
    of a differential base turning in place at top speed, 2·v_max/track."""

    max_linear_mps: float = MAX_LINEAR_MPS
    max_lateral_mps: float = MAX_LINEAR_MPS
    max_angular_radps: float = 2 * MAX_LINEAR_MPS / TRACK_M
    max_inner_angle_rad: float = MAX_INNER_ANGLE_RAD


@dataclass(frozen=True)
class Geometry:
    """Chassis geometry [m] and the steering scale (raw steering → inner-wheel angle [rad])."""

    wheelbase_m: float = WHEELBASE_M
    track_m: float = TRACK_M
    left_angle_scale: float = ANGLE_SCALE
    right_angle_scale: float = ANGLE_SCALE


DEFAULT_LIMITS = Limits()
DEFAULT_GEOMETRY = Geometry()


@dataclass(frozen=True)
class BodyVelocity:
    """Velocity of ``base_link`` expressed in ``base_link`` (m/s, m/s, rad/s)."""

    vx_mps: float = 0.0
    vy_mps: float = 0.0
    wz_radps: float = 0.0


def _clamp(x: float, limit: float) -> float:
    if not math.isfinite(x):
        return 0.0
    return max(-limit, min(limit, x))


def parse_motion_mode(name: str) -> MotionMode | None:
    """'diff' | 'ackermann' | 'mecanum' → MotionMode; 'auto' → None (take it from 0x211)."""
    table = {"auto": None, "diff": MotionMode.DIFF, "ackermann": MotionMode.ACKERMANN,
             "mecanum": MotionMode.MECANUM}
    try:
        return table[name.lower()]
    except KeyError:
        raise ValueError(f"motion mode must be one of {sorted(table)}, got {name!r}") from None


def ackermann_inner_angle(vx_mps: float, wz_radps: float, geometry: Geometry = DEFAULT_GEOMETRY) -> float:
    """Signed inner-wheel steering angle [rad] for a (vx, wz) command, unclamped (doc §5.2 steps 1–3).

    vx = 0 or wz = 0 → 0 (an Ackermann base cannot turn in place; this is also where the official
    driver produced NaN).
    """
    if vx_mps == 0.0 or wz_radps == 0.0 or not (math.isfinite(vx_mps) and math.isfinite(wz_radps)):
        return 0.0
    L, T = geometry.wheelbase_m, geometry.track_m
    r = vx_mps / wz_radps
    if abs(r) < T / 2:
        r = math.copysign(T / 2 + 0.01, r)
    phi = math.atan(L / r)  # central angle, sign of r
    s, c = math.sin(abs(phi)), math.cos(abs(phi))
    delta = math.atan2(2 * L * s, 2 * L * c - T * s)
    return math.copysign(delta, phi)


def command_to_wire(mode: MotionMode | int, vx_mps: float, wz_radps: float, vy_mps: float = 0.0,
                    limits: Limits = DEFAULT_LIMITS, geometry: Geometry = DEFAULT_GEOMETRY) -> MotionCommand:
    """Clamp a body-velocity command and map it to the 0x111 fields of ``mode``.

    An unknown mode (e.g. before the first 0x211) yields a zero command: the base is held still until
    the mode is known.
    """
    vx = _clamp(vx_mps, limits.max_linear_mps)
    wz = _clamp(wz_radps, limits.max_angular_radps)
    vy = _clamp(vy_mps, limits.max_lateral_mps)
    if mode == MotionMode.DIFF:
        return MotionCommand(vx, wz, 0.0, 0.0)
    if mode == MotionMode.MECANUM:
        return MotionCommand(vx, wz, vy, 0.0)
    if mode == MotionMode.ACKERMANN:
        delta = _clamp(ackermann_inner_angle(vx, wz, geometry), limits.max_inner_angle_rad)
        scale = geometry.left_angle_scale if delta > 0 else geometry.right_angle_scale
        return MotionCommand(vx, 0.0, 0.0, delta / scale)
    return MotionCommand()


def inner_angle_from_raw(steering_raw: float, geometry: Geometry = DEFAULT_GEOMETRY) -> float:
    """Inner-wheel angle [rad] from raw steering (left scale for > 0, right scale otherwise)."""
    return steering_raw * (geometry.left_angle_scale if steering_raw > 0 else geometry.right_angle_scale)


def ackermann_yaw_rate(v_mps: float, inner_angle_rad: float, geometry: Geometry = DEFAULT_GEOMETRY) -> float:
    """Yaw rate [rad/s] of the rigid bicycle model: sign(δ)·v / r, r = L/tan|δ| + T/2 (rear-axle centre)."""
    if inner_angle_rad == 0.0 or not math.isfinite(inner_angle_rad):
        return 0.0
    r = geometry.wheelbase_m / math.tan(abs(inner_angle_rad)) + geometry.track_m / 2
    return math.copysign(1.0, inner_angle_rad) * v_mps / r  # reversing with left lock turns clockwise


def feedback_to_body(mode: MotionMode | int, state: MotionState,
                     geometry: Geometry = DEFAULT_GEOMETRY) -> BodyVelocity:
    """Body velocity of ``base_link`` from a 0x221 frame in ``mode`` (unknown mode → zero)."""
    if mode == MotionMode.DIFF:
        return BodyVelocity(state.linear_mps, 0.0, state.angular_radps)
    if mode == MotionMode.MECANUM:
        return BodyVelocity(state.linear_mps, state.lateral_mps, state.angular_radps)
    if mode == MotionMode.ACKERMANN:
        delta = inner_angle_from_raw(state.steering_raw, geometry)
        return BodyVelocity(state.linear_mps, 0.0, ackermann_yaw_rate(state.linear_mps, delta, geometry))
    return BodyVelocity()


def wire_to_body(mode: MotionMode | int, cmd: MotionCommand, geometry: Geometry = DEFAULT_GEOMETRY) -> BodyVelocity:
    """What a base in ``mode`` does with a received 0x111 (used by the mock): same model as feedback."""
    return feedback_to_body(mode, MotionState(cmd.linear_mps, cmd.angular_radps, cmd.lateral_mps,
                                              cmd.steering_raw), geometry)
