"""Plausibility of well-formed messages, even from a legitimate writer (pure, no ROS): refused, counted, never raised.

The rules for loss samples (:class:`LossSampleCheck`), schedules (:func:`schedule_problem`), pose keys
(:class:`PoseTrack`, with its relocalisation) and ledger rows (:func:`ledger_problem`), their bounds and reasons:
docs/security.md, "Plausibility, even from the right writer". :class:`Implausible` counts the refusals by reason
(what ``/diagnostics`` shows).
"""

from __future__ import annotations

from collections import Counter, OrderedDict
from dataclasses import dataclass, field
import math

import numpy as np

from gsrmr_common.metrics import MR_LOSS_LAMBDA
from gsrmr_common.pose2d import Pose2D
from gsrmr_common.wire import POSE_KEY_BITS, LedgerRow, LossSample, ScheduleMsg

#: The largest MR loss images in [0, 1] can have: (1 − λ)·1 + λ·(1 − (−1)).
MR_LOSS_MAX = (1.0 - MR_LOSS_LAMBDA) * 1.0 + MR_LOSS_LAMBDA * 2.0
#: :meth:`LossSampleCheck.problem` of a sample equal to the one its slot already took: dropped, not implausible.
REDELIVERED = "loss_redelivered"
#: How close a loss sample's pose must be to the robot's key of that slot (the server copies the key) [m, rad].
POSE_MATCH_TOL = 1e-6


class Implausible(Counter):
    """Refusals by reason (``Counter[str]``); :meth:`values_for_diagnostics` gives them as one JSON-able dict."""

    def values_for_diagnostics(self) -> dict[str, int]:
        """``{reason: count}`` sorted by reason."""
        return dict(sorted(self.items()))


@dataclass(frozen=True)
class ScheduleLimits:
    """What a plausible schedule looks like to its reader (slots are absolute slot indices)."""

    max_slots: int = 1000  # T bound (the scheduler's horizon is 100 by default)
    max_ahead_slots: int = 50  # first slot at most this far after now (a plan is made for the next slot)
    max_power_w: float = 0.1  # the radio's maximum transmit power [W]


def schedule_problem(schedule: ScheduleMsg, now_slot: int, limits: ScheduleLimits) -> str | None:
    """Why ``schedule`` is implausible at ``now_slot`` (``schedule_length``, ``schedule_future``, ``schedule_stale``,
    ``schedule_power``), or None."""
    n = len(schedule.x)
    if not 0 < n <= limits.max_slots:
        return "schedule_length"
    if schedule.first_slot > now_slot + limits.max_ahead_slots:
        return "schedule_future"
    if schedule.first_slot + n <= now_slot:
        return "schedule_stale"
    if np.any(np.asarray(schedule.power_w) > limits.max_power_w):
        return "schedule_power"
    return None


def ledger_problem(row: LedgerRow, now_slot: int, max_skew_slots: int = 50) -> str | None:
    """Why a ledger row is implausible at ``now_slot`` (``ledger_slot``, ``ledger_values``), or None."""
    if abs(row.slot - now_slot) > max_skew_slots:
        return "ledger_slot"
    rate_ok = math.isnan(row.uplink_rate_bps) or (math.isfinite(row.uplink_rate_bps) and row.uplink_rate_bps >= 0)
    if row.x not in (0, 1) or row.held_back not in (0, 1) or row.scene_change not in (0, 1) or row.bits_sent < 0 \
            or not rate_ok:
        return "ledger_values"
    return None


def ledger_image_sent(row: LedgerRow) -> int:
    """1 when the row's slot carried an image: its x says so and it sent more than the pose key's bits. A row with
    x = 1 and only the key's bits (an image asked for with no fresh frame to send) counts as a key slot, so the
    scheduler's uplink cap and probe clock never count an image the server did not compose."""
    return int(row.x == 1 and row.bits_sent > POSE_KEY_BITS)


@dataclass
class PoseTrack:
    """Pose keys continuous within the robot's top speed, with a relocalisation rule (module docstring)."""

    max_speed_mps: float
    slot_s: float
    slack_m: float = 0.3
    relocalise_keys: int = 5
    last: tuple[int, float, float] | None = None  # (slot, a_m, b_m) of the newest accepted key
    relocalisations: int = 0
    _pending: list[tuple[int, float, float]] = field(default_factory=list)

    def __post_init__(self) -> None:
        if not (self.max_speed_mps > 0 and self.slot_s > 0 and self.slack_m >= 0 and self.relocalise_keys >= 1):
            raise ValueError("pose track: max_speed_mps, slot_s > 0, slack_m ≥ 0, relocalise_keys ≥ 1")

    def reach_m(self, slots: int) -> float:
        """How far the robot can move in ``slots`` slots (top speed, plus the slack)."""
        return self.max_speed_mps * self.slot_s * abs(slots) + self.slack_m

    def _follows(self, prev: tuple[int, float, float], slot: int, a_m: float, b_m: float) -> bool:
        return math.hypot(a_m - prev[1], b_m - prev[2]) <= self.reach_m(slot - prev[0])

    def offer(self, slot: int, a_m: float, b_m: float) -> bool:
        """True (and the track moves on) for a key that follows the track — or completes a relocalisation;
        False for a jump (kept as a relocalisation candidate)."""
        if self.last is None or self._follows(self.last, slot, a_m, b_m):
            self._pending.clear()
            if self.last is None or slot >= self.last[0]:
                self.last = (slot, a_m, b_m)
            return True
        if self._pending and not self._follows(self._pending[-1], slot, a_m, b_m):
            self._pending.clear()
        self._pending.append((slot, a_m, b_m))
        if len(self._pending) >= self.relocalise_keys:
            self.last = max(self._pending)
            self._pending.clear()
            self.relocalisations += 1
            return True
        return False


class LossSampleCheck:
    """The loss-sample rules of the module docstring; the ledger rows and keys come from the reader's own inputs."""

    def __init__(self, keep_slots: int = 2000) -> None:
        self.keep = int(keep_slots)
        self._seen: OrderedDict[int, LossSample] = OrderedDict()  # slot → the sample it took

    def problem(self, sample: LossSample, image_sent: bool | None,
                key_pose: Pose2D | None) -> str | None:
        """Why ``sample`` is implausible: ``loss_range``, ``loss_repeat`` (a second, different sample for a slot),
        ``loss_key_slot`` (the ledger says the slot sent no image), ``loss_unledgered`` (no ledger row for it),
        ``loss_pose`` (not at the slot's reported key); :data:`REDELIVERED` for the very sample the slot already took
        (a latched writer's history, read again by a reader that subscribed again: not a lie, and not used twice);
        None when it is plausible — then its slot counts as sampled."""
        if not 0.0 <= sample.loss <= MR_LOSS_MAX:
            return "loss_range"
        if sample.slot in self._seen:
            return REDELIVERED if self._seen[sample.slot] == sample else "loss_repeat"
        if image_sent is None:
            return "loss_unledgered"
        if not image_sent:
            return "loss_key_slot"
        if key_pose is not None and not all(abs(u - v) <= POSE_MATCH_TOL for u, v in
                                            zip((sample.a_m, sample.b_m, sample.theta_rad), key_pose, strict=True)):
            return "loss_pose"
        self._seen[sample.slot] = sample
        while len(self._seen) > self.keep:
            self._seen.popitem(last=False)
        return None
