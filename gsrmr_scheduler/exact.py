"""Certified optimum of P_GS (``exact``): with x binary, P_GS is a 0-1 knapsack with real weights, solved here by a
Pisinger-style expanding core with Pareto dynamic programming (its core: :mod:`gsrmr_scheduler._knapsack_kernel`).

The reduction, the bound, the tolerance and the certified gap past ``time_limit_s``: docs/scheduling.md, "P_GS is a
0-1 knapsack once x is binary" and "``exact``: certified optimum".
"""

from __future__ import annotations

import math
import time

import numpy as np

from gsrmr_scheduler import _knapsack_kernel as kernel
from gsrmr_scheduler.problem import Problem, Schedule, infeasibility_reason, schedule_from_x


def solve_exact(problem: Problem, *, time_limit_s: float | None = None, max_states: int = 2_000_000,
                rel_tol: float = 1e-12) -> Schedule:
    """Optimal binary schedule of P_GS with a certified gap (0 unless stopped by the limits)."""
    t0 = time.perf_counter()
    T = problem.slots
    x = np.ones(T, dtype=np.int8)
    reason = infeasibility_reason(problem)
    forced = ~problem.image_ok
    x[forced] = 0
    if reason is not None:
        # Least-loss schedule that is physically possible: images wherever possible.
        s = schedule_from_x(problem, x, "exact", notes=[f"infeasible: {reason}"])
        s.feasible = False
        s.solve_time_s = time.perf_counter() - t0
        return s
    notes: list[str] = []
    if np.any(forced):
        notes.append(f"{int(forced.sum())} slot(s) cannot carry an image (power not representable): forced keys")
    L = problem.gs_loss
    zero = problem.image_ok & (L == 0)
    x[zero] = 0
    cap = problem.loss_budget - math.fsum(L[forced].tolist())
    items = np.flatnonzero(problem.image_ok & (L > 0))
    w_all = L[items]
    v_all = problem.saving_j[items]
    with np.errstate(over="ignore"):
        e_all = np.minimum(v_all / w_all, np.finfo(np.float64).max)
    order = np.argsort(-e_all, kind="stable")
    idx, w, v, e = items[order], w_all[order], v_all[order], e_all[order]
    n = idx.size
    cw = np.cumsum(w)
    b = int(np.searchsorted(cw, cap, side="right"))
    y = np.zeros(n, dtype=bool)
    y[:b] = True
    steps = 0
    lb_saving_extra = 0.0  # upper bound on extra saving beyond the returned solution
    special = n == 0 or b >= n or bool(np.all(w == w[0])) or bool(np.all(v == v[0]))
    if not special:
        W0 = float(cw[b - 1]) if b > 0 else 0.0
        wmin_suffix = np.minimum.accumulate(w[::-1])[::-1].copy()
        Ws = np.array([W0])
        Vs = np.array([0.0])
        Ns = np.zeros(1, dtype=np.int64)
        s_i, t_i = b - 1, b
        z, z_node = 0.0, 0
        pool_j = np.full(1024, -1, dtype=np.int64)
        pool_p = np.full(1024, -1, dtype=np.int64)
        pool_n = 1  # node 0 = the break solution
        tol = rel_tol * max(float(np.sum(v[max(0, b - 1):b + 1])), float(v[b]))
        stopped = ""
        status = 0
        while status == 0:
            (Ws, Vs, Ns, s_i, t_i, steps, z, z_node, pool_j, pool_p, pool_n, status) = kernel.dp_chunk(
                w, v, e, wmin_suffix, cap, tol, Ws, Vs, Ns, s_i, t_i, steps, z, z_node, pool_j, pool_p, pool_n,
                64, max_states)
            if status == 2:
                stopped = f"state limit {max_states} reached"
            elif status == 0 and time_limit_s is not None and time.perf_counter() - t0 > time_limit_s:
                stopped = f"time limit {time_limit_s:g} s reached"
            if stopped:
                ub = kernel.max_bound(w, v, e, wmin_suffix, cap, Ws, Vs, s_i, t_i)
                lb_saving_extra = max(0.0, float(ub) - z)
                notes.append(f"exact: {stopped} after {steps} core steps; returning the incumbent with its "
                             "certified gap")
                break
        toggles: list[int] = []
        node = int(z_node)
        while node > 0:
            toggles.append(int(pool_j[node]))
            node = int(pool_p[node])
        for j in toggles:
            y[j] = ~y[j]
    x[idx[y]] = 0
    e_found = math.fsum(np.where(x == 1, problem.energy_image_j, problem.energy_key_j).tolist())
    e_lb = e_found - lb_saving_extra  # certified lower bound on the optimal energy
    repaired = False
    if not problem.budget_ok(x):
        # Float round-off at the capacity boundary: drop the least efficient keys until it fits.
        for j in np.flatnonzero(y)[::-1]:
            x[idx[j]] = 1
            if problem.budget_ok(x):
                break
        repaired = True
        notes.append("exact: rounding repair at the capacity boundary (gap no longer 0)")
    out = schedule_from_x(problem, x, "exact", notes=notes, iterations=steps)
    if lb_saving_extra == 0 and not repaired:
        out.optimality_gap = 0.0
    elif e_lb > 0:
        out.optimality_gap = max(0.0, (out.energy_j - e_lb) / e_lb)
    else:
        out.optimality_gap = None
        out.notes.append("exact: lower bound is 0 J, relative gap undefined")
    out.extras["energy_lower_bound_j"] = max(e_lb, 0.0)
    out.solve_time_s = time.perf_counter() - t0
    return out


def warm_up() -> float:
    """Load the numba kernel (≈1–2 s on the first call of a process, even from the on-disk cache).

    Long-running callers (the scheduler node) call this at start-up so their first real solve is fast.
    Returns the seconds it took.
    """
    t0 = time.perf_counter()
    p = Problem(channel_gain=np.array([1e-6, 2e-6, 3e-6, 4e-6]), gs_loss=np.array([0.04, 0.01, 0.03, 0.02]),
                loss_threshold=0.012)
    solve_exact(p)
    return time.perf_counter() - t0
