"""The simulation's per-slot scores (``scores.csv``) and their join with the server's ``slots.csv``.

Columns, cell rules and when the report waits for them: docs/world.md, "The simulation's scorer".
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Mapping
import os
from pathlib import Path
import signal
import time
from typing import TYPE_CHECKING, Any

from gsrmr_server.recording.slots_csv import csv_line, read_slots_csv
from gsrmr_server.slot_row import SCORE_COLUMNS, SlotScore

if TYPE_CHECKING:
    from gsrmr_sim.supervisor import ProcessStack

SCORES_NAME = "scores.csv"
#: written by the scorer when its first MR image has arrived: its subscriptions are matched (the runner waits for it)
SCORER_READY_NAME = "scorer.ready"


class ScoresWriter:
    """Appends :class:`~gsrmr_server.slot_row.SlotScore` rows to ``<folder>/scores.csv`` (created with its header;
    an existing file with that header is continued, as by a restarted scorer)."""

    def __init__(self, folder: str | os.PathLike[str]) -> None:
        self.path = Path(folder) / SCORES_NAME
        self.path.parent.mkdir(parents=True, exist_ok=True)
        header = ",".join(SCORE_COLUMNS) + "\n"
        if self.path.exists() and self.path.stat().st_size:
            with self.path.open(encoding="utf-8") as f:
                if f.readline() != header:
                    raise ValueError(f"{self.path} exists with another header; use a fresh record_dir")
            self._file = self.path.open("a", newline="", encoding="utf-8")
        else:
            self._file = self.path.open("w", newline="", encoding="utf-8")
            self._file.write(header)
            self._file.flush()

    def write(self, score: SlotScore) -> None:
        """One slot's row, flushed (a killed scorer loses no row written before)."""
        self._file.write(csv_line({"slot": score.slot, **score.columns()}, SCORE_COLUMNS))
        self._file.flush()

    def close(self) -> None:
        """Close the file."""
        self._file.close()

    def mark_ready(self) -> None:
        """Write ``<folder>/scorer.ready``: the scorer receives the server's MR images."""
        (self.path.parent / SCORER_READY_NAME).touch()


def read_scores(folder: str | os.PathLike[str]) -> dict[int, dict[str, Any]]:
    """The rows of ``<folder>/scores.csv`` by slot (a later row of a slot wins; no file: none)."""
    path = Path(folder) / SCORES_NAME
    if not path.exists() or path.stat().st_size == 0:
        return {}
    return {row["slot"]: row for row in read_slots_csv(path, SCORE_COLUMNS)}


def join_scores(rows: list[dict[str, Any]], folder: str | os.PathLike[str]) -> list[dict[str, Any]]:
    """``rows`` (``slots.csv`` rows) with their score columns taken from ``<folder>/scores.csv`` by slot; a row
    the scorer has no row for keeps its own (empty) cells."""
    scores = read_scores(folder)
    return [{**row, **{c: v for c, v in scores[row["slot"]].items() if c != "slot"}} if row["slot"] in scores
            else dict(row) for row in rows]


def await_scores(stack: ProcessStack, scorers: Mapping[str, tuple[str | os.PathLike[str], Collection[int]]], *,
                 stall_s: float = 60.0, timeout_s: float = 900.0,
                 log: Callable[[str], None] = print) -> dict[str, list[int]]:
    """Let the scorers catch up with the round, then say what they missed.

    ``scorers``: process name in ``stack`` → (its ``record_dir``, the slots it must have scored). Every other
    process of ``stack`` is sent SIGINT first (the round is over; the scorer, at the simulated world's low
    priority, gets the CPU the system under test used); ``stack.stop()`` later reaps them. The wait ends when
    every scorer has a row for each of its slots, when a scorer has exited, when no scorer wrote a row for
    ``stall_s`` or after ``timeout_s``. Returns, per scorer, the slots without a row (logged when any)."""
    for name, proc in reversed(list(stack.procs.items())):
        if name not in scorers and proc.poll() is None:
            proc.send_signal(signal.SIGINT)
    wanted = {name: set(slots) for name, (_, slots) in scorers.items()}
    total = sum(len(w) for w in wanted.values())
    t0 = last_progress = last_log = time.monotonic()
    fewest: int | None = None
    while True:
        missing = {name: wanted[name] - set(read_scores(scorers[name][0])) for name in scorers}
        left = sum(len(m) for m in missing.values())
        now = time.monotonic()
        if fewest is None or left < fewest:
            fewest, last_progress = left, now
        exited = any(missing[name] and stack.procs[name].poll() is not None for name in scorers)
        if not left or exited or now - last_progress > stall_s or now - t0 > timeout_s:
            break
        if now - last_log > 10.0:
            log(f"scorer: {total - left}/{total} composed slots of the round scored")
            last_log = now
        time.sleep(0.5)
    # once more: a scorer that exited after the read above flushed its last rows as it went (read, flush, exit,
    # poll: 6 of 288 slots counted missing that its file holds)
    missing = {name: wanted[name] - set(read_scores(scorers[name][0])) for name in scorers}
    for name, slots in missing.items():
        if slots:
            log(f"{name}: {len(slots)} of the round's {len(wanted[name])} composed slots have no score after "
                f"{time.monotonic() - t0:.0f} s (first {sorted(slots)[:10]})")
    return {name: sorted(slots) for name, slots in missing.items()}
