"""How old the robot's pose fix is (pure): :class:`FixAge` follows the ``map → odom`` correction each ledger row says
its key used and the distance the keys drove since, and says from which planned slot the keys' fix is stale, so that
the in-slot rule buys an image the server can fix the robot from (docs/nodes.md, "The server localizes the robot").
"""

from __future__ import annotations

import math

import numpy as np

from gsrmr_common.pose2d import Pose2D


class FixAge:
    """The age of the correction in force, in slots and metres driven (from the robot's ledger rows and keys).

    Stale, as the planner prices it: the keys drove more than ``stale_fix_m`` since the correction in force changed
    and more than half that since the last image (whose fix may still be on its way). Only once the ledger has shown
    a correction (seq > 0): a robot whose ``map → odom`` comes from elsewhere (``localization`` off or external)
    never gets one from the server, and images would not fix it.

    Args:
        stale_fix_m: the distance [m] after which a fix is stale; 0: never.
        ramp_m: past the stale point, the in-slot rule takes fades up to the median one over this distance [m].
    """

    def __init__(self, stale_fix_m: float, ramp_m: float = 0.5) -> None:
        if not (stale_fix_m >= 0 and ramp_m > 0):
            raise ValueError("fix age: stale_fix_m >= 0 and ramp_m > 0")
        self.stale_fix_m, self.ramp_m = float(stale_fix_m), float(ramp_m)
        self.seq = 0  # the newest correction the ledger named
        self.fix_slot: int | None = None  # the first slot whose key used it
        self.driven_since_fix_m = 0.0
        self.driven_since_image_m = 0.0
        self.stale_plans = 0  # plans that priced a stale fix
        self._last: tuple[int, Pose2D] | None = None  # the newest key (slot, pose in map)

    def ledger(self, slot: int, x: int, correction_seq: int) -> None:
        """A ledger row: ``x`` 1 when an image left in ``slot``; ``correction_seq`` the correction its key used."""
        if correction_seq > self.seq:
            self.seq, self.fix_slot, self.driven_since_fix_m = int(correction_seq), int(slot), 0.0
        if x:
            self.driven_since_image_m = 0.0

    def key(self, slot: int, pose: Pose2D) -> None:
        """An accepted pose key (map; m, rad): the distance from the previous key counts as driven."""
        if self._last is not None and slot > self._last[0]:
            step_m = math.hypot(pose[0] - self._last[1][0], pose[1] - self._last[1][1])
            self.driven_since_fix_m += step_m
            self.driven_since_image_m += step_m
        if self._last is None or slot > self._last[0]:
            self._last = (int(slot), Pose2D.of(pose))

    def slots_since_fix(self, now_slot: int) -> int:
        """Slots since the correction in force reached the keys (−1: none yet)."""
        return -1 if self.fix_slot is None else int(now_slot - self.fix_slot)

    def explore(self, poses: np.ndarray, pose: Pose2D | None) -> np.ndarray | None:
        """The in-slot rule's exploration fraction per planned slot for a stale fix: 0 until the predicted keys
        (``poses``, rows (a_m, b_m, theta_rad) from ``pose``, the newest key) make it stale, then rising to 0.5 (any
        fade at or above the median one) over ``ramp_m``. None when no planned slot is stale."""
        if self.stale_fix_m <= 0 or self.seq == 0 or len(poses) == 0:
            return None
        start = np.asarray(pose[:2] if pose is not None else poses[0, :2], dtype=np.float64)
        path = np.vstack([start, poses[:, :2]])
        ahead_m = np.cumsum(np.hypot(*np.diff(path, axis=0).T))
        past_m = np.minimum(self.driven_since_fix_m + ahead_m - self.stale_fix_m,
                            self.driven_since_image_m + ahead_m - 0.5 * self.stale_fix_m)
        if not np.any(past_m > 0):
            return None
        self.stale_plans += 1
        return 0.5 * np.clip(past_m / self.ramp_m, 0.0, 1.0)

    def diagnostic_values(self, now_slot: int) -> dict[str, object]:
        """What ``/diagnostics`` shows of it."""
        return {"correction_seq": self.seq, "slots_since_fix": self.slots_since_fix(now_slot),
                "driven_since_fix_m": round(self.driven_since_fix_m, 3), "stale_fix_plans": self.stale_plans}
