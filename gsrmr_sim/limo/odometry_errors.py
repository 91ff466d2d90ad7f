"""What a real LIMO's odometry gets wrong, for the mock base and its offline twin (pure): the wheels' distance scale,
skid-steer slip that grows with the turn rate, the IMU's yaw bias and random walk, and the operator's start-pose error.
The numbers and their sources: the scene file's ``odometry`` section; the model: docs/world.md, "Odometry that slips".
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
import math

import numpy as np

from gsrmr_common.pose2d import Pose2D


@dataclass(frozen=True)
class OdometryErrors:
    """The error model (zero everywhere: perfect odometry). Units in the names; an IMU yaw in rad."""

    scale_error: float = 0.0  # wheel speed reported / true − 1
    turn_slip_per_radps: float = 0.0  # extra forward speed over-reported per rad/s of turn rate (skid steering)
    imu_bias_radps: float = 0.0  # the gyro's bias left after calibration, integrated into the IMU yaw (σ of a draw)
    imu_random_walk_rad_per_sqrt_s: float = 0.0  # the IMU yaw's random walk
    start_error_m: float = 0.0  # the operator's placement error, σ per axis
    start_error_rad: float = 0.0  # … and of the heading

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not math.isfinite(value) or (f.name != "scale_error" and value < 0) or value <= -1:
                raise ValueError(f"odometry errors: {f.name} must be finite (and ≥ 0 but scale_error > −1), "
                                 f"got {value}")

    def scaled(self, k: float) -> OdometryErrors:
        """Every error times ``k`` (0: perfect odometry), for sweeps."""
        if not (math.isfinite(k) and k >= 0):
            raise ValueError(f"odometry error scale must be ≥ 0, got {k}")
        return replace(self, **{f.name: getattr(self, f.name) * k for f in fields(self)})

    @property
    def perfect(self) -> bool:
        """No error at all."""
        return all(getattr(self, f.name) == 0 for f in fields(self))

    def reported_speed(self, v_mps: float, wz_radps: float) -> float:
        """The forward speed the wheels report while the base moves at ``v_mps``, turning at ``wz_radps``."""
        return v_mps * (1.0 + self.scale_error + self.turn_slip_per_radps * abs(wz_radps))


@dataclass
class OdometryErrorDraw:
    """One robot's errors, drawn from a seed: its IMU bias and start-pose error, and the IMU's random walk as it goes.

    Args:
        errors: The model.
        seed: The run's seed (the channel seed unless given: ``gsrmr-demo --odometry-seed``).
    """

    errors: OdometryErrors
    seed: int

    def __post_init__(self) -> None:
        rng = np.random.default_rng([int(self.seed), 0x0D0])
        e = self.errors
        self.imu_bias_radps = float(rng.normal(0.0, e.imu_bias_radps)) if e.imu_bias_radps else 0.0
        dx, dy = (rng.normal(0.0, e.start_error_m, 2) if e.start_error_m else (0.0, 0.0))
        dt = float(rng.normal(0.0, e.start_error_rad)) if e.start_error_rad else 0.0
        self.start_error = Pose2D(float(dx), float(dy), dt)  # the true start in the frame of the believed one
        self._walk_rng = np.random.default_rng([int(self.seed), 0x1A1])
        self.imu_offset_rad = 0.0  # the IMU's yaw minus the true yaw, as it grows

    def true_start(self, believed: Pose2D) -> Pose2D:
        """Where the robot really starts when the operator believes it at ``believed`` (``map_from_odom``)."""
        return Pose2D.of(believed).compose(self.start_error)

    def advance(self, dt_s: float) -> float:
        """Let ``dt_s`` seconds pass; the IMU's yaw offset from the true yaw [rad] after them."""
        if dt_s > 0:
            walk = self.errors.imu_random_walk_rad_per_sqrt_s
            step = float(self._walk_rng.normal(0.0, walk * math.sqrt(dt_s))) if walk else 0.0
            self.imu_offset_rad += self.imu_bias_radps * dt_s + step
        return self.imu_offset_rad
