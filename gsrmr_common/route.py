"""The robot's route: a closed waypoint loop and a pure-pursuit controller producing (v, ω). Pure functions, no ROS.

Both wings use it: the scheduler predicts future poses along the route, the simulator's route follower drives it
(the controller: docs/world.md, "Route and rounds"). Map frame (x forward, y left), metres, radians (yaw
counter-clockwise), m/s and rad/s. Progress is an *unwrapped* arc length ``s_m`` (it keeps growing past the loop
length: laps are ``floor(s_m / length_m)``), and the closest path point is searched only in a window ahead of the
previous progress, so the controller never jumps across the loop.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

from gsrmr_common.pose2d import Pose2D, wrap_angle


class LoopPath:
    """A closed polyline through ``waypoints`` (last point connects back to the first)."""

    def __init__(self, waypoints: tuple[tuple[float, float], ...] | list | np.ndarray) -> None:
        pts = np.asarray(waypoints, dtype=np.float64).reshape(-1, 2)
        if len(pts) < 3:
            raise ValueError("a loop needs at least 3 waypoints")
        self.points = np.vstack([pts, pts[:1]])
        self.segments = np.diff(self.points, axis=0)
        self.seg_len = np.hypot(self.segments[:, 0], self.segments[:, 1])
        if np.any(self.seg_len <= 0):
            raise ValueError("consecutive waypoints must differ")
        self.cum = np.concatenate([[0.0], np.cumsum(self.seg_len)])
        self.length_m = float(self.cum[-1])

    def _segment(self, s_m: float) -> tuple[int, float]:
        s = s_m % self.length_m
        i = int(np.clip(np.searchsorted(self.cum, s, side="right") - 1, 0, len(self.seg_len) - 1))
        return i, (s - self.cum[i]) / self.seg_len[i]

    def point_at(self, s_m: float) -> tuple[float, float]:
        """(x_m, y_m) at arc length ``s_m`` (taken modulo the loop length)."""
        i, f = self._segment(s_m)
        p = self.points[i] + f * self.segments[i]
        return float(p[0]), float(p[1])

    def points_at(self, s_m: np.ndarray) -> np.ndarray:
        """N×2 points at the arc lengths ``s_m`` (vectorised :meth:`point_at`)."""
        s = np.asarray(s_m, dtype=np.float64) % self.length_m
        i = np.clip(np.searchsorted(self.cum, s, side="right") - 1, 0, len(self.seg_len) - 1)
        f = (s - self.cum[i]) / self.seg_len[i]
        return self.points[i] + f[:, None] * self.segments[i]

    def heading_at(self, s_m: float) -> float:
        """Heading (rad) of the segment at arc length ``s_m``."""
        i, _ = self._segment(s_m)
        return math.atan2(self.segments[i, 1], self.segments[i, 0])

    def project(self, x_m: float, y_m: float, s_hint_m: float, window_m: float = 1.0) -> float:
        """Unwrapped arc length of the closest path point in [s_hint − 0.1 m, s_hint + window_m]."""
        samples = np.linspace(s_hint_m - 0.1, s_hint_m + window_m, 111)
        pts = self.points_at(samples)
        d2 = (pts[:, 0] - x_m) ** 2 + (pts[:, 1] - y_m) ** 2
        return float(max(s_hint_m, samples[int(np.argmin(d2))]))


@dataclass(frozen=True)
class PurePursuit:
    """Pure-pursuit parameters: nominal speed, look-ahead distance and turn-rate limit."""

    speed_mps: float = 0.3
    lookahead_m: float = 0.3
    max_omega_rps: float = 1.5

    def command(self, path: LoopPath, pose: Pose2D, s_hint_m: float
                ) -> tuple[float, float, float]:
        """(v_mps, omega_rps, s_m) for robot pose (x_m, y_m, theta_rad) and previous progress ``s_hint_m``.

        Curvature κ = 2·sin(α)/L_d towards the path point ``lookahead_m`` ahead of the closest one
        (α: its bearing in the robot frame, L_d: its distance); ω = v·κ clipped to ±max_omega_rps,
        and v shrinks with cos α (turning on the spot when the target is behind).
        """
        x, y, th = pose
        s = path.project(x, y, s_hint_m, window_m=max(1.0, 3.0 * self.lookahead_m))
        tx, ty = path.point_at(s + self.lookahead_m)
        dx, dy = tx - x, ty - y
        ld = math.hypot(dx, dy)
        if ld < 1e-9:
            return self.speed_mps, 0.0, s
        alpha = math.atan2(dy, dx) - th
        alpha = wrap_angle(alpha)
        v = self.speed_mps * max(0.0, math.cos(alpha))
        kappa = 2.0 * math.sin(alpha) / ld
        omega = float(np.clip((v if v > 1e-3 else self.speed_mps) * kappa, -self.max_omega_rps,
                              self.max_omega_rps))
        return v, omega, s


def laps_completed(s_m: float, length_m: float) -> int:
    """Whole laps in an unwrapped progress ``s_m``."""
    return math.floor(s_m / length_m + 1e-9)
