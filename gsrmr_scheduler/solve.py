"""One entry point for every method: :func:`solve` (``solve(problem, method, **options)`` → a
:class:`~gsrmr_scheduler.problem.Schedule`).

The registry :data:`METHODS` lives here and nowhere else: a method that needs another one's result (the
rate-allocation baselines' ``budget_from``) gets it through :func:`solve`, so no solver module imports the registry.
"""

from __future__ import annotations

from collections.abc import Callable
import inspect
import math
import time
from typing import Any

import numpy as np

from gsrmr_scheduler import apo, baselines, exact, rate_allocation
from gsrmr_scheduler.problem import Problem, Schedule

#: Method name → solver function ``f(problem, **options) -> Schedule``.
METHODS: dict[str, Callable[..., Schedule]] = {
    "apo": apo.solve_apo,
    "exact": exact.solve_exact,
    "ranking": baselines.solve_ranking,
    "rounding": baselines.solve_rounding,
    "search": baselines.solve_search,
    "exchange": baselines.solve_exchange,
    "maxrate": rate_allocation.solve_maxrate,
    "fairness": rate_allocation.solve_fairness,
    "robomr": baselines.solve_robomr,
    "robogs": baselines.solve_robogs,
}
#: Methods that spend an energy budget; without one (option or problem) they get the energy of the method their
#: ``budget_from`` option names (default :data:`DEFAULT_BUDGET_FROM`; the paper uses ``"apo"``).
BUDGET_SPENDERS = frozenset({"maxrate", "fairness"})
DEFAULT_BUDGET_FROM = "exact"


def method_options(method: str) -> list[str]:
    """Names of the keyword options a method accepts (``time_limit_s`` is accepted by all)."""
    sig = inspect.signature(METHODS[method])
    names = [n for n, p in sig.parameters.items() if p.kind == p.KEYWORD_ONLY or (n != "problem" and
                                                                                p.default is not p.empty)]
    return [*names, "budget_from"] if method in BUDGET_SPENDERS else names


def solve(problem: Problem, method: str, **options: Any) -> Schedule:
    """Solve P_GS with one method: the single entry point to every solver.

    Every result is checked before it is returned: no NaN or inf, no negative power, and ``feasible`` only if the
    loss budget ``Σ L_t·(1 − x_t) ≤ T·L_th`` holds.

    Args:
        problem: the instance (gains dimensionless ``|h|²``, payloads in bits, noise in W, slots of
            τ = ``problem.slot_s`` seconds).
        method: a key of :data:`METHODS` (``"exact"``, ``"apo"``, ``"ranking"``, …).
        **options: the method's keyword options (:func:`method_options` names them). ``time_limit_s`` (s, > 0)
            is accepted by every method and honoured by ``exact`` (it returns the incumbent with a certified
            gap), ``apo`` (it stops iterating), ``search`` and ``exchange``; the closed-form methods ignore it.
            ``maxrate`` and ``fairness`` also take ``budget_from``: the method whose energy (J) is their budget
            when neither their ``energy_budget_j`` nor the problem's gives one (default ``"exact"``).

    Returns:
        :class:`~gsrmr_scheduler.problem.Schedule`: per slot x (1 = image) and power (W), the energy (J),
        the mean loss, ``feasible``, and the wall-clock seconds of this call at least (``solve_time_s``).

    Raises:
        ValueError: an unknown method or option, ``time_limit_s`` ≤ 0, or a ``budget_from`` that is not a method
            choosing its own energy.

    Example:
        A 288-slot instance on the paper's route (Rician channel, seed 1), solved to optimality::

            import numpy as np
            from gsrmr_common.channel import ChannelModel, paper_route_distances
            from gsrmr_scheduler.problem import Problem
            from gsrmr_scheduler.solve import solve

            gains = ChannelModel(seed=1).gains(paper_route_distances(288))
            losses = np.random.default_rng(0).uniform(0.0, 0.096, 288)
            sched = solve(Problem(channel_gain=gains, gs_loss=losses, loss_threshold=0.03), "exact")
            sched.energy_j, sched.mean_loss, sched.optimality_gap  # J, ≤ 0.03, 0.0: certified optimal
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
    budget_note = None
    if method in BUDGET_SPENDERS:
        options, budget_note = _with_reference_budget(problem, options)
    sched = METHODS[method](problem, **options)
    if budget_note:
        sched.notes.insert(0, budget_note)
    elapsed = time.perf_counter() - t0
    sched.solve_time_s = max(sched.solve_time_s, elapsed) if sched.solve_time_s else elapsed
    _check(problem, sched)
    return sched


def _with_reference_budget(problem: Problem, options: dict[str, Any]) -> tuple[dict[str, Any], str | None]:
    """``options`` without ``budget_from``, and with ``energy_budget_j`` = the energy of the ``budget_from``
    method when neither the options nor the problem give a budget (then also the note saying so)."""
    options = dict(options)
    budget_from = options.pop("budget_from", DEFAULT_BUDGET_FROM)
    if options.get("energy_budget_j") is not None or problem.energy_budget_j is not None:
        return options, None
    if not isinstance(budget_from, str) or budget_from not in METHODS or budget_from in BUDGET_SPENDERS:
        choices = ", ".join(m for m in METHODS if m not in BUDGET_SPENDERS)
        raise ValueError(f"budget_from must be a method that chooses its own energy ({choices}), got {budget_from!r}")
    ref = solve(problem, budget_from)
    options["energy_budget_j"] = ref.energy_j
    return options, f"energy budget = {budget_from} energy {ref.energy_j:.6g} J (no budget given)"


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


def warm_up(method: str, **options: Any) -> tuple[float, float | None]:
    """Load the compiled knapsack kernel (1–2 s from the numba cache, ~8 s cold) and make ``method``'s first call
    (APO imports CVXPY: ~1 s), so that a long-running caller's first real solve is fast.

    Returns:
        The seconds the kernel took, and those of the method's first call (None for ``exact``: the kernel's).
    """
    kernel_s = exact.warm_up()
    if method == "exact":
        return kernel_s, None
    t0 = time.perf_counter()
    solve(Problem(channel_gain=np.array([1e-6, 2e-6, 3e-6, 4e-6]), gs_loss=np.array([0.04, 0.01, 0.03, 0.02]),
                  loss_threshold=0.012), method, **options)
    return kernel_s, time.perf_counter() - t0
