"""One entry point for every method: ``solve(problem, method, **options)`` → :class:`Schedule`."""

from __future__ import annotations

from collections.abc import Callable
import inspect
import math
import time
from typing import Any

import numpy as np

from gsrmr_server.scheduling import apo, baselines, exact
from gsrmr_server.scheduling.problem import Problem, Schedule

#: Method name → solver function ``f(problem, **options) -> Schedule``.
METHODS: dict[str, Callable[..., Schedule]] = {
    "apo": apo.solve_apo,
    "exact": exact.solve_exact,
    "ranking": baselines.solve_ranking,
    "rounding": baselines.solve_rounding,
    "search": baselines.solve_search,
    "exchange": baselines.solve_exchange,
    "maxrate": baselines.solve_maxrate,
    "fairness": baselines.solve_fairness,
    "robomr": baselines.solve_robomr,
    "robogs": baselines.solve_robogs,
}


def method_options(method: str) -> list[str]:
    """Names of the keyword options a method accepts (``time_limit_s`` is accepted by all)."""
    sig = inspect.signature(METHODS[method])
    return [n for n, p in sig.parameters.items() if p.kind == p.KEYWORD_ONLY or (n != "problem" and
                                                                               p.default is not p.empty)]


def solve(problem: Problem, method: str, **options: Any) -> Schedule:
    """Solve P_GS with ``method`` (a key of :data:`METHODS`).

    ``time_limit_s`` is honoured by ``exact`` (returns a certified gap), ``apo`` (stops iterating),
    ``search`` and ``exchange``; the closed-form methods ignore it. Raises ``ValueError`` for an unknown
    method or option.
    The result is checked: no NaN/inf, no negative power, and ``feasible`` only if the loss budget holds.
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    allowed = method_options(method)
    time_limit = options.pop("time_limit_s", None)
    if time_limit is not None:
        time_limit = float(time_limit)
        if not (time_limit > 0):
            raise ValueError("time_limit_s must be > 0")
        if "time_limit_s" in allowed:
            options["time_limit_s"] = time_limit
    for key in options:
        if key not in allowed:
            raise ValueError(f"method {method!r} has no option {key!r} (options: {', '.join(allowed) or 'none'})")
    t0 = time.perf_counter()
    sched = METHODS[method](problem, **options)
    elapsed = time.perf_counter() - t0
    sched.solve_time_s = max(sched.solve_time_s, elapsed) if sched.solve_time_s else elapsed
    _check(problem, sched)
    return sched


def _check(problem: Problem, s: Schedule) -> None:
    """Last line of defence: the guarantees every method makes."""
    if s.power_w.shape != (problem.slots,) or s.x.shape != (problem.slots,):
        raise AssertionError(f"{s.method}: schedule has the wrong length")
    if not np.all(np.isfinite(s.power_w)) or np.any(s.power_w < 0):
        raise AssertionError(f"{s.method}: power must be finite and >= 0")
    if not math.isfinite(s.energy_j) or not math.isfinite(s.mean_loss):
        raise AssertionError(f"{s.method}: energy and loss must be finite")
    if s.feasible and s.mean_loss * problem.slots > problem.loss_budget * (1 + 1e-12) + 1e-300:
        s.feasible = False
        s.notes.append("loss budget violated: marked infeasible")
