"""Accelerated penalty optimisation (APO, paper Sec. IV) with CVXPY: :func:`solve_apo`.

The penalty, the difference-of-convex iterations, the substitution that conditions the exponential cone, the solver
chain and the optional post-step ``repair_budget`` (ours): docs/scheduling.md, "``apo`` (paper Sec. IV)".
"""

from __future__ import annotations

import math
import time
from typing import Any
import warnings

import numpy as np

from gsrmr_common import link_model as link
from gsrmr_scheduler.baselines import relaxed_energy_j, repair, solve_ranking
from gsrmr_scheduler.problem import Problem, Schedule, infeasibility_reason, schedule_from_x

DEFAULT_SOLVERS = ("CLARABEL", "SCS")
#: Default β = BETA_SCALE / mean(E_img − E_key): calibrated on paper-default instances (docs/scheduling.md);
#: the paper does not state its β.
BETA_SCALE = 30.0


def _phi(x: np.ndarray) -> float:
    """The paper's zero-one loss ``(1/T)·Σ x(1 − x)`` (Fig. 4a)."""
    return float(np.mean(x * (1.0 - x)))


class _DcProblem:
    """The convex DC subproblem over the free slots, compiled once (DPP parameters in the objective)."""

    def __init__(self, problem: Problem, free: np.ndarray, cap: float) -> None:
        import cvxpy as cp  # late: importing cvxpy costs ~1 s, and only APO needs it
        n = int(free.sum())
        # DPP compilation builds an O(n²) parameter map: only worth it for small n (re-solved every iteration).
        self.dpp = n <= 1000
        a = link.snr_exponent(problem.pose_bits, problem.slot_s, problem.bandwidth_hz)
        a_i = link.snr_exponent(problem.image_bits, problem.slot_s, problem.bandwidth_hz)
        self.q_img = float(np.expm1(a_i))
        self.e_img = problem.energy_image_j[free]
        self.u = cp.Variable(n, nonneg=True)
        self.x = cp.Variable(n)
        self.c_u = cp.Parameter(n, nonneg=True)
        self.c_x = cp.Parameter(n)
        L = problem.gs_loss[free]
        cons = [cp.log(1 + self.q_img * self.u) >= a + (a_i - a) * self.x, self.x >= 0, self.x <= 1]
        if cap < math.fsum(L.tolist()):
            # Loss budget scaled to O(1).
            ls = max(float(L.max()), 1e-300)
            cons.append((L / ls) @ (1 - self.x) <= cap / ls)
        self.prob = cp.Problem(cp.Minimize(self.c_u @ self.u + self.c_x @ self.x), cons)

    def solve(self, lin_x_j: np.ndarray, solvers: tuple[str, ...], deadline: float | None = None
              ) -> tuple[np.ndarray | None, str, list[str]]:
        """Minimise ``Σ E_img u + lin_x·x`` (both in J); returns (x or None, solver/status, notes).

        ``deadline`` (``time.perf_counter()`` value) is passed to the solvers as their own time limit.
        """
        import cvxpy as cp
        scale = max(float(np.max(self.e_img)), float(np.max(np.abs(lin_x_j))) if lin_x_j.size else 0.0, 1e-300)
        attempts: list[tuple[str, float]] = []
        for s in solvers:
            attempts += [(s, 1.0), (s, 1e3)]
        notes: list[str] = []
        fallback: tuple[np.ndarray, str] | None = None
        for solver, factor in attempts:
            kwargs: dict[str, Any] = {}
            if deadline is not None:
                remaining = deadline - time.perf_counter()
                if remaining <= 0:
                    notes.append(f"time limit reached before trying {solver} (scale x{factor:g})")
                    break
                if solver == "CLARABEL":
                    kwargs["time_limit"] = remaining
                elif solver == "SCS":
                    kwargs["time_limit_secs"] = remaining
            self.c_u.value = self.e_img / scale * factor
            self.c_x.value = lin_x_j / scale * factor
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # "inaccurate" is recorded in the notes instead
                    self.prob.solve(solver=solver, ignore_dpp=not self.dpp, **kwargs)
                status = self.prob.status
            except (cp.error.SolverError, ValueError, ArithmeticError) as exc:
                notes.append(f"{solver} (scale x{factor:g}) failed: {type(exc).__name__}: {str(exc)[:80]}")
                continue
            xv = self.x.value
            if status == cp.OPTIMAL and xv is not None and np.all(np.isfinite(xv)):
                return np.clip(xv, 0.0, 1.0), f"{solver}:{status}", notes
            notes.append(f"{solver} (scale x{factor:g}) returned {status}")
            if status == cp.OPTIMAL_INACCURATE and xv is not None and np.all(np.isfinite(xv)) and fallback is None:
                fallback = (np.clip(xv, 0.0, 1.0), f"{solver}:{status}")
        if fallback is not None:
            return fallback[0], fallback[1], notes
        return None, "failed", notes


