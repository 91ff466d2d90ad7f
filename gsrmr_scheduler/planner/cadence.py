"""When the periodic replan runs (pure): :class:`SampleAlignedCadence` turns the replan timer into a deadline, so that
the replan runs right after the next loss sample, not at the timer's arbitrary phase of the slot.

Why: docs/scheduling.md, "Sample timing and the probe gap: measured" (*When a sample counts*).
"""

from __future__ import annotations


class SampleAlignedCadence:
    """The periodic replan's trigger: the timer's period is a deadline, met by the next loss sample, or by the next
    timer when no sample came in a whole period; ``aligned`` false: the timer replans at once."""

    def __init__(self, aligned: bool = True) -> None:
        self.aligned = bool(aligned)
        self.waiting = False  # the period is over and the replan waits for the next loss sample
        self.waited_out = 0  # periods in which no sample came: replanned at the next timer instead

    def timer_fired(self) -> bool:
        """The replan timer fired; True: replan now (not aligned, or a whole period passed without a sample)."""
        if not self.aligned:
            return True
        if self.waiting:
            self.waiting = False
            self.waited_out += 1
            return True
        self.waiting = True
        return False

    def sample_taken(self) -> bool:
        """The scheduler took a loss sample; True: the period's replan is due now."""
        if self.waiting:
            self.waiting = False
            return True
        return False

    def replanned(self) -> None:
        """A replan ran (for any reason): the period is satisfied."""
        self.waiting = False
