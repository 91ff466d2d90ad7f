"""The slot clock (pure: no ROS): which slot a time is in, which slot a stamp names, and when a slot is due.

Slot ``k`` covers ROS time ``[k·τ, (k+1)·τ)`` (``τ = slot_s``; integer nanoseconds of the node's clock). Two
questions look alike and are not: **the slot we are in** at ``t`` is ``⌊t/τ⌋`` (:meth:`SlotClock.slot_at`);
**the slot a stamp names** is the nearest slot start (:meth:`SlotClock.slot_named`), because every upload is stamped
with its slot's start and a stamp a few µs early (a float round trip, another host's clock) still names its slot.
Robot, server, scheduler and the simulated radio only have to agree on τ. The timing policies built on it:
:class:`SlotTicker` (the robot's slot loop) and :class:`ComposeCursor` (the server's: a slot is composed once its
uploads are complete or at ``start + delay``, never before it starts; catch-up: :meth:`~ComposeCursor.next_slot`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
import math


def slot_ns(slot_s: float) -> int:
    """Slot length in integer nanoseconds (τ must be positive and finite)."""
    if not (math.isfinite(slot_s) and slot_s > 0):
        raise ValueError(f"slot_s must be a positive finite number of seconds, got {slot_s}")
    return round(slot_s * 1e9)


@dataclass(frozen=True)
class SlotClock:
    """Slot arithmetic for one slot length ``slot_s`` [s] (see the module docstring)."""

    slot_s: float

    def __post_init__(self) -> None:
        slot_ns(self.slot_s)  # validates

    @property
    def slot_len_ns(self) -> int:
        """τ in integer nanoseconds."""
        return slot_ns(self.slot_s)

    def slot_at(self, now_ns: int) -> int:
        """The slot time ``now_ns`` lies in (floor): the slot we are in."""
        return int(now_ns) // self.slot_len_ns

    def slot_named(self, stamp_ns: int) -> int:
        """The slot a stamp names (nearest slot start): stamps are slot starts."""
        n = self.slot_len_ns
        return (int(stamp_ns) + n // 2) // n

    def start_ns(self, slot: int) -> int:
        """Start time of ``slot`` [ns]."""
        return int(slot) * self.slot_len_ns

    def phase_ns(self, now_ns: int) -> int:
        """Time since the current slot started [ns], in ``[0, τ)``."""
        return int(now_ns) % self.slot_len_ns

    def deadline_ns(self, slot: int, delay_s: float) -> int:
        """When ``slot`` is due: its start + ``delay_s``."""
        return self.start_ns(slot) + round(delay_s * 1e9)

    def due_slot(self, now_ns: int, delay_s: float) -> int:
        """The newest slot whose deadline (start + ``delay_s``) has passed at ``now_ns``."""
        return (int(now_ns) - round(delay_s * 1e9)) // self.slot_len_ns


class SlotTicker:
    """Each slot once, in order, from a timer that polls the clock (the robot's slot loop).

    The first poll only learns where it is (the slot that is already running is not started half-way)."""

    def __init__(self, clock: SlotClock) -> None:
        self.clock = clock
        self.last_slot: int | None = None

    def poll(self, now_ns: int) -> tuple[int, int] | None:
        """``(slot, skipped)`` when a new slot has begun since the last poll (``skipped`` slots in between
        were never run: the node was overloaded), else None."""
        slot = self.clock.slot_at(now_ns)
        if self.last_slot is None:
            self.last_slot = slot  # start on the next boundary
            return None
        if slot <= self.last_slot:
            return None
        skipped = slot - self.last_slot - 1
        self.last_slot = slot
        return slot, skipped


class ComposeCursor:
    """Which slot the server composes next (see the module docstring).

    ``delay_s`` (the latest a slot waits for its uploads after it starts) and ``max_backlog_slots`` are read
    at every :meth:`next_slot` call, so a live parameter change acts from the next one."""

    def __init__(self, clock: SlotClock) -> None:
        self.clock = clock
        self.next: int | None = None  # the slot composed next
        self.first: int | None = None  # the first slot composed (round time 0 of the MR content)
        self.skips = 0  # times the cursor skipped ahead

    def next_slot(self, now_ns: int, *, delay_s: float, max_backlog_slots: int,
                  complete: Callable[[int], bool]) -> int | None:
        """The slot to compose now, or None. ``complete(k)``: slot k's uploads have all arrived.

        The first call starts the cursor at the slot after the one due now (nothing composed). A slot is
        returned once it is due, or once it has started and ``complete`` says its uploads are in; when the
        due slot is more than ``max_backlog_slots`` ahead, the cursor skips to it (counted in ``skips``)."""
        due = self.clock.due_slot(now_ns, delay_s)
        if self.next is None:
            self.next = self.first = due + 1
            return None
        if due < self.next and not (self.next <= self.clock.slot_at(now_ns) and complete(self.next)):
            return None
        if due > self.next + max_backlog_slots:  # far behind (suspended, clock jump): skip ahead
            self.skips += 1
            self.next = due
        slot = self.next
        self.next += 1
        return slot

    def round_time_s(self, slot: int) -> float:
        """Seconds from the first composed slot's start to ``slot``'s (0 before the cursor started)."""
        return (slot - (self.first if self.first is not None else slot)) * self.clock.slot_s
