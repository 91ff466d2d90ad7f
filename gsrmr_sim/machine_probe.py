"""The machine a bench ran on, printed in a bench table's header: CPUs, load average and two speed probes, since a
cloud machine's speed varies from day to day (no ROS). What the probes time and their usual values: docs/results.md,
"The machine"."""

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
    the first camera of the garden data (after one warm-up call): the server's per-slot work, which the CPU probe
    alone does not track."""
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
