"""Baselines of the paper's Sec. V on P_GS that choose x (pure numpy): robomr, robogs, ranking, rounding,
search and exchange. The physical-layer baselines (maxrate, fairness) are :mod:`rate_allocation`.
"""

from __future__ import annotations

import math
import time

import numpy as np

from gsrmr_common import link_model as link
from gsrmr_scheduler.problem import Problem, Schedule, infeasibility_reason, schedule_from_x


def solve_robomr(problem: Problem) -> Schedule:
    """Vanilla RoboMR: every slot uploads its image (x = 1)."""
    return schedule_from_x(problem, np.ones(problem.slots, dtype=np.int8), "robomr")


def solve_robogs(problem: Problem) -> Schedule:
    """Vanilla GS: every slot uploads only its pose key (x = 0)."""
    return schedule_from_x(problem, np.zeros(problem.slots, dtype=np.int8), "robogs")


def _base_x(problem: Problem) -> tuple[np.ndarray, float, list[str]]:
    """x with forced keys (slots that cannot carry an image) and zero-loss keys; remaining capacity; notes."""
    x = np.ones(problem.slots, dtype=np.int8)
    forced = ~problem.image_ok
    x[forced] = 0
    x[problem.image_ok & (problem.gs_loss == 0)] = 0
    notes = []
    if np.any(forced):
        notes.append(f"{int(forced.sum())} slot(s) cannot carry an image (power not representable): forced keys")
    cap = problem.loss_budget - math.fsum(problem.gs_loss[forced].tolist())
    return x, cap, notes


def _infeasible(problem: Problem, method: str, reason: str) -> Schedule:
    x = np.where(problem.image_ok, 1, 0).astype(np.int8)
    s = schedule_from_x(problem, x, method, notes=[f"infeasible: {reason}"])
    s.feasible = False
    return s


def solve_ranking(problem: Problem) -> Schedule:
    """Paper eq. (ranking): keys for the smallest losses L_t (ascending) as long as the budget holds.

    Optimal when all gains are equal (paper Proposition 2). Slots that cannot carry an image are keys first.
    """
    reason = infeasibility_reason(problem)
    if reason:
        return _infeasible(problem, "ranking", reason)
    x, cap, notes = _base_x(problem)
    cand = np.flatnonzero(x == 1)
    order = cand[np.argsort(problem.gs_loss[cand], kind="stable")]
    cum = np.cumsum(problem.gs_loss[order])
    k = int(np.searchsorted(cum, cap, side="right"))
    x[order[:k]] = 0
    while k > 0 and not problem.budget_ok(x):  # float round-off of the cumulative sum
        k -= 1
        x[order[k]] = 1
    return schedule_from_x(problem, x, "ranking", notes=notes, iterations=1)


def relaxed_solution(problem: Problem, tol_iter: int = 200) -> tuple[np.ndarray, float]:
    """Exact continuous relaxation of P_GS (x ∈ [0,1], p continuous) by dual bisection on the loss multiplier.

    With p eliminated (rate tight), slot t costs ``f_t(x) = E^key_t·(e^{b·x}·e^{a} − 1)/(e^{a} − 1)``, convex;
    stationarity ``f_t'(x) = λ·L_t`` gives x_t in closed form (log domain), clipped to [0,1]; λ ≥ 0 is the
    smallest value meeting ``Σ L_t(1 − x_t) ≤ C``. Returns (x_relaxed, energy lower bound in J).
    Slots that cannot carry an image are 0; the caller checks feasibility first.
    """
    a = link.snr_exponent(problem.pose_bits, problem.slot_s, problem.bandwidth_hz)
    bexp = link.snr_exponent(problem.image_bits - problem.pose_bits, problem.slot_s, problem.bandwidth_hz)
    T = problem.slots
    x = np.zeros(T)
    ok = problem.image_ok & (problem.gs_loss > 0)
    L = problem.gs_loss[ok]
    # ln f'_t(x) = ln(τσ²/g · b) + a + b·x
    log_c = math.log(problem.slot_s * problem.noise_w * bexp) - np.log(problem.channel_gain[ok]) + a
    cap = problem.loss_budget - math.fsum(problem.gs_loss[~problem.image_ok].tolist())
    if L.size and math.fsum(L.tolist()) > cap:
        lo = float(np.min(log_c - np.log(L)))  # at this ln λ every x_t = 0
        hi = float(np.max(log_c + bexp - np.log(L)))  # at this ln λ every x_t = 1

        def x_of(log_lam: float) -> np.ndarray:
            return np.clip((log_lam + np.log(L) - log_c) / bexp, 0.0, 1.0)

        for _ in range(tol_iter):
            mid = 0.5 * (lo + hi)
            if math.fsum((L * (1 - x_of(mid))).tolist()) <= cap:
                hi = mid
            else:
                lo = mid
            if hi - lo < 1e-13 * max(1.0, abs(hi)):
                break
        x[ok] = x_of(hi)
    x[problem.image_ok & ~ok] = 0.0
    return x, relaxed_energy_j(problem, x)


