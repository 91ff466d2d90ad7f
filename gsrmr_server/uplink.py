"""Server-side uplink bookkeeping (pure): which uploads arrived for which slot, and every fault.

:class:`UplinkAssembler` files uploads under the slot their stamp names (:mod:`gsrmr_common.wire`); a missing, late,
duplicated, stale or corrupt upload never blocks a slot. The fault counters are named, and each documented, by
:class:`gsrmr_common.wire.UplinkFault`.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

from gsrmr_common.pose2d import wrap_angle
from gsrmr_common.wire import PoseKey, UplinkFault


@dataclass
class SlotUploads:
    """What arrived for one slot."""

    slot: int
    key: PoseKey | None = None
    jpeg: bytes | None = None
    key_arrival_ns: int | None = None
    image_arrival_ns: int | None = None
    faults: list[UplinkFault] = field(default_factory=list)


class UplinkAssembler:
    """Collects pose keys and JPEG uploads per absolute slot index.

    A slot is *taken* once, when the server composes its MR image; anything for that slot arriving later is counted
    ``late``. :meth:`take` always returns what is known, and :meth:`best_pose` extrapolates the last valid pose key so
    the server can fall back to a render. This class counts the faults it sees (duplicates, invalid keys, late,
    future, evicted, missing key or image); the server node counts the others through :meth:`count` (refused JPEGs,
    see :func:`gsrmr_server.compose.refusal_fault`; oversized or malformed uploads; malformed ledger rows; skipped
    slots). All counters are cumulative.
    """

    def __init__(self, max_future_slots: int = 50, max_extrapolation_slots: int = 20) -> None:
        self.max_future_slots = max_future_slots
        self.max_extrapolation_slots = max_extrapolation_slots
        self.faults: Counter[str] = Counter()
        self._pending: dict[int, SlotUploads] = {}
        self._taken_up_to: int | None = None
        self._last_pose: PoseKey | None = None
        self._velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)  # per slot

    def count(self, fault: UplinkFault, slot: int | None = None) -> None:
        """Count a fault found elsewhere (e.g. a JPEG that failed to decode)."""
        self.faults[fault] += 1
        if slot is not None and slot in self._pending:
            self._pending[slot].faults.append(fault)

    def _admit(self, slot: int, now_slot: int) -> SlotUploads | None:
        if self._taken_up_to is not None and slot <= self._taken_up_to:
            self.faults[UplinkFault.LATE] += 1
            return None
        if slot > now_slot + self.max_future_slots:
            self.faults[UplinkFault.FUTURE] += 1
            return None
        if len(self._pending) > 4 * self.max_future_slots:  # bound memory whatever arrives
            oldest = min(self._pending)
            del self._pending[oldest]
            self.faults[UplinkFault.EVICTED] += 1
        return self._pending.setdefault(slot, SlotUploads(slot))

    def on_key(self, key: PoseKey, now_slot: int, now_ns: int) -> None:
        """A pose key arrived (``now_slot`` = the server's current slot index)."""
        if not key.is_valid():
            self.faults[UplinkFault.INVALID_KEY] += 1
            return
        entry = self._admit(key.slot, now_slot)
        if entry is None:
            return
        if entry.key is not None:
            self.faults[UplinkFault.DUPLICATE_KEY] += 1
            return
        entry.key, entry.key_arrival_ns = key, now_ns
        self._update_motion(key)

    def on_image(self, slot: int, jpeg: bytes, now_slot: int, now_ns: int) -> None:
        """A compressed image arrived for ``slot``."""
        entry = self._admit(slot, now_slot)
        if entry is None:
            return
        if entry.jpeg is not None:
            self.faults[UplinkFault.DUPLICATE_IMAGE] += 1
            return
        entry.jpeg, entry.image_arrival_ns = bytes(jpeg), now_ns

    def _update_motion(self, key: PoseKey) -> None:
        last = self._last_pose
        if last is not None and key.slot > last.slot:
            n = key.slot - last.slot
            dtheta = wrap_angle(key.theta_rad - last.theta_rad)
            self._velocity = ((key.a_m - last.a_m) / n, (key.b_m - last.b_m) / n, dtheta / n)
        if last is None or key.slot > last.slot:
            self._last_pose = key

    def complete(self, slot: int, image_expected: bool | None) -> bool:
        """Whether everything expected for ``slot`` has arrived: its key, and its image unless the
        schedule says a key-only slot (``image_expected`` False; None = no schedule: wait for both)."""
        entry = self._pending.get(slot)
        if entry is None or entry.key is None:
            return False
        return entry.jpeg is not None or image_expected is False

    def take(self, slot: int, image_expected: bool | None = None) -> SlotUploads:
        """Everything known for ``slot``; the slot is closed afterwards (later uploads are ``late``)."""
        entry = self._pending.pop(slot, SlotUploads(slot))
        for old in [s for s in self._pending if s < slot]:  # never-taken older slots
            del self._pending[old]
        self._taken_up_to = slot if self._taken_up_to is None else max(self._taken_up_to, slot)
        if entry.key is None:
            entry.faults.append(UplinkFault.MISSING_KEY)
            self.faults[UplinkFault.MISSING_KEY] += 1
        if image_expected and entry.jpeg is None:
            entry.faults.append(UplinkFault.MISSING_IMAGE)
            self.faults[UplinkFault.MISSING_IMAGE] += 1
        return entry

    def best_pose(self, slot: int) -> PoseKey | None:
        """Last valid key, extrapolated at the recent velocity (at most ``max_extrapolation_slots``)."""
        last = self._last_pose
        if last is None:
            return None
        n = max(0, min(slot - last.slot, self.max_extrapolation_slots))
        va, vb, vt = self._velocity
        return PoseKey(slot, last.a_m + n * va, last.b_m + n * vb, last.theta_rad + n * vt)
