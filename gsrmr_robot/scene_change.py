"""Sudden changes of the camera's view, found on the robot (pure: numpy and OpenCV only, no ROS).

In a key slot the server sees no image, so a change of the world stays unseen until the next image slot; the robot
has every slot's frame. :class:`SceneChangeDetector` finds such a change, :class:`ChangeProbe` picks the slot that
sends its image. Design and measurements: ``docs/scheduling.md``, "The live loop", item 8 ("Scene changes seen by
the robot"), and "Scene changes: measured".
"""

from __future__ import annotations

from collections import deque
import math
import statistics

import cv2
import numpy as np

from gsrmr_common.channel import rician_power_samples

#: Scores a baseline needs before the detector judges a frame (the first slots only fill it).
MIN_BASELINE_SCORES = 5
#: The fade quantile a scene change's image needs: in the slot of the change, and in the last slot of the wait.
CHANGE_FADE_QUANTILES = (0.3, 0.1)


class SceneChangeDetector:
    """Consecutive frames' thumbnail difference against the run's own recent differences.

    A frame's score is the mean absolute difference of its thumbnail and the previous slot's (:meth:`thumbnail`,
    compared at the best shift: :meth:`aligned_difference`). Driving and turning move the view too, so a change is a
    score above ``ratio`` × the median of the last ``window`` scores — changes included: when the robot starts to
    drive, every score rises for good, and the median follows within half a window — and above ``min_score``, a
    difference too small to matter for the MR loss whatever the baseline (driving and turning in the sandbox give
    0.01–0.04, the changes of its second round 0.05–0.11). A frame of another size than the previous one (a new
    calibration, another uplink width) or a missing frame restarts the comparison; the previous slot's frame again
    (the camera sent no new one) is skipped, so that the baseline does not fill with zeros.
    """

    def __init__(self, *, ratio: float = 4.0, min_score: float = 0.04, thumbnail_width_px: int = 32,
                 window: int = 30, max_shift_fraction: float = 0.2) -> None:
        if (not ratio > 1.0 or not 0.0 <= min_score <= 1.0 or thumbnail_width_px < 4 or window < MIN_BASELINE_SCORES
                or not 0.0 <= max_shift_fraction <= 0.5):
            raise ValueError("scene change: ratio must be > 1, min_score in [0, 1], thumbnail_width_px >= 4, "
                             f"window >= {MIN_BASELINE_SCORES} and max_shift_fraction in [0, 0.5] (a shift of half "
                             "the thumbnail leaves too little overlap to compare)")
        self.ratio = float(ratio)
        self.min_score = float(min_score)
        self.thumbnail_width_px = int(thumbnail_width_px)
        self._max_shift_x = int(round(max_shift_fraction * thumbnail_width_px))
        self._max_shift_y = 1 if self._max_shift_x else 0
        self._baseline: deque[float] = deque(maxlen=int(window))
        self._previous: np.ndarray | None = None
        self._previous_shape: tuple[int, ...] | None = None
        self._previous_stamp_ns: int | None = None
        self.last_score = float("nan")  # the newest frame's score (NaN: nothing to compare it with)
        self.changes = 0  # changes found so far

    def thumbnail(self, frame_u8: np.ndarray) -> np.ndarray:
        """``frame_u8`` (H×W×3 or H×W uint8) as a float32 thumbnail in [0, 1], ``thumbnail_width_px`` wide."""
        h, w = frame_u8.shape[:2]
        width = min(self.thumbnail_width_px, w)
        height = max(1, round(h * width / w))
        return cv2.resize(frame_u8, (width, height), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0

    def aligned_difference(self, thumb: np.ndarray, previous: np.ndarray) -> float:
        """Mean absolute difference of two thumbnails at the best whole-pixel shift of up to ``max_shift_fraction``
        of the width (sideways) and one pixel (up/down), over the part both cover: turning the camera shifts
        the view, a light or an object that changed does not go away with a shift."""
        h, w = thumb.shape[:2]
        shift_x, shift_y = min(self._max_shift_x, w // 2), min(self._max_shift_y, h // 2)  # a frame narrower than
        best = math.inf  # the thumbnail width keeps its own width: its shifts stay within half of it
        for dy in range(-shift_y, shift_y + 1):
            for dx in range(-shift_x, shift_x + 1):
                a = thumb[max(dy, 0):h + min(dy, 0), max(dx, 0):w + min(dx, 0)]
                b = previous[max(-dy, 0):h + min(-dy, 0), max(-dx, 0):w + min(-dx, 0)]
                best = min(best, float(np.mean(np.abs(a - b))))
        return best

    def baseline(self) -> float | None:
        """Median score of the recent frames that were no change (None until :data:`MIN_BASELINE_SCORES`)."""
        return statistics.median(self._baseline) if len(self._baseline) >= MIN_BASELINE_SCORES else None

    def update(self, frame_u8: np.ndarray | None, stamp_ns: int | None = None) -> bool:
        """This slot's frame (None: no frame) and its capture stamp; True when it differs suddenly from the previous
        slot's. The frame of the previous call again (same ``stamp_ns``: the camera sent none since) is no news."""
        if frame_u8 is None:
            self._previous = None
            self.last_score = float("nan")
            return False
        if stamp_ns is not None and stamp_ns == self._previous_stamp_ns and self._previous is not None:
            return False
        self._previous_stamp_ns = stamp_ns
        thumb = self.thumbnail(frame_u8)
        previous, self._previous = self._previous, thumb
        if previous is None or frame_u8.shape != self._previous_shape:
            self._previous_shape = frame_u8.shape
            self.last_score = float("nan")
            return False
        score = self.aligned_difference(thumb, previous)
        self.last_score = score
        base = self.baseline()
        changed = base is not None and score > max(self.ratio * base, self.min_score)
        self.changes += int(changed)
        self._baseline.append(score)
        return changed


class ChangeProbe:
    """The image a scene change asks for: sent in the first of ``wait_slots`` slots (the change's included) whose
    gain reaches ``mean gain · q-quantile of |h|²``, q ramping from :data:`CHANGE_FADE_QUANTILES` [0] (0.3) in the
    slot of the change down to [1] (0.1) in the last one. Each slot of delay leaves one more key slot whose loss
    the server can only guess, so a fade somewhat worse than the median is taken at once, a poor one at the end,
    a deep one never. Any image ends the wait. Pure: the robot's core and the planner replay use it alike."""

    def __init__(self, rician_k: float, wait_slots: int = 5) -> None:
        if wait_slots < 1:
            raise ValueError("change probe: wait_slots must be >= 1")
        #: the bound on the fade |h|² (mean 1) in each slot of the wait
        self.fades = np.quantile(rician_power_samples(rician_k), np.linspace(*CHANGE_FADE_QUANTILES, wait_slots))
        self._change_slot: int | None = None

    def changed(self, slot: int) -> None:
        """The view changed in ``slot``: the wait (re)starts there."""
        self._change_slot = int(slot)

    def wants_image(self, slot: int, gain: float, mean_gain: float) -> bool:
        """Whether ``slot``, at the measured ``gain`` where the expected one is ``mean_gain``, sends the image."""
        if self._change_slot is None:
            return False
        waited = int(slot) - self._change_slot
        return 0 <= waited < len(self.fades) and gain >= mean_gain * float(self.fades[waited])

    @property
    def waiting(self) -> bool:
        """An image is asked for (the wait has started and no image went since)."""
        return self._change_slot is not None

    def image_sent(self) -> None:
        """An image went (for the change or not): nothing is waited for any more."""
        self._change_slot = None
