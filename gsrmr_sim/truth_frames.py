"""The simulator's true camera frames for scoring (pure, no ROS): the truth-frames backplane and the frame matcher.

Why the truth crosses two simulated hosts through a folder: docs/two_hosts.md, "Ground truth stays off the
uplink". Layout: one ``<stamp_us>.npy`` per frame (H×W×3 uint8 RGB; capture stamp in integer microseconds since the
clock's epoch), written to a temporary name and renamed, so a reader never sees half a frame; the writer keeps the
newest ``keep`` (:data:`TRUTH_FRAMES_KEPT`: the scorer may lag the server by a round).
"""

from __future__ import annotations

from collections import deque
import contextlib
import math
import os
from pathlib import Path

import numpy as np

from gsrmr_common.wire import LedgerRow

#: Frames the writer keeps by default: two sandbox rounds (288 slots) at one frame per slot.
TRUTH_FRAMES_KEPT = 600


def _name(stamp_us: int) -> str:
    return f"{stamp_us:020d}.npy"


class TruthFrameWriter:
    """Writes true frames into ``folder`` and prunes all but the newest ``keep``."""

    def __init__(self, folder: str | os.PathLike[str], keep: int = TRUTH_FRAMES_KEPT) -> None:
        if keep < 1:
            raise ValueError("keep must be ≥ 1")
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.keep = int(keep)
        self._written: deque[Path] = deque()

    def put(self, stamp_ns: int, frame_u8: np.ndarray) -> Path:
        """Store ``frame_u8`` (H×W×3 uint8) captured at ``stamp_ns``; returns its path."""
        frame = np.ascontiguousarray(frame_u8, dtype=np.uint8)
        path = self.folder / _name(int(stamp_ns) // 1000)
        tmp = path.with_suffix(".tmp")
        with open(tmp, "wb") as f:
            np.save(f, frame)
        os.replace(tmp, path)
        self._written.append(path)
        while len(self._written) > self.keep:
            with contextlib.suppress(FileNotFoundError):
                self._written.popleft().unlink()
        return path


class TruthFrameReader:
    """Finds the true frame of a slot in a folder a :class:`TruthFrameWriter` fills."""

    def __init__(self, folder: str | os.PathLike[str]) -> None:
        self.folder = Path(folder)

    def _load(self, path: Path) -> np.ndarray | None:
        try:
            return np.load(path, allow_pickle=False)
        except (FileNotFoundError, ValueError, OSError):  # pruned meanwhile, or not a frame
            return None

    def frame(self, capture_stamp_s: float | None, slot_start_ns: int) -> np.ndarray | None:
        """The frame captured at ``capture_stamp_s`` (float seconds, as the robot's ledger row carries it:
        matched to the microsecond, ± 1 µs for the float's rounding); without a stamp, the newest frame
        captured by 5 ms after ``slot_start_ns`` (as :func:`match_frame` picks)."""
        if capture_stamp_s is not None and math.isfinite(capture_stamp_s):
            us = round(capture_stamp_s * 1e6)
            for candidate in (us, us - 1, us + 1):
                path = self.folder / _name(candidate)
                if path.exists():
                    return self._load(path)
            return None
        limit_us = (int(slot_start_ns) + 5_000_000) // 1000
        try:
            names = sorted(n for n in os.listdir(self.folder) if n.endswith(".npy"))
        except FileNotFoundError:
            return None
        older = [n for n in names if int(n[:-4]) <= limit_us]
        return self._load(self.folder / older[-1]) if older else None


def match_frame(frames: list[tuple[int, np.ndarray]], ledger: LedgerRow | None,
                slot_start_ns: int) -> np.ndarray | None:
    """The true camera frame of a slot among ``(stamp_ns, frame)``: the one whose stamp the robot's ledger row
    names (within 1 ms: the row carries it in float seconds), else the newest one at the slot start."""
    used = ledger.frame_stamp_s if ledger else None
    if used is not None and math.isfinite(used):
        match = [f for s, f in frames if abs(s / 1e9 - used) < 1e-3]
    else:
        match = [f for s, f in frames if s <= slot_start_ns + 5_000_000][-1:]
    return match[0] if match else None
