"""The loss budget of the next plan (pure): :class:`LossBudget` books the slots that passed — what the robot did (its
ledger, else the plan's x), at the pose it reported, as the server composed them (source and level) — with their
estimated MR loss, and gives each block of a plan the Σ loss it may leave (:meth:`LossBudget.caps`).

Why rounds, and why slots are charged as composed: docs/scheduling.md, "The live loop", items 4 and 9.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
import math

from gsrmr_common.pose2d import Pose2D
from gsrmr_common.wire import ScheduleMsg

KeyLoss = Callable[[int, Pose2D | None], float]  # (slot, reported pose or None) → estimated loss of a key there
HISTORY_SLOTS = 1000  # ledger rows and reported poses kept this long before the slot is booked
#: A slot the server composed at its fallback pose (its upload missing) is charged at this × the key's estimate: over
#: 78 such slots of 90 recorded sandbox runs its true loss was 1.79× the burst model's estimate of a key there on
#: average (quartiles 1.04 / 1.42 / 2.13): the pose is extrapolated, and uploads go missing when the world is busy.
FALLBACK_LOSS_FACTOR = 2.0
_KEY_SOURCES = frozenset({"render"})  # what a key slot is composed from when all went well
_MISSED_SOURCES = frozenset({"fallback", "none"})  # composed without the slot's upload


class LossBudget:
    """Booked slots and the loss budget of the next plan.

    A booked slot counts with its estimated MR loss (:meth:`slot_loss`); a key's estimate follows the measurements
    that arrive until ``refine_slots`` newer slots are booked, then it is frozen."""

    def __init__(self, key_loss: KeyLoss, *, image_slot_loss: float = 0.0, round_slots: int = 0,
                 round_start_m: float = 0.05, refine_slots: int = 300,
                 level_extra_loss: tuple[float, ...] = (0.0, 0.0, 0.0), level_window_slots: int = 50) -> None:
        if not (image_slot_loss >= 0 and math.isfinite(image_slot_loss)):
            raise ValueError("loss budget: image_slot_loss must be a finite loss >= 0")
        if not all(0 <= e <= 1 for e in level_extra_loss) or level_window_slots < 1:
            raise ValueError("loss budget: level_extra_loss must be losses in [0, 1], level_window_slots >= 1")
        self.level_extra_loss = tuple(float(e) for e in level_extra_loss)
        self.level_window_slots = int(level_window_slots)
        if round_slots < 0 or refine_slots < 0 or not round_start_m >= 0:
            raise ValueError("loss budget: round_slots, round_start_m and refine_slots must be >= 0")
        self.key_loss = key_loss
        self.image_slot_loss = float(image_slot_loss)
        self.round_slots, self.round_start_m = int(round_slots), float(round_start_m)
        self.refine_slots = int(refine_slots)
        self.slots_done = 0  # slots booked so far
        self._actual_x: dict[int, int] = {}  # slot → what the robot did (its ledger)
        self._reported: dict[int, Pose2D] = {}  # slot → the pose it reported
        self._composed: dict[int, tuple[str, int]] = {}  # slot → its mr/slot_info (source, composition level)
        self._done: deque[tuple[int, int, Pose2D | None]] = deque()  # (slot, x, pose) still re-estimated
        self._frozen_spent = 0.0  # Σ estimated loss of the slots no longer re-estimated
        self._accounted_up_to: int | None = None  # last slot booked (or planned from)
        self._round_start: int | None = None  # first slot the reported pose left its start (round mode)
        self._home: tuple[float, float] | None = None
        self._round_frozen, self._round_frozen_n = 0.0, 0

    # ------------------------------------------------------------------ what happened
    def record_action(self, slot: int, x: int) -> None:
        """What the robot did in ``slot`` (1 = image), from its ledger; a slot already booked without it (its row
        came after the plan that booked it) is booked again with it."""
        if self._rebook(slot, x=int(x)):
            return
        self._actual_x[slot] = int(x)
        for old in [k for k in self._actual_x if k < slot - HISTORY_SLOTS]:
            del self._actual_x[old]

    def record_pose(self, slot: int, pose: Pose2D) -> None:
        """The pose the robot reported for ``slot`` (its pose key): a key there is charged at it; in round mode
        the first move of more than ``round_start_m`` starts a round."""
        if not self._rebook(slot, pose=pose):
            self._reported[slot] = pose
        if self.round_slots <= 0:
            return
        if self._round_start is not None and slot >= self._round_start + self.round_slots:
            self._round_start, self._home = None, None  # the round is over: the next one starts on motion
        if self._round_start is None:
            if self._home is None:
                self._home = (pose[0], pose[1])
            elif math.hypot(pose[0] - self._home[0], pose[1] - self._home[1]) > self.round_start_m:
                self._round_start, self._round_frozen, self._round_frozen_n = slot, 0.0, 0

    def record_composed(self, slot: int, source: str, level: int = 0) -> None:
        """What the server composed ``slot`` from (``image``, ``render``, ``fallback`` or ``none``) and at which
        composition level (0 = full size; its ``mr/slot_info``): the slot is charged by them (:meth:`slot_loss`),
        booked or not."""
        level = int(level) if 0 <= int(level) < len(self.level_extra_loss) else len(self.level_extra_loss) - 1
        self._composed[int(slot)] = (str(source), level)
        if len(self._composed) > 2 * HISTORY_SLOTS:
            for old in [k for k in self._composed if k < slot - HISTORY_SLOTS]:
                del self._composed[old]

    def account_until(self, slot: int, schedule: ScheduleMsg | None) -> None:
        """Book the slots of ``schedule`` (the active one) that ended before ``slot``: what the robot did (its
        ledger, else the plan) and the pose it reported (else none)."""
        if schedule is None:
            return
        start = schedule.first_slot if self._accounted_up_to is None else self._accounted_up_to + 1
        for k in range(start, slot):
            entry = schedule.lookup(k)
            if entry is None:
                continue
            self.slots_done += 1
            self._done.append((k, self._actual_x.pop(k, entry[0]), self._reported.pop(k, None)))
            self._accounted_up_to = k
        self._freeze(self.refine_slots)
        for old in [k for k in self._reported if k < slot - HISTORY_SLOTS]:
            del self._reported[old]

    def _freeze(self, keep: int) -> None:
        """Fix the estimate of every booked slot but the newest ``keep``: it will not change any more."""
        while len(self._done) > keep:
            done = self._done.popleft()
            loss = self.slot_loss(*done)
            self._frozen_spent += loss
            if self._round_start is not None and done[0] >= self._round_start:
                self._round_frozen += loss
                self._round_frozen_n += 1

    def freeze_all(self) -> None:
        """Fix the estimate of every slot booked so far, with the key-loss estimate as it is now: before the seed
        map changes (a model swap), the slots the old model served keep the loss estimated for them — the new
        map describes the new model, and re-estimating the round's past with it (no measurement of it yet) makes the
        planner send an image in 77–100 % of the slots left after a swap."""
        self._freeze(0)

    def _rebook(self, slot: int, *, x: int | None = None, pose: Pose2D | None = None) -> bool:
        """Correct a booked slot that is still re-estimated with a ledger row or pose key that came after the plan
        that booked it (delayed on the way). True when ``slot`` is such a slot."""
        if self._accounted_up_to is None or slot > self._accounted_up_to:
            return False
        for i in range(len(self._done) - 1, -1, -1):
            k, booked_x, booked_pose = self._done[i]
            if k == slot:
                self._done[i] = (k, booked_x if x is None else x, booked_pose if pose is None else pose)
                return True
            if k < slot:
                break
        return False

    def planned_from(self, now_slot: int) -> None:
        """A new schedule covers the slots after ``now_slot``: booking continues from there."""
        self._accounted_up_to = now_slot

    # ------------------------------------------------------------------ what it cost
    def slot_loss(self, slot: int, x: int, pose: Pose2D | None) -> float:
        """Estimated MR loss a booked slot left: the image slot's loss J (``image_slot_loss``) for an image,
        ``key_loss`` for a key — as the server composed it when it said: an image it did not have in time but
        rendered at the key (``render``) counts as a key, a slot composed without its upload at the server's pose
        estimate (``fallback``) or from nothing (``none``) at :data:`FALLBACK_LOSS_FACTOR` × the key's estimate."""
        source, level = self._composed.get(slot, (None, 0))
        extra = self.level_extra_loss[level]  # a render below full size: the level's measured extra loss
        if source in _MISSED_SOURCES:
            return FALLBACK_LOSS_FACTOR * self.key_loss(slot, pose) + extra
        if x and source in _KEY_SOURCES:
            return self.key_loss(slot, pose) + extra
        return self.image_slot_loss if x else self.key_loss(slot, pose) + extra

    def level_loss_now(self, slot: int) -> float:
        """The extra loss a key slot composed now is expected to carry: the mean of the level's extra loss over the
        slots composed in the last ``level_window_slots`` before ``slot`` (0 when none was reported). A server
        that runs short of CPU degrades its renders; the plan then prices its key slots higher and buys images."""
        recent = [self.level_extra_loss[level] for k, (_, level) in self._composed.items()
                  if slot - self.level_window_slots <= k < slot]
        return math.fsum(recent) / len(recent) if recent else 0.0

    @property
    def loss_spent(self) -> float:
        """Σ estimated MR loss of the booked slots (recent ones re-estimated as measurements arrive)."""
        return self._frozen_spent + math.fsum(self.slot_loss(*d) for d in self._done)

    def round_remaining(self, first: int) -> int | None:
        """Slots of the current round from ``first`` on (None outside a round or without ``round_slots``)."""
        if self.round_slots <= 0 or self._round_start is None:
            return None
        left = self._round_start + self.round_slots - first
        return left if left > 0 else None

    def round_booked(self) -> tuple[int, float]:
        """(slots booked since the round started, their estimated Σ loss)."""
        start = self._round_start if self._round_start is not None else 0
        inside = [d for d in self._done if d[0] >= start]
        return (self._round_frozen_n + len(inside),
                self._round_frozen + math.fsum(self.slot_loss(*d) for d in inside))

    def caps(self, first: int, horizon_slots: int, target: float) -> list[tuple[slice, float]]:
        """The plan's blocks from slot ``first``: (slice of the horizon, Σ loss allowed over it) — one block, or
        two when the round ends inside the horizon.

        With ``target`` the mean loss aimed at (L_th·(1 − loss_margin)) and H = ``horizon_slots``: inside a round
        (``round_slots`` T > 0; it starts at the first reported pose more than ``round_start_m`` from where the robot
        stood), cap = target·(n + min(r, H)) − Σ booked in the round, n slots booked in it and r left, and what
        follows its end gets a fresh target·(H − r). Otherwise — no rounds, before a round started, or after one ended
        until the robot moves again — the running mean: cap = target·(n_done + H) − Σ booked over every booked
        slot."""
        remaining = self.round_remaining(first)
        if remaining is None:
            return [(slice(0, horizon_slots), target * (self.slots_done + horizon_slots) - self.loss_spent)]
        n_round, spent_round = self.round_booked()
        if remaining > horizon_slots:
            return [(slice(0, horizon_slots), target * (n_round + horizon_slots) - spent_round)]
        blocks = [(slice(0, remaining), target * (n_round + remaining) - spent_round)]
        if remaining < horizon_slots:  # what follows the round: a fresh budget
            blocks.append((slice(remaining, horizon_slots), target * (horizon_slots - remaining)))
        return blocks
