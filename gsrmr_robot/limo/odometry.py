"""Planar odometry of the LIMO (pure) from 0x221 body velocities and an optional IMU yaw.

Pose of ``base_link`` in ``odom`` (REP-105): x, y [m], yaw [rad, CCW; unwrapped internally, reported wrapped to
(-π, π]]. Integration, heading sources and covariances: ``docs/limo.md``, "Odometry".
"""

from __future__ import annotations

from dataclasses import dataclass
import math

from gsrmr_common.pose2d import Pose2D, wrap_angle
from gsrmr_robot.limo.kinematics import BodyVelocity

HEADING_SOURCES = ("imu", "gyro_integration")
UNESTIMATED_VAR = 1e6  # variance given to z, roll, pitch (planar odometry)


@dataclass(frozen=True)
class OdometryNoise:
    """Noise model for the covariances (standard deviations)."""

    pos_floor_m: float = 0.001
    pos_per_m: float = 0.01  # 1 cm per metre travelled
    yaw_per_rad: float = 0.02  # gyro integration: 2 % of the angle turned
    yaw_per_m: float = 0.005  # plus 5 mrad per metre travelled
    imu_yaw_std_rad: float = math.radians(1.0)
    v_std_mps: float = 0.01
    w_std_radps: float = 0.02


class Odometry2D:
    """Dead-reckoning integrator; not thread-safe (the driver serialises calls)."""

    def __init__(self, heading_source: str = "imu", max_gap_s: float = 0.25,
                 noise: OdometryNoise = OdometryNoise()) -> None:
        if heading_source not in HEADING_SOURCES:
            raise ValueError(f"heading_source must be one of {HEADING_SOURCES}, got {heading_source!r}")
        if max_gap_s <= 0:
            raise ValueError("max_gap_s must be > 0")
        self.heading_source = heading_source
        self.max_gap_s = max_gap_s
        self.noise = noise
        self.reset()

    def reset(self, pose: Pose2D = Pose2D()) -> None:
        """Restart at ``pose`` with zero covariance growth."""
        self._x, self._y, self._yaw = pose.x_m, pose.y_m, pose.theta_rad
        self._t_prev: float | None = None
        self._imu_ref: float | None = None  # (IMU yaw unwrapped at reference)
        self._imu_prev: float | None = None
        self._imu_unwrapped = 0.0
        self._yaw_at_imu_ref = pose.theta_rad
        self.distance_m = 0.0
        self.turned_rad = 0.0
        self.velocity = BodyVelocity()
        self.gaps = 0

    def set_heading_source(self, heading_source: str) -> None:
        """Switch the heading source without a jump in the current heading."""
        if heading_source not in HEADING_SOURCES:
            raise ValueError(f"heading_source must be one of {HEADING_SOURCES}, got {heading_source!r}")
        self.heading_source = heading_source
        self._yaw_at_imu_ref = self._yaw - self._imu_unwrapped

    @property
    def pose(self) -> Pose2D:
        """Current pose (yaw wrapped to (-π, π])."""
        return Pose2D(self._x, self._y, wrap_angle(self._yaw))

    @property
    def using_imu(self) -> bool:
        """True when the heading currently comes from the IMU."""
        return self.heading_source == "imu" and self._imu_ref is not None

    def update_imu_yaw(self, yaw_rad: float) -> None:
        """Feed an IMU yaw [rad] (0x323); used as the heading when ``heading_source == 'imu'``."""
        if not math.isfinite(yaw_rad):
            return
        if self._imu_prev is None:
            self._imu_prev = yaw_rad
            self._imu_unwrapped = 0.0
            self._imu_ref = 0.0
            self._yaw_at_imu_ref = self._yaw
            return
        self._imu_unwrapped += wrap_angle(yaw_rad - self._imu_prev)
        self._imu_prev = yaw_rad

    def update_velocity(self, vel: BodyVelocity, t_s: float) -> Pose2D:
        """Integrate a body velocity received at host time ``t_s`` [s]; return the new pose."""
        self.velocity = vel
        if self._t_prev is None or t_s - self._t_prev > self.max_gap_s or t_s < self._t_prev:
            if self._t_prev is not None:
                self.gaps += 1
            self._t_prev = t_s
            self._sync_imu_heading()
            return self.pose
        dt = t_s - self._t_prev
        self._t_prev = t_s
        yaw0 = self._yaw
        if self.using_imu:
            self._sync_imu_heading()
        else:
            self._yaw += vel.wz_radps * dt
        yaw_mid = 0.5 * (yaw0 + self._yaw)
        c, s = math.cos(yaw_mid), math.sin(yaw_mid)
        self._x += (vel.vx_mps * c - vel.vy_mps * s) * dt
        self._y += (vel.vx_mps * s + vel.vy_mps * c) * dt
        self.distance_m += math.hypot(vel.vx_mps, vel.vy_mps) * dt
        self.turned_rad += abs(self._yaw - yaw0)
        return self.pose

    def _sync_imu_heading(self) -> None:
        if self.using_imu:
            self._yaw = self._yaw_at_imu_ref + self._imu_unwrapped

    def pose_covariance(self) -> list[float]:
        """6×6 row-major pose covariance (x, y, z, roll, pitch, yaw)."""
        n = self.noise
        var_xy = n.pos_floor_m ** 2 + (n.pos_per_m * self.distance_m) ** 2
        if self.using_imu:
            var_yaw = n.imu_yaw_std_rad ** 2
        else:
            var_yaw = (n.yaw_per_rad * self.turned_rad) ** 2 + (n.yaw_per_m * self.distance_m) ** 2 + 1e-6
        return _diag([var_xy, var_xy, UNESTIMATED_VAR, UNESTIMATED_VAR, UNESTIMATED_VAR, var_yaw])

    def twist_covariance(self) -> list[float]:
        """6×6 row-major twist covariance (vx, vy, vz, wx, wy, wz)."""
        n = self.noise
        v, w = n.v_std_mps ** 2, n.w_std_radps ** 2
        return _diag([v, v, UNESTIMATED_VAR, UNESTIMATED_VAR, UNESTIMATED_VAR, w])


def _diag(values: list[float]) -> list[float]:
    out = [0.0] * 36
    for i, v in enumerate(values):
        out[7 * i] = float(v)
    return out
