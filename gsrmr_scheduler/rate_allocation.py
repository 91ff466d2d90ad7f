"""The physical-layer baselines of the paper's Sec. V on P_GS (pure numpy): ``maxrate`` and ``fairness``.

Both ignore the MR loss and spend an energy budget; what a slot then delivers, the charge of an undelivered slot
(``undelivered_loss``) and where the budget comes from: docs/scheduling.md, "Baselines".
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from gsrmr_common import link_model as link
from gsrmr_scheduler.problem import IMAGE, KEY, NONE, Problem, Schedule

#: Relative slack when comparing delivered bits against a payload (rate computed in floating point).
BITS_RTOL = 1e-9


def spend_budget_j(problem: Problem, energy_budget_j: float | None, method: str) -> float:
    """The energy ``method`` spends: ``energy_budget_j``, else the problem's; ValueError when neither is given."""
    if energy_budget_j is not None:
        e = float(energy_budget_j)
        if not math.isfinite(e) or e < 0:
            raise ValueError("energy_budget_j must be a finite number >= 0")
        return e
    if problem.energy_budget_j is not None:
        return problem.energy_budget_j
    raise ValueError(f"{method} spends an energy budget: give energy_budget_j, the problem's energy_budget_j, "
                     "or solve(..., budget_from=METHOD)")


def _classify(problem: Problem, power_w: np.ndarray, undelivered_loss: Any) -> tuple[np.ndarray, list[str], float]:
    bits = np.asarray(link.slot_bits(power_w, problem.channel_gain, problem.slot_s, problem.bandwidth_hz,
                                     problem.noise_w))
    img = bits >= problem.image_bits * (1 - BITS_RTOL)
    key = ~img & (bits >= problem.pose_bits * (1 - BITS_RTOL))
    delivered = np.where(img, IMAGE, np.where(key, KEY, NONE))
    if isinstance(undelivered_loss, str):
        if undelivered_loss != "gs":
            raise ValueError(f"undelivered_loss must be 'gs' or a number, got {undelivered_loss!r}")
        none_cost = problem.gs_loss
    else:
        c = float(undelivered_loss)
        if not math.isfinite(c) or c < 0:
            raise ValueError("undelivered_loss must be a finite number >= 0")
        none_cost = np.full(problem.slots, c)
    loss = math.fsum(problem.gs_loss[key].tolist()) + math.fsum(none_cost[~img & ~key].tolist())
    return img.astype(np.int8), delivered.tolist(), loss / problem.slots


def _phy_schedule(problem: Problem, method: str, power: np.ndarray, budget: float, notes: list[str],
                  undelivered_loss: Any) -> Schedule:
    x, delivered, mean_loss = _classify(problem, power, undelivered_loss)
    energy = link.energy_j(power, problem.slot_s)
    n_none = delivered.count(NONE)
    notes = [*notes, f"{delivered.count(IMAGE)} image(s), {delivered.count(KEY)} key(s), {n_none} undelivered slot(s)"]
    feasible = mean_loss * problem.slots <= problem.loss_budget and energy <= budget * (1 + 1e-9)
    s = Schedule(method=method, x=x, power_w=power, energy_j=energy, mean_loss=mean_loss, feasible=feasible,
                 iterations=1, delivered=delivered, notes=notes)
    s.extras["energy_budget_j"] = budget
    return s


def solve_maxrate(problem: Problem, *, energy_budget_j: float | None = None, undelivered_loss: Any = "gs") -> Schedule:
    """Water-filling: maximise Σ log2(1 + g_t p_t/σ²) s.t. τ Σ p_t ≤ budget; p_t = max(0, μ − σ²/g_t)."""
    budget, notes = spend_budget_j(problem, energy_budget_j, "maxrate"), []
    g = problem.channel_gain
    n = np.full(problem.slots, np.inf)
    live = g > 0
    n[live] = problem.noise_w / g[live]
    power = np.zeros(problem.slots)
    total = budget / problem.slot_s  # Σ p
    if total > 0 and np.any(live):
        order = np.argsort(n, kind="stable")
        ns = n[order][: int(live.sum())]
        cum = np.cumsum(ns)
        k_arr = np.arange(1, ns.size + 1)
        mu = (total + cum) / k_arr
        valid = mu > ns
        k = int(np.flatnonzero(valid)[-1]) + 1
        level = (total + cum[k - 1]) / k
        p_sorted = np.maximum(0.0, level - ns[:k])
        power[order[:k]] = p_sorted
    return _phy_schedule(problem, "maxrate", power, budget, notes, undelivered_loss)


def solve_fairness(problem: Problem, *, energy_budget_j: float | None = None, undelivered_loss: Any = "gs"
                   ) -> Schedule:
    """Max-min rate: the same rate in every live slot, ``p_t = (σ²/g_t)·γ`` with ``τ Σ p_t = budget``.

    Slots with gain 0 cannot get any rate; they are left out (lexicographic max-min) and noted.
    """
    budget, notes = spend_budget_j(problem, energy_budget_j, "fairness"), []
    g = problem.channel_gain
    live = g > 0
    power = np.zeros(problem.slots)
    if np.any(~live):
        notes.append(f"{int((~live).sum())} slot(s) with gain 0 get no power")
    if np.any(live) and budget > 0:
        # γ = budget / (τ Σ σ²/g) computed as a ratio of logs-safe sums (σ²/g may be huge).
        inv = problem.noise_w / g[live]
        s = math.fsum(inv.tolist())
        if math.isfinite(s) and s > 0:
            gamma = budget / problem.slot_s / s
            power[live] = inv * gamma
        else:
            notes.append("fairness: Σ σ²/g overflows; no power allocated")
    return _phy_schedule(problem, "fairness", power, budget, notes, undelivered_loss)
