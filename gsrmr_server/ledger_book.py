"""What the server knows of a slot before it composes it (pure, no ROS): the robot's ledger row and the schedule.

The robot publishes its ledger row for slot k (``gsrmr/ledger``) before its uploads, so the row says whether an
image follows (the robot decides in the slot: the schedule alone cannot say). :meth:`LedgerBook.take` gives the
slot's :class:`SlotPlan`, which decides whether the server waits for — and counts as missing — an image.
"""

from __future__ import annotations

from dataclasses import dataclass

from gsrmr_common.wire import LedgerRow, ScheduleMsg


@dataclass(frozen=True)
class SlotPlan:
    """One slot's expectations: the robot's ledger row (None: none arrived) and the schedule's x (None: none)."""

    ledger: LedgerRow | None = None
    scheduled_x: int | None = None

    @property
    def image_expected(self) -> bool | None:
        """Whether an image should come: the ledger row's x, else the schedule's, else unknown (None)."""
        if self.ledger is not None:
            return bool(self.ledger.x)
        return None if self.scheduled_x is None else bool(self.scheduled_x)


class LedgerBook:
    """The robot's ledger rows by slot, the newest ``keep`` of them, until their slots are composed; the latest
    schedule (``schedule``, None before the first)."""

    def __init__(self, keep: int = 200) -> None:
        if keep < 1:
            raise ValueError("keep must be ≥ 1")
        self.keep = int(keep)
        self._rows: dict[int, LedgerRow] = {}
        self.schedule: ScheduleMsg | None = None

    def add(self, row: LedgerRow) -> None:
        """A row arrived (a repeat of its slot replaces the earlier one); the oldest is dropped past ``keep``."""
        self._rows[row.slot] = row
        if len(self._rows) > self.keep:
            del self._rows[min(self._rows)]

    def image_sent(self, slot: int) -> bool | None:
        """The robot's word on ``slot``: whether it sent an image (its row's x), None without a row."""
        row = self._rows.get(slot)
        return None if row is None else bool(row.x)

    def take(self, slot: int) -> SlotPlan:
        """The plan of ``slot`` being composed now (its row leaves the book)."""
        entry = self.schedule.lookup(slot) if self.schedule is not None else None
        return SlotPlan(self._rows.pop(slot, None), None if entry is None else entry[0])
