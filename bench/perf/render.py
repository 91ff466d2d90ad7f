"""Renderer benchmark: frames/s of ``render()`` on the garden test model (not a test; prints tables).

Tables: fps against resolution (the 3 real garden cameras' field of view, scaled), against Gaussian
count (random subsets of the garden model, fixed seed) and against SH degree (coefficients above
degree 0 drawn at random so the SH path really runs). Each figure is the median over ``--repeats``
renders per camera, over the 3 cameras. Also reports the numba first-call time with a cold cache
(compile) and a warm cache (load), each in a fresh subprocess.

Also the stage split of one frame (projection, sort, gather, binning, compositing), 1 and 2 threads.

Usage: .venv/bin/python bench/perf/render.py [--repeats 7] [--threads N]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

import numba
import numpy as np

from gsrmr_common.camera import Camera
from gsrmr_sim.shared_data import garden_model, load_garden
from gsrmr_splat.display_raster import TILE, display_kernel
from gsrmr_splat.model import GaussianModel
from gsrmr_splat.project import NEAR_M, project_numpy
from gsrmr_splat.rasterize import PACK_WIDTH, bin_kernel, depth_order, gather_pack_kernel
from gsrmr_splat.render import render

FIRST_CALL = ("import time; t0 = time.perf_counter();"
              "from gsrmr_sim.shared_data import garden_model, load_garden;"
              "from gsrmr_splat.render import render;"
              "m = garden_model(); cam = load_garden()[2][0]; t1 = time.perf_counter(); render(m, cam);"
              "t2 = time.perf_counter(); render(m, cam); t3 = time.perf_counter();"
              "print(f'{t1 - t0:.2f} {t2 - t1:.2f} {t3 - t2:.3f}')")


CPU_MS: list[float] = []  # process CPU ms per render of the last time_renders call (all threads)


def time_renders(model: GaussianModel, cams: list[Camera], repeats: int) -> tuple[float, int]:
    """(median wall seconds per render over all cameras × repeats, mean visible Gaussians)."""
    times, vis = [], []
    CPU_MS.clear()
    for cam in cams:
        render(model, cam)  # warm-up (JIT already compiled; caches, page faults)
        for _ in range(repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            out = render(model, cam)
            times.append(time.perf_counter() - t0)
            CPU_MS.append(1000 * (time.process_time() - c0))
        vis.append(out.num_visible)
    return float(np.median(times)), int(np.mean(vis))


def scaled(cams: list[Camera], width: int, height: int) -> list[Camera]:
    return [Camera(c.intrinsics.scaled(width, height), c.world_to_camera) for c in cams]


def with_random_sh(model: GaussianModel, degree: int, seed: int = 0) -> GaussianModel:
    m = model.with_degree(degree)
    rng = np.random.default_rng(seed)
    m.sh[:, 1:] = rng.normal(0.0, 0.1, m.sh[:, 1:].shape).astype(np.float32)
    return m


def stage_split_ms(model: GaussianModel, cams: list[Camera], repeats: int) -> dict[str, float]:
    """Median wall ms of each stage of render() (SH degree 0), over cameras × repeats."""
    stages: dict[str, list[float]] = {}
    sh0 = np.ascontiguousarray(model.sh[:, 0, :])
    for cam in cams:
        k, w, h = cam.intrinsics, cam.width, cam.height
        for rep in range(repeats + 1):
            t = [time.perf_counter()]
            geom, box = project_numpy(model.means, model.quats, model.log_scales, model.opacity_logits,
                                      cam.world_to_camera, (k.fx, k.fy, k.cx, k.cy), w, h, NEAR_M)
            t.append(time.perf_counter())
            visible = np.nonzero((box[:, 0] <= box[:, 1]) & (box[:, 2] <= box[:, 3]))[0]
            order = visible[depth_order(geom[visible, 6])]
            t.append(time.perf_counter())
            packed = np.empty((order.shape[0], PACK_WIDTH), np.float32)
            pbox = np.empty((order.shape[0], 4), np.int64)
            gather_pack_kernel(geom, box, order, np.zeros((0, 3)), sh0, packed, pbox)
            t.append(time.perf_counter())
            tiles_x, tiles_y = (w + TILE - 1) // TILE, (h + TILE - 1) // TILE
            offsets, lst = bin_kernel(pbox, TILE, tiles_x, tiles_y)
            t.append(time.perf_counter())
            rgb, alpha, depth = (np.empty((h, w, 3), np.float32), np.empty((h, w), np.float32),
                                 np.empty((h, w), np.float32))
            display_kernel(packed, pbox, offsets, lst, w, h, tiles_x, np.zeros(3, np.float32), rgb, alpha, depth)
            t.append(time.perf_counter())
            if rep:  # the first is a warm-up
                for name, a, b in zip(("projection", "sort", "gather", "binning", "compositing"), t[:-1], t[1:],
                                      strict=True):
                    stages.setdefault(name, []).append(1000 * (b - a))
    return {name: float(np.median(v)) for name, v in stages.items()}


def first_call_times() -> list[str]:
    rows = []
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        for label in ("cold cache (compile)", "warm cache (load)"):
            out = subprocess.run([sys.executable, "-c", FIRST_CALL], env=env, capture_output=True, text=True,
                                 check=True).stdout.split()
            rows.append(f"| {label} | {out[0]} | {out[1]} | {float(out[2]) * 1000:.0f} |")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--threads", type=int, default=None, help="numba threads (default: all cores)")
    ap.add_argument("--skip-compile", action="store_true")
    args = ap.parse_args()
    if args.threads:
        numba.set_num_threads(args.threads)
    model = garden_model()
    _, _, cams = load_garden()
    print(f"# load average before the run: {os.getloadavg()[0]:.1f} (other processes share the 2 cores)")
    print(f"# render() benchmark: garden model, {model.num_gaussians} Gaussians (SH 0), "
          f"{numba.get_num_threads()} numba threads, {os.cpu_count()} CPUs, median of {args.repeats} × 3 cameras\n")
    print("## fps vs resolution (all Gaussians)\n")
    print("| resolution | wall ms/frame | fps | CPU ms/frame (all threads) | visible Gaussians |")
    print("|---|---|---|---|---|")
    for w, h in [(160, 120), (320, 240), (648, 420), (1296, 840)]:
        t, vis = time_renders(model, scaled(cams, w, h), args.repeats)
        print(f"| {w}×{h} | {t * 1000:.1f} | {1 / t:.1f} | {np.median(CPU_MS):.1f} | {vis} |", flush=True)
    print("\n## fps vs Gaussian count (random subsets, seed 0)\n")
    print("| Gaussians | 320×240 wall ms | fps | CPU ms | 648×420 wall ms | fps | CPU ms |")
    print("|---|---|---|---|---|---|---|")
    rng = np.random.default_rng(0)
    for frac in (0.1, 0.25, 0.5, 1.0):
        sub = model if frac == 1.0 else model.subset(np.sort(rng.choice(len(model), int(frac * len(model)),
                                                                        replace=False)))
        t1, _ = time_renders(sub, scaled(cams, 320, 240), args.repeats)
        c1 = float(np.median(CPU_MS))
        t2, _ = time_renders(sub, cams, args.repeats)
        print(f"| {len(sub)} | {t1 * 1000:.1f} | {1 / t1:.1f} | {c1:.1f} | {t2 * 1000:.1f} | {1 / t2:.1f} | "
              f"{np.median(CPU_MS):.1f} |", flush=True)
    print("\n## fps vs SH degree (all Gaussians)\n")
    print("| SH degree | 320×240 wall ms | fps | CPU ms | 648×420 wall ms | fps | CPU ms |")
    print("|---|---|---|---|---|---|---|")
    for degree in range(4):
        m = with_random_sh(model, degree) if degree else model
        t1, _ = time_renders(m, scaled(cams, 320, 240), args.repeats)
        c1 = float(np.median(CPU_MS))
        t2, _ = time_renders(m, cams, args.repeats)
        print(f"| {degree} | {t1 * 1000:.1f} | {1 / t1:.1f} | {c1:.1f} | {t2 * 1000:.1f} | {1 / t2:.1f} | "
              f"{np.median(CPU_MS):.1f} |", flush=True)
    print("\n## numba threads (all Gaussians; render(..., threads=N))\n")
    print("| threads | 320×240 wall ms | CPU ms | 648×420 wall ms | CPU ms |\n|---|---|---|---|---|")
    for threads in (1, 2):
        numba.set_num_threads(threads)
        t1, _ = time_renders(model, scaled(cams, 320, 240), args.repeats)
        c1 = float(np.median(CPU_MS))
        t2, _ = time_renders(model, cams, args.repeats)
        print(f"| {threads} | {t1 * 1000:.1f} | {c1:.1f} | {t2 * 1000:.1f} | {np.median(CPU_MS):.1f} |", flush=True)
    print("\n## stage split (wall ms, median; SH 0, all Gaussians)\n")
    names = ("projection", "sort", "gather", "binning", "compositing")
    print("| threads | resolution | " + " | ".join(names) + " |\n|---|---|" + "---|" * len(names))
    for threads in (1, 2):
        numba.set_num_threads(threads)
        for w, h in [(320, 240), (648, 420)]:
            split = stage_split_ms(model, scaled(cams, w, h), args.repeats)
            print(f"| {threads} | {w}×{h} | " + " | ".join(f"{split[n]:.1f}" for n in names) + " |", flush=True)
    print(f"\n# load average after the run: {os.getloadavg()[0]:.1f}")
    if not args.skip_compile:
        print("\n## first call in a fresh process (648×420)\n")
        print("| numba cache | import + model build s | first render s | second render ms |\n|---|---|---|---|")
        for row in first_call_times():
            print(row, flush=True)


if __name__ == "__main__":
    main()
