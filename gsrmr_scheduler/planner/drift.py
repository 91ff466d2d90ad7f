"""Drift of the L_t prediction (pure): when measured losses stray from what the plan predicted, replan."""

from __future__ import annotations

from collections import deque

import numpy as np


class DriftMonitor:
    """The mean ``|measured − predicted|`` L of the last ``window_samples`` measured slots against ``threshold``."""

    def __init__(self, threshold: float, window_samples: int) -> None:
        if not threshold >= 0 or window_samples < 1:
            raise ValueError("drift monitor: threshold >= 0 and window_samples >= 1")
        self.threshold, self.window_samples = float(threshold), int(window_samples)
        self._errors: deque[float] = deque(maxlen=self.window_samples)

    def add(self, error: float) -> bool:
        """A measured slot's ``|measured − predicted|`` L; True when a replan is due (a full window whose mean
        exceeds the threshold)."""
        self._errors.append(error)
        return len(self._errors) >= self.window_samples and float(np.mean(self._errors)) > self.threshold

    def clear(self) -> None:
        """Forget past errors (after a replan)."""
        self._errors.clear()

    def reconfigure(self, threshold: float, window_samples: int) -> None:
        """New threshold and window; the newest errors are kept (up to the new window)."""
        if not threshold >= 0 or window_samples < 1:
            raise ValueError("drift monitor: threshold >= 0 and window_samples >= 1")
        self.threshold, self.window_samples = float(threshold), int(window_samples)
        self._errors = deque(self._errors, maxlen=self.window_samples)
