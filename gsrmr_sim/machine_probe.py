"""The machine a bench ran on: CPUs, load average and two speed probes, printed in a bench table's header.

``from gsrmr_sim.machine_probe import machine_line`` in every bench that prints it (``bench/perf/``,
``bench/acceptance/``); no ROS.

Cloud machines of one nominal size differ in speed from day to day (on 2026-11-25 the 2-core machine ran the
renderer 2.5–3.2× slower than on 2026-11-24), so a table says how fast its machine was:

* ``cpu_probe_s`` times a pure-Python loop of 10⁷ additions (one core; 0.35 s on a good hour of that day, 1.65 s on
  a bad one);
* ``render_probe_ms`` times one 320×240 render of the garden test model on one thread (the server's per-slot work;
  the Python probe alone missed a slow renderer on a day its loop was fast).
"""

from __future__ import annotations

import os
import time

import numpy as np

from gsrmr_common.camera import Camera
from gsrmr_sim.shared_data import garden_model, load_garden
from gsrmr_splat.render import render


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


def render_probe_ms(repeats: int = 7) -> float:
    """Median wall time [ms] of ``render()`` of the garden test model (111,785 Gaussians) at 320×240 on one thread,
    the first camera of the garden data (after one warm-up call)."""
    cam = load_garden()[2][0]
    camera = Camera(cam.intrinsics.scaled(320, 240), cam.world_to_camera)
    model = garden_model()
    render(model, camera, threads=1)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        render(model, camera, threads=1)
        times.append(1e3 * (time.perf_counter() - t0))
    return float(np.median(times))


def machine_line(render_probe: bool = True) -> str:
    """``2 CPUs, load average 0.7, CPU probe 0.35 s, render probe 60 ms`` (see the module docstring)."""
    line = f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}, CPU probe {cpu_probe_s():.2f} s"
    return line + (f", render probe {render_probe_ms():.0f} ms" if render_probe else "")
