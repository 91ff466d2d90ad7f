"""Scheduler benchmark: solve time, energy and gap to the certified optimum for every method.

Prints three tables (paper-default instances from ``gsrmr-schedule make-problem``: τ = 0.1 s, I = 67.2 kbit,
S = 192 bit, B = 1 MHz, σ² = −60 dBm, Rician K = 1 at ~10 m, L_t ~ U(0, 0.096)):

1. method × T ∈ {288, 1e4, 1e5} at L_th = 0.03: median solve time, energy, gap to exact, feasible;
   plus the peak RSS of a fresh process solving T = 1e5 with ``exact``;
2. APO with N ∈ {1, 2, 5, 10, 20, 30} (tol = 0, so exactly N iterations) at T = 288: time and gap;
3. every method's energy relative to exact at L_th ∈ {0.02, …, 0.04}, mean over seeds (maxrate/fairness get
   APO's energy as budget, as in the paper, and their resulting mean loss is shown).

Usage: ``.venv/bin/python bench/perf/scheduler.py [--full]``. The default run (what ``make bench`` runs; 141–151 s on
the 2 shared cores, load 1–5) leaves APO out at T = 1e5, solves T = 1e5 once per method (exchange stops at its 60 s
limit there) and averages table 3 over 3 seeds. ``--full`` (332 s at load 2–3, of which 300 s are the 60 s limits of
APO at 1e4 and 1e5 and of exchange's 3 repeats at 1e5): APO at every T, 3 repeats at 1e5, 10 seeds — the tables of
docs/scheduling.md, "Measured". ``--quick`` is the default run (the flag is kept for old command lines).
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time

import numpy as np

from gsrmr_scheduler.cli import make_problem
from gsrmr_scheduler.solve import METHODS, solve

ORDER = ["exact", "apo", "ranking", "rounding", "search", "exchange", "maxrate", "fairness", "robomr", "robogs"]


def timed(problem, method, repeats, **opts):
    times, res = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        res = solve(problem, method, **opts)
        times.append(time.perf_counter() - t0)
    return statistics.median(times), res


def rss_exact_1e5() -> str:
    """Peak RSS of a fresh process solving T = 1e5 (VmHWM: ru_maxrss would include the forked parent)."""
    code = ("import time; from gsrmr_scheduler.solve import solve; "
            "from gsrmr_scheduler.cli import make_problem; p=make_problem(100000, 0); "
            "s=solve(p,'exact'); t=time.perf_counter(); s=solve(p,'exact'); dt=time.perf_counter()-t; "
            "hwm=[ln for ln in open('/proc/self/status') if ln.startswith('VmHWM')][0].split()[1]; "
            "print(f'{int(hwm)/1024:.0f} MB peak RSS (VmHWM, whole process incl. numpy/numba), "
            "{dt:.3f} s (2nd solve), gap {s.optimality_gap}')")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    return (r.stdout or r.stderr).strip()


def table_sizes(quick: bool) -> None:
    print("\n## 1. method x T (L_th = 0.03, seed 0): median solve time, energy, gap to exact")
    print(f"{'T':>7} {'method':>9} {'repeats':>7} {'time_s':>10} {'energy_J':>12} {'gap_vs_exact':>13} {'feasible':>8} "
          f"{'mean_loss':>9}")
    for T in (288, 10_000, 100_000):
        p = make_problem(T, 0, 0.03)
        solve(p, "exact")  # warm (numba cache load)
        ex_t, ex = timed(p, "exact", 21 if T == 288 else 5)
        for m in ORDER:
            if m == "apo":
                if T == 100_000 and quick:
                    print(f"{T:>7} {m:>9}  skipped (--quick)")
                    continue
                reps = 3 if T == 288 else 1
                # Large T: stop after the iteration that crosses 60 s (iterations done are printed).
                t, s = timed(p, m, reps, iterations=10, time_limit_s=600.0 if T == 288 else 60.0)
            elif m == "exact":
                t, s = ex_t, ex
                reps = 21 if T == 288 else 5
            else:
                reps = 5 if T < 100_000 else 1 if quick else 3
                opts = {"energy_budget_j": ex.energy_j} if m in ("maxrate", "fairness") else {}
                if m in ("search", "exchange"):
                    opts["time_limit_s"] = 60.0
                t, s = timed(p, m, reps, **opts)
            gap = s.energy_j / ex.energy_j - 1
            extra = f" (certified gap {s.optimality_gap})" if m == "exact" else ""
            if m in ("apo", "exchange"):
                extra = f" ({s.iterations} iterations)"
            elif m == "search":
                extra = f" ({s.iterations} of {s.extras['proposals']} random moves accepted)"
            print(f"{T:>7} {m:>9} {reps:>7} {t:>10.4f} {s.energy_j:>12.5g} {gap:>13.4%} {s.feasible!s:>8} "
                  f"{s.mean_loss:>9.4f}{extra}")
    print(f"exact, T = 1e5, fresh process: {rss_exact_1e5()}")


def table_apo_n() -> None:
    print("\n## 2. APO iterations N (T = 288, L_th = 0.03, tol = 0, seeds 0-2): median time, gap to exact")
    print(f"{'N':>3} {'time_s':>8} {'gap_mean':>9} {'gap_max':>9} {'phi_last':>9} {'dx_last':>9}")
    probs = [make_problem(288, s, 0.03) for s in range(3)]
    exs = [solve(p, "exact").energy_j for p in probs]
    for N in (1, 2, 5, 10, 20, 30):
        ts, gaps, phis, dxs = [], [], [], []
        for p, e in zip(probs, exs, strict=True):
            t, s = timed(p, "apo", 1, iterations=N, tol=0.0)
            ts.append(t)
            gaps.append(s.energy_j / e - 1)
            phis.append(s.history[-1]["phi"] if s.history else float("nan"))
            dxs.append(s.history[-1]["dx_norm"] if s.history else float("nan"))
        print(f"{N:>3} {statistics.median(ts):>8.3f} {np.mean(gaps):>9.3%} {np.max(gaps):>9.3%} "
              f"{np.mean(phis):>9.2e} {np.mean(dxs):>9.2e}")


def table_thresholds(seeds: int) -> None:
    print(f"\n## 3. energy / exact energy vs L_th (T = 288, mean over {seeds} seeds); [mean loss] for maxrate/fairness "
          "with APO's energy as budget")
    lths = (0.02, 0.025, 0.03, 0.035, 0.04)
    print(f"{'method':>9} " + " ".join(f"{lt:>16}" for lt in lths))
    rows: dict[str, list[str]] = {m: [] for m in ORDER}
    for lt in lths:
        acc: dict[str, list[float]] = {m: [] for m in ORDER}
        loss: dict[str, list[float]] = {m: [] for m in ORDER}
        for seed in range(seeds):
            p = make_problem(288, seed, lt)
            ex = solve(p, "exact")
            apo = solve(p, "apo")
            for m in ORDER:
                s = ex if m == "exact" else apo if m == "apo" else solve(
                    p, m, **({"energy_budget_j": apo.energy_j} if m in ("maxrate", "fairness") else {}))
                acc[m].append(s.energy_j / ex.energy_j)
                loss[m].append(s.mean_loss)
        for m in ORDER:
            cell = f"{np.mean(acc[m]):.4f}"
            if m in ("maxrate", "fairness", "robogs"):
                cell += f" [{np.mean(loss[m]):.3f}]"
            rows[m].append(cell)
    for m in ORDER:
        print(f"{m:>9} " + " ".join(f"{c:>16}" for c in rows[m]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--full", action="store_true", help="APO at T = 1e5, 3 repeats at 1e5, 10 seeds in table 3")
    ap.add_argument("--quick", action="store_true", help="the default run (kept for old command lines)")
    args = ap.parse_args()
    quick = not args.full
    assert set(ORDER) == set(METHODS)
    print(f"# bench/perf/scheduler.py{'' if quick else ' --full'}  python {sys.version.split()[0]}, "
          f"numpy {np.__version__}")
    table_sizes(quick)
    table_apo_n()
    table_thresholds(3 if quick else 10)


if __name__ == "__main__":
    main()
