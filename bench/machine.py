"""The machine a bench ran on: CPUs, load average and a CPU speed probe, printed in every table's header.

Cloud machines of one nominal size differ in speed from day to day (on 2026-11-25 the 2-core machine ran the
renderer 3.2× slower than on 2026-11-24), so a table says how fast its machine was: ``cpu_probe_s`` times a
pure-Python loop of 10⁷ additions (one core; ≈ 0.5 s on a current x86 core, 1.65 s on that slow day).
"""

from __future__ import annotations

import os
import time


def cpu_probe_s(repeats: int = 3) -> float:
    """Best of ``repeats`` timings [s] of ``for i in range(10**7): s += i`` (one core, CPython)."""
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        s = 0
        for i in range(10_000_000):
            s += i
        best = min(best, time.perf_counter() - t0)
    return best


def machine_line() -> str:
    """``2 CPUs, load average 0.7, CPU probe 1.65 s`` (see the module docstring)."""
    return f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}, CPU probe {cpu_probe_s():.2f} s"
