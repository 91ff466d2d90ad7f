"""Where the robot will be (pure): future poses along the scene's route loop at a nominal speed."""

from __future__ import annotations

import math

import numpy as np

from gsrmr_common.pose2d import Pose2D
from gsrmr_common.route import LoopPath


class RoutePredictor:
    """Future poses along a closed route at a nominal speed."""

    def __init__(self, waypoints: np.ndarray | list, speed_mps: float) -> None:
        if not (speed_mps > 0 and math.isfinite(speed_mps)):
            raise ValueError("route speed must be > 0")
        self.path = LoopPath(waypoints)
        self.speed_mps = float(speed_mps)
        self._dense_s = np.linspace(0.0, self.path.length_m, max(200, int(self.path.length_m / 0.01)),
                                    endpoint=False)
        self._dense_xy = self.path.points_at(self._dense_s)

    def nearest_s(self, a_m: float, b_m: float) -> float:
        """Arc length of the route point nearest to (a, b)."""
        d2 = (self._dense_xy[:, 0] - a_m) ** 2 + (self._dense_xy[:, 1] - b_m) ** 2
        return float(self._dense_s[int(np.argmin(d2))])

    def predict(self, pose: Pose2D | None, n_slots: int, slot_s: float) -> np.ndarray:
        """n_slots×3 poses (a_m, b_m, theta_rad) for the next slots (route start if pose is None)."""
        s0 = 0.0 if pose is None else self.nearest_s(pose[0], pose[1])
        s = s0 + self.speed_mps * slot_s * np.arange(1, n_slots + 1)
        xy = self.path.points_at(s)
        theta = np.array([self.path.heading_at(v) for v in s])
        return np.column_stack([xy, theta])
