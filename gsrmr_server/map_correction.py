"""The server's localization of the robot (pure): fixes of the robot's pose from its images, filtered into the
``map → odom`` correction the robot applies. Design: docs/nodes.md, "The server localizes the robot".

A correction X (planar, in ``map``) is applied on the left of the robot's ``map_from_odom`` parameter M₀:
``map → odom = X ∘ M₀``. It is absolute — each message stands alone, a lost one costs nothing — and numbered; the
robot's ledger row names the correction its key used (0: none), so a fix from a key made with correction c gives
``X = B ∘ key⁻¹ ∘ X_c`` (B: the registered base pose), whatever corrections came since.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

from gsrmr_common.pose2d import Pose2D, wrap_angle

UNLOCALIZED, TRACKING, LOST = "unlocalized", "tracking", "lost"
#: Why a fix is refused (counted by reason).
FIX_JUMP, FIX_UNKNOWN_CORRECTION, FIX_STALE = "fix_jump", "fix_unknown_correction", "fix_stale"


@dataclass(frozen=True)
class FilterConfig:
    """The correction filter's noise model and rules (SI units; variances of x, y [m²] and θ [rad²])."""

    fix_sigma_m: float = 0.005  # a registration's position noise (measured: median 2.5 mm, p90 5 mm)
    fix_sigma_rad: float = math.radians(0.1)
    drift_m_per_m: float = 0.05  # how fast odometry can drift: σ grows this much per metre driven …
    drift_rad_per_m: float = math.radians(1.0)
    drift_m_per_s: float = 0.002  # … and per second (an IMU's random walk, a parked robot)
    drift_rad_per_s: float = math.radians(0.02)
    first_fix_m: float = 0.5  # the first fix may move the robot this far (an operator's start error) …
    first_fix_rad: float = math.radians(20.0)
    gate: float = 16.3  # … later ones within this squared Mahalanobis distance (χ², 3 dof, p = 0.999)
    lost_after_s: float = 10.0  # no accepted fix for this long: lost (the robot keeps its last correction)
    lost_after_refusals: int = 5  # … or this many refused in a row


@dataclass(frozen=True)
class Fix:
    """One registration of a received image: the base pose B it found, the key it started from and the
    correction that key was made with (all in ``map``; stamp in seconds of the slot clock)."""

    stamp_s: float
    base: Pose2D
    key: Pose2D
    key_correction: int
    sigma_m: float | None = None  # this fix's own noise, when the registration knows it better
    sigma_rad: float | None = None


@dataclass(frozen=True)
class Correction:
    """A numbered correction: ``map → odom = X ∘ M₀`` with its variance (the ``gsrmr/map_correction`` record)."""

    seq: int
    stamp_s: float
    x: Pose2D
    variance: tuple[float, float, float]  # x [m²], y [m²], θ [rad²]


class CorrectionFilter:
    """Planar Kalman filter of the correction X over accepted fixes; each fix is gated against it."""

    def __init__(self, config: FilterConfig | None = None) -> None:
        self.config = config or FilterConfig()
        self.state = UNLOCALIZED
        self.x: Pose2D | None = None  # the estimate of X (None: no fix yet)
        self.p = np.zeros(3)  # its variances
        self.stamp_s = -math.inf  # of the newest accepted fix
        self._sent: dict[int, Pose2D] = {0: Pose2D()}  # seq → the X it carried (0: no correction)
        self.seq = 0
        self.accepted = 0
        self.refused: dict[str, int] = {}
        self._refused_in_a_row = 0

    def correction_of(self, seq: int) -> Pose2D | None:
        """The X of correction ``seq`` (0: identity), None when this server never sent it."""
        return self._sent.get(seq)

    def offer(self, fix: Fix, travelled_m: float = 0.0) -> str | None:
        """A fix; ``travelled_m`` how far the robot drove since the last accepted one. Returns why it is refused
        (counted), or None when it updated the estimate."""
        cfg = self.config
        x_c = self.correction_of(fix.key_correction)
        if x_c is None:
            return self._refuse(FIX_UNKNOWN_CORRECTION)
        if fix.stamp_s < self.stamp_s:
            return self._refuse(FIX_STALE)
        measured = fix.base.compose(fix.key.inverse()).compose(x_c)  # X = B ∘ key⁻¹ ∘ X_c
        r = np.array([(fix.sigma_m or cfg.fix_sigma_m) ** 2] * 2 + [(fix.sigma_rad or cfg.fix_sigma_rad) ** 2])
        if self.x is None:
            if measured.distance_m((0.0, 0.0)) > cfg.first_fix_m or abs(measured.theta_rad) > cfg.first_fix_rad:
                return self._refuse(FIX_JUMP)
            self.x, self.p = measured, r
        else:
            dt = max(0.0, fix.stamp_s - self.stamp_s)
            q = np.array([(cfg.drift_m_per_m * travelled_m) ** 2 + (cfg.drift_m_per_s ** 2) * dt] * 2
                         + [(cfg.drift_rad_per_m * travelled_m) ** 2 + (cfg.drift_rad_per_s ** 2) * dt])
            p = self.p + q
            innovation = np.array([measured.x_m - self.x.x_m, measured.y_m - self.x.y_m,
                                   wrap_angle(measured.theta_rad - self.x.theta_rad)])
            s = p + r
            if self.state == LOST:  # relocalizing: any fix a start error could explain
                jump = math.hypot(innovation[0], innovation[1]) > cfg.first_fix_m or abs(innovation[2]) > \
                    cfg.first_fix_rad
            else:
                jump = float(np.sum(innovation ** 2 / s)) > cfg.gate
            if jump:
                self.p = p  # the estimate aged all the same
                return self._refuse(FIX_JUMP)
            k = p / s
            update = k * innovation
            self.x = Pose2D(self.x.x_m + update[0], self.x.y_m + update[1], wrap_angle(self.x.theta_rad + update[2]))
            self.p = (1.0 - k) * p
        self.stamp_s = fix.stamp_s
        self.accepted += 1
        self._refused_in_a_row = 0
        self.state = TRACKING
        return None

    def _refuse(self, reason: str) -> str:
        self.refused[reason] = self.refused.get(reason, 0) + 1
        self._refused_in_a_row += 1
        if self.x is not None and self._refused_in_a_row >= self.config.lost_after_refusals:
            self.state = LOST
        return reason

    def update_state(self, now_s: float) -> str:
        """The localization state at ``now_s``: unlocalized (no fix yet), tracking, or lost (no fix accepted for
        ``lost_after_s``, or too many refused in a row)."""
        if self.x is not None and now_s - self.stamp_s > self.config.lost_after_s:
            self.state = LOST
        return self.state

    def next_correction(self) -> Correction | None:
        """The estimate as the next numbered correction (remembered, so that fixes from keys made with it can be
        read), None before the first fix."""
        if self.x is None:
            return None
        self.seq += 1
        self._sent[self.seq] = self.x
        while len(self._sent) > 64:  # a key names a correction of the last few seconds
            del self._sent[min(k for k in self._sent if k != 0)]
        return Correction(self.seq, self.stamp_s, self.x, (float(self.p[0]), float(self.p[1]), float(self.p[2])))