def relaxed_energy_j(problem: Problem, x: np.ndarray) -> float:
    """Energy (J) of a fractional x with tight rate: ``Σ τ(σ²/g)(2^{(S + x(I−S))/τB} − 1)``."""
    bits = problem.pose_bits + np.asarray(x) * (problem.image_bits - problem.pose_bits)
    p = link.required_power_w(bits, problem.channel_gain, problem.slot_s, problem.bandwidth_hz, problem.noise_w)
    p = np.where(np.isfinite(p), p, 0.0)
    return link.energy_j(p, problem.slot_s)


def repair(problem: Problem, x: np.ndarray) -> tuple[np.ndarray, int]:
    """Make binary x meet the loss budget: turn keys into images, least saving per unit loss first.

    Returns (x, number of flips). Forced keys (no image possible) are never flipped.
    """
    x = np.asarray(x, dtype=np.int8).copy()
    flips = 0
    if problem.budget_ok(x):
        return x, 0
    cand = np.flatnonzero((x == 0) & problem.image_ok & (problem.gs_loss > 0))
    eff = problem.saving_j[cand] / problem.gs_loss[cand]
    excess = problem.loss_sum(x) - problem.loss_budget
    for t in cand[np.argsort(eff, kind="stable")]:
        x[t] = 1
        flips += 1
        excess -= problem.gs_loss[t]
        if excess <= 0 and problem.budget_ok(x):
            break
    return x, flips


def solve_rounding(problem: Problem, threshold: float = 0.5) -> Schedule:
    """Continuous relaxation (solved exactly) plus rounding at ``threshold``, then a feasibility repair."""
    reason = infeasibility_reason(problem)
    if reason:
        return _infeasible(problem, "rounding", reason)
    xr, e_lb = relaxed_solution(problem)
    x = np.where(xr >= threshold, 1, 0).astype(np.int8)
    x[~problem.image_ok] = 0
    x, flips = repair(problem, x)
    notes = [f"relaxation energy {e_lb:.6g} J (a lower bound on P_GS)"]
    if flips:
        notes.append(f"rounded x broke the loss budget: {flips} key(s) turned back into images")
    s = schedule_from_x(problem, x, "rounding", notes=notes, iterations=1)
    s.extras["relaxed_energy_j"] = e_lb
    s.extras["fractional_slots"] = int(np.sum((xr > 1e-9) & (xr < 1 - 1e-9)))
    return s


