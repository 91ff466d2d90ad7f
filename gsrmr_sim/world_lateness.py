"""How late the simulated world ran in a ``gsrmr-demo`` run, per part, from its report folder (the computations
pure): the camera, the mock base and the simulated radio, apart from the deployment nodes
(``bench/acceptance/load.py``). Every figure is over the scored slots (``slots.csv`` ``scored`` = 1):

* ``world_age_p95_ms`` (camera): p95 of slot start − capture stamp of the frame the robot used;
* ``base_late_p95_ms`` (mock base): p95 of how late its 50 Hz integration ticks (the LIMO's serial frames and
  its true pose) ran behind their schedule, from the first scored slot's start to the last's
  (``recording/truth_poses.csv`` ``tick_late_ms``);
* ``channel_gain_p95_ms`` (simulated radio): p95 of the time its slot's gain was published − slot start
  (negative: ahead; the radio aims at −``lead_s`` + 1 ms, −39 ms; ``recording/channel_publish.csv``), and
  ``channel_no_gain_slots``: the slots whose ledger row has no measured gain (``round_slot`` −1: none had arrived
  when the robot booked it).
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from gsrmr_sim.sim_stack import CHANNEL_LOG, TRUTH_LOG


def _p95(values: list[float]) -> float:
    return float(np.percentile(values, 95)) if values else math.nan


def _float(text: str | None) -> float:
    try:
        return float(text) if text not in (None, "") else math.nan
    except ValueError:
        return math.nan


def read_rows(path: Path) -> list[dict[str, str]]:
    """A CSV's rows as strings by column (a torn last line, as a killed writer leaves it, is dropped)."""
    text = Path(path).read_text(encoding="utf-8")
    lines = text.splitlines(keepends=True)
    if lines and not lines[-1].endswith("\n"):
        lines.pop()
    return list(csv.DictReader(lines))


def scored(rows: list[dict[str, str]]) -> list[dict[str, str]]:
    """The ``slots.csv`` rows of the scored round."""
    return [r for r in rows if r.get("scored") == "1"]


def frame_age_p95_ms(rows: list[dict[str, str]]) -> float:
    """p95 of slot start − the used camera frame's capture stamp [ms] over ``rows`` (scored slots)."""
    return _p95([1e3 * (float(r["stamp_s"]) - float(r["frame_stamp_s"])) for r in rows if r.get("frame_stamp_s")])


def base_late_p95_ms(truth: list[dict[str, str]], rows: list[dict[str, str]]) -> float:
    """p95 of the mock base's tick lateness [ms] (truth log ``tick_late_ms``) over the truth rows stamped from the
    first to the last start of ``rows`` (scored slots); NaN without such rows (or a log without the column)."""
    starts = [float(r["stamp_s"]) for r in rows if r.get("stamp_s")]
    if not starts:
        return math.nan
    lo, hi = 1e9 * min(starts), 1e9 * max(starts)
    late = [_float(t.get("tick_late_ms")) for t in truth if lo <= _float(t.get("stamp_ns")) <= hi]
    return _p95([v for v in late if math.isfinite(v)])


def channel_gain_p95_ms(published: list[dict[str, str]], rows: list[dict[str, str]]) -> float:
    """p95 of publish time − slot start [ms] of the radio's gains for the slots of ``rows`` (scored slots)."""
    wanted = {int(r["slot"]) for r in rows if r.get("slot")}
    return _p95([(int(p["published_ns"]) - int(p["slot_start_ns"])) / 1e6 for p in published
                 if p.get("slot") and int(p["slot"]) in wanted and p.get("published_ns") and p.get("slot_start_ns")])


def no_gain_slots(rows: list[dict[str, str]]) -> int:
    """How many of ``rows`` (scored slots) the robot's ledger booked without a measured gain (``round_slot`` −1)."""
    return sum(1 for r in rows if not r.get("round_slot") or int(r["round_slot"]) < 0)


def world_lateness(report_dir: Path) -> tuple[dict, list[str]]:
    """The module's figures of one run's report folder, and what could not be read (a figure it needs stays
    out)."""
    out: dict = {}
    problems: list[str] = []
    try:
        rows = scored(read_rows(report_dir / "slots.csv"))
    except (OSError, KeyError, ValueError) as e:
        return out, [f"slots.csv: {e}"]
    parts = (("world_age_p95_ms", None, frame_age_p95_ms),
             ("base_late_p95_ms", TRUTH_LOG, base_late_p95_ms),
             ("channel_gain_p95_ms", CHANNEL_LOG, channel_gain_p95_ms))
    for key, log, figure in parts:
        try:
            out[key] = figure(rows) if log is None else figure(read_rows(report_dir / "recording" / log), rows)
        except (OSError, KeyError, ValueError) as e:
            problems.append(f"{log or 'slots.csv'}: {e}")
    try:
        out["channel_no_gain_slots"] = no_gain_slots(rows)
    except ValueError as e:
        problems.append(f"slots.csv round_slot: {e}")
    return out, problems
