"""Deadline-aware composition (pure): which level each slot is composed at, from its time left and recent costs.

Levels and their measured loss and time: docs/nodes.md, "Composing against the deadline".
"""

from __future__ import annotations

from dataclasses import dataclass
import math

from gsrmr_common.wire import COMPOSE_LEVELS

#: The composition levels, best first: the GS render at full size, at half and at a quarter of the width and height
#: (enlarged to the full size; the virtual view and the blend stay full size).
LEVEL_NAMES = COMPOSE_LEVELS
RENDER_SCALES = (1.0, 0.5, 0.25)
#: compose time of each level against the full one before any is measured (bench/perf/compose_levels.py: 10.3, 7.3
#: and 6.6 ms at 320×240 on one render thread; the virtual view and the blend stay full size)
PRIOR_COST_RATIOS = (1.0, 0.7, 0.65)


@dataclass(frozen=True)
class LevelChoice:
    """One slot's level and what it was chosen from (all in ms): its time left before τ when chosen, the level's
    predicted time from the choice to the MR image's publication."""

    level: int
    time_left_ms: float
    predicted_ms: float

    @property
    def name(self) -> str:
        """``full``, ``half`` or ``quarter``."""
        return LEVEL_NAMES[self.level]

    @property
    def render_scale(self) -> float:
        """The GS render's fraction of the full width and height."""
        return RENDER_SCALES[self.level]

    @property
    def degraded(self) -> bool:
        """Composed below full size: the work off the slot path (the loss sample, the localizer) is skipped."""
        return self.level > 0


class DeadlineLevels:
    """Picks each slot's level: the best whose predicted time fits the time left less ``margin_ms``, else the
    cheapest (a late slot is still published: missing one is the last resort).

    Each level's time (choice → publication, ms) is an exponentially weighted mean of its own slots (weight
    ``alpha``); a slot of one level also moves the others by the same factor (a CPU share that shrinks slows every
    level alike), so a level not used for a while is not predicted from an idle past. Before a level has a time of
    its own it is predicted from the full level's by :data:`PRIOR_COST_RATIOS`.

    Args:
        margin_ms: Time kept in hand after the predicted time (timer granularity, the publication's own jitter).
        alpha: Weight of the newest slot in each mean (0 < alpha ≤ 1).
        max_level: The cheapest level allowed (0: always full size, the level selection off).

    Example:
        ::

            levels = DeadlineLevels()
            choice = levels.choose(time_left_ms=62.0)  # before composing
            levels.observe(choice.level, took_ms=31.5)  # once the MR image is published
    """

    def __init__(self, *, margin_ms: float = 5.0, alpha: float = 0.3, max_level: int = len(LEVEL_NAMES) - 1) -> None:
        if not 0.0 < alpha <= 1.0 or not 0 <= max_level < len(LEVEL_NAMES) or not margin_ms >= 0.0:
            raise ValueError(f"DeadlineLevels: alpha in (0, 1], max_level in 0..{len(LEVEL_NAMES) - 1}, margin ≥ 0")
        self.margin_ms, self.alpha, self.max_level = float(margin_ms), float(alpha), int(max_level)
        self._ms: list[float | None] = [None] * len(LEVEL_NAMES)

    def predicted_ms(self, level: int) -> float:
        """The level's predicted time (ms); 0 before any slot was observed."""
        own = self._ms[level]
        if own is not None:
            return own
        known = [(ms / PRIOR_COST_RATIOS[k], k) for k, ms in enumerate(self._ms) if ms is not None]
        return known[0][0] * PRIOR_COST_RATIOS[level] if known else 0.0

    def choose(self, time_left_ms: float) -> LevelChoice:
        """The level for a slot with ``time_left_ms`` before its deadline (negative: already late); full size
        before any slot was observed."""
        if all(ms is None for ms in self._ms):
            return LevelChoice(0, float(time_left_ms), 0.0)
        for level in range(self.max_level + 1):
            predicted = self.predicted_ms(level)
            if predicted + self.margin_ms <= time_left_ms:
                return LevelChoice(level, float(time_left_ms), predicted)
        return LevelChoice(self.max_level, float(time_left_ms), self.predicted_ms(self.max_level))

    def observe(self, level: int, took_ms: float) -> None:
        """A slot of ``level`` took ``took_ms`` from its choice to its publication."""
        if not (math.isfinite(took_ms) and took_ms > 0.0):
            return
        before = self.predicted_ms(level)
        own = self._ms[level]
        self._ms[level] = took_ms if own is None else (1.0 - self.alpha) * own + self.alpha * took_ms
        if own is None or before <= 0.0:
            return
        factor = (self._ms[level] or before) / before  # the change the newest slot made, applied to the others
        for k, ms in enumerate(self._ms):
            if k != level and ms is not None:
                self._ms[k] = ms * factor
