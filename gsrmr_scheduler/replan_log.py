"""What the scheduler node reports about its replans: their times, why they ran, the one-line summary of a plan and
the ``/diagnostics`` values of the planner (pure, no ROS)."""

from __future__ import annotations

import json
import math

from gsrmr_common.wire import ScheduleMsg
from gsrmr_scheduler.planner import OnlinePlanner, PlanResult

#: How many recent plan times predict how long the next plan takes (its p90).
PLAN_TIME_WINDOW = 20


def ratio_text(value: float | None) -> str:
    """A fraction as a percentage, or ``n/a``."""
    return "n/a" if value is None else f"{value:.0%}"


def changed_slots(previous: ScheduleMsg | None, schedule: ScheduleMsg) -> int:
    """How many slots ``schedule`` switches image/key against ``previous`` (slots both cover)."""
    if previous is None:
        return 0
    changed = 0
    for i, x in enumerate(schedule.x):
        old = previous.lookup(schedule.first_slot + i)
        changed += int(old is not None and old[0] != int(x))
    return changed


def plan_summary(result: PlanResult, changed: int) -> str:
    """One line about a plan (the replan log line and the ``gsrmr/replan`` answer)."""
    return (f"method={result.method} T={len(result.schedule.x)} images={result.images} "
            f"energy_j={result.energy_j:.6g} predicted_mean_loss={result.mean_predicted_loss:.4f} "
            f"budget={result.budget:.4f} feasible={result.feasible} solve_time_s={result.solve_time_s:.4f} "
            f"changed_slots={changed}")


def service_answer(previous: PlanResult | None, result: PlanResult, changed: int) -> tuple[bool, str]:
    """The ``gsrmr/replan`` answer: success (the plan is feasible) and what changed against ``previous``."""
    what = f"{changed} slot(s) switched image/key against the previous schedule"
    if previous is not None and not changed:
        what = "no slot changed image/key (same inputs give the same optimum)"
    return bool(result.feasible), plan_summary(result, changed) + "; " + what


class ServiceGate:
    """``gsrmr/replan`` answers at most once per ``replan_min_interval_s``; refusals are counted."""

    def __init__(self) -> None:
        self.last_s: float | None = None  # monotonic time of the last replan the service ran
        self.refused = 0

    def refusal(self, now_s: float, interval_s: float, period_s: float) -> str | None:
        """Why a call at ``now_s`` is refused (counted), or None (the call is let through and remembered)."""
        if self.last_s is not None and now_s - self.last_s < interval_s:
            self.refused += 1
            return (f"rate-limited: one replan per {interval_s:g} s on this service (the last "
                    f"{now_s - self.last_s:.2f} s ago); the schedule is replanned every {period_s:g} s anyway")
        self.last_s = now_s
        return None

    def problems(self) -> list[str]:
        """What ``/diagnostics`` warns about."""
        return [f"gsrmr/replan calls refused (rate limit): {self.refused}"] if self.refused else []


class ReplanLog:
    """Every replan's reason, wall time, solve time and slack (end of the first covered slot − schedule ready [s]:
    > 0 in time, < 0 late; ``bench/acceptance/demo.py``'s ``replans_late``)."""

    def __init__(self) -> None:
        self.last: PlanResult | None = None
        self.replans: dict[str, int] = {}
        self.solve_times_s: list[float] = []
        self.plan_times_s: list[float] = []  # wall time of the whole plan (predictor, solver, thresholds)
        self.plan_slack_s: list[float] = []
        self._logged_cap: float | None = None

    def expected_plan_ns(self) -> int:
        """How long the next plan will take [ns]: the p90 of the recent ones (0 before the first)."""
        recent = sorted(self.plan_times_s[-PLAN_TIME_WINDOW:])
        return int(1e9 * recent[int(0.9 * (len(recent) - 1))]) if recent else 0

    def record(self, reason: str, result: PlanResult, plan_time_s: float, slack_s: float) -> None:
        """A finished replan."""
        self.last = result
        self.plan_times_s.append(plan_time_s)
        del self.plan_times_s[:-100]
        self.plan_slack_s.append(round(slack_s, 4))
        del self.plan_slack_s[:-10_000]
        self.solve_times_s.append(round(result.solve_time_s, 6))
        del self.solve_times_s[:-10_000]
        kind = reason.split(":")[0]
        self.replans[kind] = self.replans.get(kind, 0) + 1

    def image_cap_news(self, planner: OnlinePlanner) -> str | None:
        """The log line about the uplink image cap when it appeared, went or moved by 0.05 since the last one."""
        cap = planner.last_image_cap
        if (cap is None) == (self._logged_cap is None) and (cap is None or abs(cap - self._logged_cap) < 0.05):
            return None
        self._logged_cap = cap
        if cap is None:
            return "uplink image cap: image_cap=none (the link carries an image per slot)"
        link_cap = planner.link_cap
        return (f"uplink image cap: image_cap={cap:.3f} ({link_cap.images_held_back()} held back in the last slots, "
                f"{ratio_text(link_cap.delivery_ratio())} of the last images composed in their slot; the plan keeps "
                "the images saving the most loss per joule)")

    def problems(self) -> list[str]:
        """What ``/diagnostics`` warns about: an infeasible plan."""
        return ["plan infeasible"] if self.last is not None and not self.last.feasible else []

    def diagnostic_values(self, planner: OnlinePlanner, next_slot: int) -> dict[str, object]:
        """The planner's state for ``/diagnostics`` (``next_slot``: the slot after now)."""
        r, cfg, budget, lp = self.last, planner.config, planner.budget, planner.forecast.model
        values: dict[str, object] = {
            "replans": json.dumps(self.replans), "loss_map_cells": len(planner.loss_map.cells),
            "loss_spent": round(budget.loss_spent, 6), "slots_accounted": budget.slots_done,
            # what L_t is predicted by: the burst model, or the loss map as it is (the oracle's survey)
            "loss_model": "map" if lp is None else "burst", "image_slot_loss": round(cfg.image_slot_loss, 6),
            "loss_sample_offset": round(cfg.loss_sample_offset, 6),
            # the image fraction the last plan was held to because the robot held images back (-1: none)
            "link_image_cap": -1 if planner.last_image_cap is None else round(planner.last_image_cap, 4),
            "images_held_back": planner.link_cap.images_held_back(),
            "image_delivery_ratio": ratio_text(planner.link_cap.delivery_ratio()),
            **planner.fix_age.diagnostic_values(next_slot - 1)}
        if lp is not None:
            values.update({"loss_level_ratio": round(math.exp(lp.level), 4), "loss_margin_factor": round(lp.margin, 4),
                           "loss_burst_factor": round(lp.burst_factor, 4)})
        if cfg.round_slots:
            remaining = budget.round_remaining(next_slot)
            values["round_slots_remaining"] = -1 if remaining is None else remaining
        if r is not None:
            values.update({"method": r.method, "horizon": len(r.schedule.x), "images": r.images,
                           "energy_j": r.energy_j, "feasible": r.feasible, "solve_time_s": round(r.solve_time_s, 5),
                           "seq": r.schedule.seq})
        return values
