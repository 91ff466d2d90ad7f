"""What the scheduler takes from the graph, after its plausibility rules: the robot's ledger rows and pose keys, the
server's loss samples and slot info (pure, no ROS; the rules themselves: :mod:`gsrmr_common.plausibility`)."""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

from gsrmr_common.plausibility import (
    REDELIVERED,
    Implausible,
    LossSampleCheck,
    PoseTrack,
    ledger_image_sent,
    ledger_problem,
)
from gsrmr_common.pose2d import Pose2D
from gsrmr_common.wire import LedgerRow, LossSample, MRSlotInfo

#: Slots whose ledger rows and pose keys the loss-sample check remembers.
MEMORY_SLOTS = 2000
#: An ``mr/slot_info`` names a slot within this many of now (as a ledger row does).
SLOT_INFO_SKEW_SLOTS = 50
#: A loss sample waits this many slots for its slot's ledger row, then it is refused (``loss_unledgered``).
LOSS_WAIT_SLOTS = 20
#: At most this many loss samples wait for their ledger rows.
LOSS_WAITING_MAX = 16



@dataclass(frozen=True)
class Refusal:
    """A loss sample refused, and why (a :class:`~gsrmr_common.plausibility.Implausible` reason)."""

    sample: LossSample
    reason: str


class SchedulerIntake:
    """The scheduler's inputs as the planner may take them; every refusal counted in :attr:`implausible`.

    A loss sample is taken only for a slot the robot's ledger says carried an image, at the key the robot reported
    for it; one that arrives before its slot's ledger row waits for it (``LOSS_WAIT_SLOTS`` at most). Samples of
    slots before the first ledger row heard are not used and counted ``loss_samples_unverified`` (at start-up
    discovery may match the server before the robot), not implausible.
    """

    def __init__(self, max_speed_mps: float, slot_s: float) -> None:
        self.implausible = Implausible()
        self.poses = PoseTrack(max_speed_mps, slot_s)
        self.loss_check = LossSampleCheck(MEMORY_SLOTS)
        self._ledger_x: OrderedDict[int, int] = OrderedDict()  # slot → what the robot's ledger row says it did
        self._key_poses: OrderedDict[int, Pose2D] = OrderedDict()  # slot → its accepted key
        self._waiting: dict[int, LossSample] = {}  # samples whose slot's ledger row has not come yet
        self._first_ledger_slot: int | None = None
        self.loss_samples_unverified = 0
        self.loss_samples_redelivered = 0

    def ledger(self, row: LedgerRow, now_slot: int) -> tuple[int | None, LossSample | None]:
        """A ledger row. Returns:
            ``x`` (1 when an image left) of a plausible row, else None; the loss sample that waited for it, if any.
        """
        reason = ledger_problem(row, now_slot)
        if reason is None and row.slot in self._ledger_x:
            reason = "ledger_repeat"  # one row per slot: the first stands
        if reason:
            self.implausible[reason] += 1
            return None, None
        x = ledger_image_sent(row)  # what left, not what was asked for
        _remember(self._ledger_x, row.slot, x)
        first = self._first_ledger_slot
        self._first_ledger_slot = row.slot if first is None else min(row.slot, first)
        return x, self._waiting.pop(row.slot, None)

    def key(self, slot: int, pose: Pose2D) -> bool:
        """A valid pose key; False (counted ``pose_jump``) when it moved faster than the robot drives."""
        if not self.poses.offer(slot, pose[0], pose[1]):
            self.implausible["pose_jump"] += 1
            return False
        _remember(self._key_poses, slot, pose)
        return True

    def slot_info(self, info: MRSlotInfo, now_slot: int) -> bool:
        """An ``mr/slot_info``: True when it names a slot near now."""
        if abs(info.slot - now_slot) > SLOT_INFO_SKEW_SLOTS:
            self.implausible["slot_info_slot"] += 1
            return False
        return True

    def loss(self, sample: LossSample) -> bool | Refusal | None:
        """A loss sample. Returns:
            True to take it now; a :class:`Refusal` (counted implausible) to log; None when it is not taken
            otherwise: it waits for its ledger row, was taken already (redelivered) or cannot be verified.
        """
        x = self._ledger_x.get(sample.slot)
        reason = self.loss_check.problem(sample, None if x is None else bool(x), self._key_poses.get(sample.slot))
        if reason is None:
            return True
        if reason == REDELIVERED:  # the server's latched history, read again after this reader resubscribed
            self.loss_samples_redelivered += 1
            return None
        if reason == "loss_unledgered" and len(self._waiting) < LOSS_WAITING_MAX and sample.slot not in self._waiting:
            self._waiting[sample.slot] = sample
            return None
        return self._refuse(sample, reason)

    def expire(self, now_slot: int) -> list[Refusal]:
        """Refuse the waiting samples whose ledger row did not come within ``LOSS_WAIT_SLOTS``."""
        late = [slot for slot in self._waiting if slot < now_slot - LOSS_WAIT_SLOTS]
        refused = [self._refuse(self._waiting.pop(slot), "loss_unledgered") for slot in late]
        return [r for r in refused if r is not None]

    def _refuse(self, sample: LossSample, reason: str) -> Refusal | None:
        """Count a refused sample: implausible, or unverified (no ledger row for a slot before the first one heard:
        then None)."""
        if reason == "loss_unledgered" and (self._first_ledger_slot is None or sample.slot < self._first_ledger_slot):
            self.loss_samples_unverified += 1
            return None
        self.implausible[reason] += 1
        return Refusal(sample, reason)

    def problems(self) -> list[str]:
        """What ``/diagnostics`` warns about: the implausible inputs refused."""
        return ["implausible inputs refused: " + ", ".join(f"{k} {n}" for k, n in sorted(self.implausible.items()))
                ] if self.implausible else []

    def counters(self) -> dict[str, int]:
        """What ``/diagnostics`` and the exit summary count beside :attr:`implausible`."""
        return {"relocalisations": self.poses.relocalisations,
                "loss_samples_unverified": self.loss_samples_unverified,
                "loss_samples_redelivered": self.loss_samples_redelivered}


def _remember(book: OrderedDict, slot: int, value: object) -> None:
    """``book[slot] = value``, the oldest slots forgotten past ``MEMORY_SLOTS``."""
    book[slot] = value
    while len(book) > MEMORY_SLOTS:
        book.popitem(last=False)