def solve_search(problem: Problem, *, seed: int = 0, max_proposals: int = 50_000,
                 time_limit_s: float | None = None) -> Schedule:
    """Randomized local search from the ranking solution — *our reading* of the paper's cited baseline.

    The paper names "local search" without details. Here: draw a move at random (seeded ``seed``) — with
    probability ½ a **flip** of one random slot, otherwise a **swap** of a random image slot with a random
    key slot — and accept it when the schedule stays within the loss budget and its energy strictly
    drops. Stops after ``max_proposals`` proposals or ``time_limit_s``. Deterministic for a given seed;
    ``extras`` records the seed, proposals and accepted moves. The deterministic best-improvement 1-for-k
    exchange is :func:`solve_exchange`.
    """
    t0 = time.perf_counter()
    start = solve_ranking(problem)
    if not start.feasible:
        start.method = "search"
        return start
    rng = np.random.default_rng(int(seed))
    x = start.x.astype(np.int8).copy()
    v, L = problem.saving_j, problem.gs_loss
    movable = np.flatnonzero(problem.image_ok & (L > 0))
    cap = problem.loss_budget
    loss = problem.loss_sum(x)
    accepted = proposals = 0
    notes: list[str] = []
    if movable.size:
        # index lists of the movable image and key slots, kept in sync with x (O(1) moves)
        pos = np.full(x.size, -1, np.int64)
        lists: dict[int, list[int]] = {0: [], 1: []}
        for t in movable:
            pos[t] = len(lists[int(x[t])])
            lists[int(x[t])].append(int(t))

        def move(t: int, to: int) -> None:
            src = lists[1 - to]
            last = src.pop()
            if last != t:
                src[pos[t]] = last
                pos[last] = pos[t]
            pos[t] = len(lists[to])
            lists[to].append(t)
            x[t] = to

        draws = rng.random((max_proposals, 3))
        for k in range(max_proposals):
            if time_limit_s is not None and k % 1024 == 0 and time.perf_counter() - t0 > time_limit_s:
                notes.append(f"search: time limit {time_limit_s:g} s reached")
                break
            proposals += 1
            imgs, keys = lists[1], lists[0]
            if draws[k, 0] < 0.5 or not imgs or not keys:  # flip one slot
                t = int(movable[int(draws[k, 1] * movable.size)])
                if x[t] == 1 and loss + L[t] <= cap and v[t] > 0:  # image → key: cheaper if it fits
                    loss += L[t]
                    move(t, 0)
                    accepted += 1
                # key → image never lowers the energy (v ≥ 0): rejected
            else:  # swap an image i (→ key) with a key j (→ image)
                i = imgs[int(draws[k, 1] * len(imgs))]
                j = keys[int(draws[k, 2] * len(keys))]
                if v[i] > v[j] and loss + L[i] - L[j] <= cap:
                    loss += L[i] - L[j]
                    move(i, 0)
                    move(j, 1)
                    accepted += 1
        if not problem.budget_ok(x):  # float drift of the running sum at the boundary: never return infeasible
            x, flips = repair(problem, x)
            notes.append(f"search: running loss sum drifted past the budget; {flips} key(s) back to images")
    s = schedule_from_x(problem, x, "search", notes=start.notes + notes, iterations=accepted)
    s.extras.update({"seed": int(seed), "proposals": proposals, "accepted_moves": accepted})
    return s


def solve_exchange(problem: Problem, *, max_iterations: int = 10_000, time_limit_s: float | None = None) -> Schedule:
    """Deterministic best-improvement local search from the ranking solution (1-for-k exchanges).

    Moves: image→key if it fits the remaining budget; exchange (image i→key, and the keys with the lowest
    saving per unit loss back to images until the budget holds) if the net saving is positive.
    Stops at a local optimum (no improving move), after ``max_iterations`` or ``time_limit_s``.
    """
    t0 = time.perf_counter()
    start = solve_ranking(problem)
    if not start.feasible:
        start.method = "exchange"
        return start
    x = start.x.copy()
    v = problem.saving_j
    L = problem.gs_loss
    movable = problem.image_ok & (L > 0)
    cap = problem.loss_budget
    it = 0
    notes: list[str] = []
    while it < max_iterations:
        if time_limit_s is not None and time.perf_counter() - t0 > time_limit_s:
            notes.append(f"exchange: time limit {time_limit_s:g} s reached")
            break
        slack = cap - problem.loss_sum(x)
        imgs = np.flatnonzero((x == 1) & movable)
        keys = np.flatnonzero((x == 0) & movable)
        if imgs.size == 0:
            break
        best_gain, move = 0.0, None
        fits = imgs[L[imgs] <= slack]
        if fits.size:
            i = fits[np.argmax(v[fits])]
            best_gain, move = float(v[i]), (int(i), None)
        if keys.size:
            # Insert image i as a key and eject the keys with the lowest saving per unit loss until it fits
            # (a 1-for-k exchange; k = 1 is the plain swap).
            ko = keys[np.argsort(v[keys] / L[keys], kind="stable")]
            cw = np.cumsum(L[ko])
            cv = np.cumsum(v[ko])
            need = L[imgs] - slack
            pos = np.searchsorted(cw, need, side="left")  # eject ko[:pos+1]
            valid = (need > 0) & (pos < ko.size)
            if np.any(valid):
                gains = np.full(imgs.size, -np.inf)
                gains[valid] = v[imgs[valid]] - cv[pos[valid]]
                r = int(np.argmax(gains))
                if gains[r] > best_gain:
                    best_gain, move = float(gains[r]), (int(imgs[r]), ko[: int(pos[r]) + 1])
        if move is None or best_gain <= 0:
            break
        i, ejected = move
        x_try = x.copy()
        x_try[i] = 0
        if ejected is not None:
            x_try[ejected] = 1
        if not problem.budget_ok(x_try):  # float round-off at the boundary: stop rather than cycle
            break
        x = x_try
        it += 1
    return schedule_from_x(problem, x, "exchange", notes=start.notes + notes, iterations=it)
