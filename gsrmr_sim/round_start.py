"""Where the scored round starts in a server's ``slots.csv`` rows (``gsrmr-demo``, one robot or a fleet).

Round 2 starts when the robot sets off: the robot's ledger says so (:func:`first_round_row`), else the simulated
radio's own log (:func:`radio_round_row`); a stack without a radio, the first pose key that moved
(:func:`first_moving_slot`).
"""

from __future__ import annotations

import re

from gsrmr_sim.world.kinematics import has_moved

RADIO_ROUND_START = re.compile(r"round clock of the channel starts at slot (\d+)")
RADIO_GRACE_SLOTS = 20  # the server's rows must reach this far past the radio's start before its log is used


def first_round_row(rows: list[dict], *, moved_key_fallback: bool = True) -> int | None:
    """Index of the row of the round's first slot: where the radio's ``round_slot`` (through the robot's
    ledger) is 0 — the slot the channel's fading index starts from, so runs with one channel seed score
    the same fading; without round slots, the first slot whose pose key moved if ``moved_key_fallback`` (a stack
    without a simulated radio). With a radio the fallback must stay off: a map → odom correction moves the key of a
    robot that is still parked."""
    for i, r in enumerate(rows):
        k = r.get("round_slot")
        if k is not None and k >= 0:
            return max(0, i - int(k))
    return first_moving_slot(rows) if moved_key_fallback else None


def first_moving_slot(rows: list[dict]) -> int | None:
    """Index of the first row whose pose key has moved from the first keyed pose: round 2 starts when
    the robot sets off (the mock camera starts its round clock then too). None before that."""
    rest = None
    for i, r in enumerate(rows):
        if r["pose_a_m"] is None or r["source"] not in ("image", "render"):
            continue
        pose = (r["pose_a_m"], r["pose_b_m"], r["pose_theta_rad"])
        rest = rest or pose
        if has_moved(pose, rest):
            return i
    return None


def radio_round_row(rows: list[dict], radio_log: str) -> int | None:
    """Row of the round's first slot from the simulated radio's own log (``gsrmr-sim-channel``: "round clock of
    the channel starts at slot S", the slot whose ``round_slot`` is 0) — for a server so overloaded that neither
    the robot's ledger (round slots) nor a moved pose key reached it (:func:`first_round_row` finds nothing);
    None until its rows reach :data:`RADIO_GRACE_SLOTS` slots past S."""
    found = RADIO_ROUND_START.search(radio_log)
    if found is None or not rows or rows[-1]["slot"] < int(found.group(1)) + RADIO_GRACE_SLOTS:
        return None
    start = int(found.group(1))
    return next(i for i, r in enumerate(rows) if r["slot"] >= start)