def solve_apo(problem: Problem, *, beta: float | None = None, iterations: int = 10, tol: float = 1e-3,
              init: str = "ranking", solvers: Any = DEFAULT_SOLVERS, time_limit_s: float | None = None,
              repair_budget: bool = True) -> Schedule:
    """APO as in the paper: DC iterations on the penalised relaxation from the ranking initialisation.

    Args:
        beta: penalty parameter β > 0 (φ = (1/β)Σx(1−x) in joules). Default ``30/mean(E_img − E_key)``: a
            fully fractional slot (x(1−x) = ¼) is charged 1/120 of a typical saving (the paper does not
            state β).
        iterations: N, the maximum number of DC iterations (paper: 10).
        tol: stop when ‖x^[n] − x^[n−1]‖₂ < tol.
        init: ``"ranking"`` (paper) or ``"ones"`` (all images, the naive start).
        solvers: CVXPY solver names tried in order (each also once rescaled).
        time_limit_s: stop iterating when exceeded (the current iterate is rounded); the remaining time is
            also passed to CLARABEL (``time_limit``) and SCS (``time_limit_secs``).
        repair_budget: our post-step (not the paper's): when the rounding at 0.5 breaks the loss budget,
            turn the least efficient keys back into images. False returns the paper's rounding as is
            (``feasible`` False if it breaks the budget).

    History entries: ``iteration``, ``dx_norm``, ``phi`` ((1/T)Σx(1−x)), ``objective_j`` (τΣp + φ(x) at the
    iterate with tight p), ``energy_relaxed_j``, ``solver``.
    """
    t0 = time.perf_counter()
    if isinstance(solvers, str):
        solvers = tuple(s.strip().upper() for s in solvers.split(",") if s.strip())
    solvers = tuple(str(s).upper() for s in solvers)
    iterations = int(iterations)
    if iterations < 0:
        raise ValueError("iterations must be >= 0")
    if init not in ("ranking", "ones"):
        raise ValueError("init must be 'ranking' or 'ones'")
    reason = infeasibility_reason(problem)
    if reason:
        s = solve_ranking(problem)
        s.method = "apo"
        return s
    free = problem.image_ok.copy()
    forced = ~problem.image_ok
    cap = problem.loss_budget - math.fsum(problem.gs_loss[forced].tolist())
    sav = problem.saving_j[free]
    if beta is None:
        beta = BETA_SCALE / float(np.mean(sav)) if sav.size and np.mean(sav) > 0 else 1.0
    beta = float(beta)
    if not (math.isfinite(beta) and beta > 0):
        raise ValueError("beta must be a finite number > 0")
    start = solve_ranking(problem)
    x_full = start.x.astype(np.float64) if init == "ranking" else np.where(problem.image_ok, 1.0, 0.0)
    notes = list(start.notes)
    history: list[dict[str, Any]] = []

    def objective_j(xf: np.ndarray) -> tuple[float, float]:
        e = relaxed_energy_j(problem, xf)
        return e + float(np.sum(xf * (1 - xf))) / beta, e

    n_done = 0
    if free.any() and iterations > 0:
        dc = _DcProblem(problem, free, cap)
        for it in range(1, iterations + 1):
            if time_limit_s is not None and time.perf_counter() - t0 > time_limit_s:
                notes.append(f"apo: time limit {time_limit_s:g} s reached after {n_done} iteration(s)")
                break
            xs = x_full[free]
            lin = (1.0 - 2.0 * xs) / beta
            deadline = None if time_limit_s is None else t0 + time_limit_s
            xv, status, snotes = dc.solve(lin, solvers, deadline)
            notes += [f"iteration {it}: {m}" for m in snotes]
            if xv is None:
                if deadline is not None and time.perf_counter() >= deadline:
                    notes.append(f"apo: time limit {time_limit_s:g} s reached during iteration {it}; keeping the "
                                 "previous iterate")
                else:
                    notes.append(f"apo: every solver failed at iteration {it}; keeping the previous iterate")
                break
            x_new = x_full.copy()
            x_new[free] = xv
            dx = float(np.linalg.norm(x_new - x_full))
            x_full = x_new
            obj, e_rel = objective_j(x_full)
            n_done = it
            history.append({"iteration": it, "dx_norm": dx, "phi": _phi(x_full), "objective_j": obj,
                            "energy_relaxed_j": e_rel, "solver": status})
            if dx < tol:
                break
    obj, e_rel = objective_j(x_full)
    xb = np.where(x_full >= 0.5, 1, 0).astype(np.int8)
    xb[forced] = 0
    paper = schedule_from_x(problem, xb, "apo")
    flips = 0
    if repair_budget:
        xb, flips = repair(problem, xb)
    if flips:
        notes.append(f"apo: rounding broke the loss budget; repair turned {flips} key(s) back into images")
    s = schedule_from_x(problem, xb, "apo", notes=notes, iterations=n_done, history=history)
    s.extras.update({"beta": beta, "relaxed_energy_j": e_rel, "relaxed_objective_j": obj, "relaxed_phi": _phi(x_full),
                     "relaxed_x": [float(v) for v in x_full],
                     "paper": {"energy_j": paper.energy_j, "mean_loss": paper.mean_loss, "images": int(paper.x.sum()),
                               "feasible": paper.feasible},
                     "repair_flips": flips})
    s.solve_time_s = time.perf_counter() - t0
    return s
