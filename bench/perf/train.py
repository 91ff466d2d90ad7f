"""Training benchmark: iterations/s and held-out PSNR against CPU minutes of the two training engines (``fused``, the
default, and ``torch``, the autograd reference; ``TrainConfig.engine``), at two widths, with 1 and 2 numba threads,
on two datasets; and (``--profile``) where one step's time goes in each engine.

**Datasets** (every run of one dataset trains on the same frames):

* ``garden`` — 48 views of the garden test model rendered by the engine at the run's width (160×120, 270×202) on a
  circle around the scene (radius 1.1 m, heights 0.35/0.6 m, looking at (0, 0, 0.1), 68° horizontal field of view,
  with depth); every 6th view (8) is held out, 40 train. TrainConfig's defaults (SH degree 0 here, budget 200k,
  30k initial Gaussians from the depth) with the schedule scaled to ``--iterations`` (densification to 2/3).
* ``sandbox`` — the sandbox's mapping round as the live model trains on it: ``gsrmr_sim.world.recorder.record_round1``
  (144 frames at the scene camera's 320×240 with depth, true poses), every 8th frame held out
  (``holdout_split``); the live recipe's config (``gsrmr_sim.models.live_recipe``: SH degree 0, at most 100k
  Gaussians, the scene's background, no opacity reset) at ``--iterations`` steps of schedule, trained at the run's
  width (``TrainConfig.resolution``).

**Rows**: dataset × width (``--widths``) × numba threads (``--threads``) × engine (``--engines``), and the sandbox with
pose refinement on (``pose_opt``, at ``--pose-opt-threads``) for both engines. torch runs on 1 thread in every row
(``TrainConfig.torch_threads``); the fused engine's adaptive thread count is off (``adaptive_threads``): every step
uses the row's count. The engines of one configuration run one after the other (alternating which goes
first from run to run), so that both see the same machine load; the load average is printed before each pair.

**Each run** trains (seed = run index, ``final_prune`` off) until the last of ``--stages-min`` CPU-minutes of
training (process CPU time of the steps, all threads: what ``Trainer.train(cpu_budget_s=…)`` counts) and measures
the held-out PSNR (``Trainer.evaluate``, the display renderer at the recorded poses) at each stage. The steps are
timed in windows of ``--window`` steps (wall time): the table gives the median and the worst (slowest) window's
it/s, and the speed-up compares the windows both engines ran (the same iterations of the same schedule: window k
of fused against window k of torch), median and worst of those ratios.

``--profile``: for each dataset and width, a state after ``--profile-at`` fused steps of the run's schedule (its
density control then frozen), ``--profile-steps`` steps of each engine from it, the median ms per step of each
phase (fused: the engine's own timers; torch: timers wrapped around its functions) at each thread count.

Usage: .venv/bin/python bench/perf/train.py [--datasets garden sandbox] [--widths 160 270] [--threads 1 2]
    [--stages-min 0.5 1] [--runs 1] [--profile] [--json OUT]

The default run (what ``make bench`` runs; 112–127 s on the 2 shared cores, load 3–4) is one row: the garden at
160 px on 2 numba threads, both engines, stages 0.5 and 1 CPU-minute. The whole grid, ``--datasets garden sandbox
--widths 160 270 --threads 1 2 --stages-min 1 3`` (the defaults before 2026-11-29), is 10 rows of 2 engines × 3
CPU-minutes, about an hour (not run here; docs/splatting.md's ≈ 25 min is that grid at stages 0.5 and 1, with the
profile).

``--quick``: tiny frames and budgets; checks the script, measures nothing.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, replace
import json
import math
import os
from pathlib import Path
import statistics
import sys
import tempfile
import time

import numba
import torch

from gsrmr_common.camera import Intrinsics
from gsrmr_common.nerfstudio import DatasetFrame, holdout_split, read_dataset
from gsrmr_sim.machine_probe import machine_line
from gsrmr_sim.shared_data import garden_model
from gsrmr_splat import diffrender
from gsrmr_splat import train as train_module
from gsrmr_splat.datasets import orbit_cameras, render_views
from gsrmr_splat.train import Trainer
from gsrmr_splat.train_config import ENGINES, TrainConfig

GARDEN_FOV_DEG = 68.0
GARDEN_VIEWS = 48
GARDEN_HOLDOUT = 6
SANDBOX_HOLDOUT = 8


@dataclass(frozen=True)
class Row:
    """One configuration of the table (both engines run it)."""

    dataset: str
    width: int
    threads: int
    pose_opt: bool = False


def garden_frames(width: int, views: int = GARDEN_VIEWS) -> tuple[list[DatasetFrame], list[DatasetFrame]]:
    """The garden views rendered at ``width`` × ¾·``width`` (train, held out)."""
    height = (3 * width) // 4
    frames = render_views(garden_model(), orbit_cameras(views, Intrinsics.from_fov(width, height,
                                                                                    math.radians(GARDEN_FOV_DEG))))
    return ([f for i, f in enumerate(frames) if i % GARDEN_HOLDOUT != GARDEN_HOLDOUT - 1],
            frames[GARDEN_HOLDOUT - 1::GARDEN_HOLDOUT])


def sandbox_frames(folder: Path, frames: int | None, size: tuple[int, int] | None = None
                   ) -> tuple[list[DatasetFrame], list[DatasetFrame]]:
    """The sandbox's mapping round, recorded under ``folder`` (train, held out)."""
    from gsrmr_sim.world.recorder import record_round1, with_resolution
    from gsrmr_sim.world.scene import load_scene

    scene = load_scene("sandbox")
    if size is not None:
        scene = with_resolution(scene, *size)
    path = record_round1(scene, folder / "round1", frames=frames or scene.frames, seed=0)
    return holdout_split(read_dataset(path), SANDBOX_HOLDOUT)


def config(dataset: str, width: int, iterations: int, seed: int, engine: str, pose_opt: bool,
           quick: bool) -> TrainConfig:
    """The run's TrainConfig (see the module docstring)."""
    if dataset == "sandbox":
        from gsrmr_sim.models import live_recipe

        cfg = live_recipe("sandbox", iterations=iterations, width=width).config
    else:
        cfg = TrainConfig(iterations=iterations, sh_degree=0, densify_until=(2 * iterations) // 3,
                          opacity_reset_interval=max(3000, iterations + 1))
    cfg = replace(cfg, seed=seed, final_prune=False, engine=engine, pose_opt=pose_opt, adaptive_threads=False)
    if quick:
        cfg = replace(cfg, init_points=1500, budget=6000, densify_from=20, densify_interval=20)
    return cfg


def run(train: list[DatasetFrame], held: list[DatasetFrame], cfg: TrainConfig, stages_s: list[float],
        window: int) -> dict:
    """Train to each CPU stage; window timings, held-out PSNR per stage, iterations and times."""
    trainer = Trainer(train, cfg, held)
    psnr_db, windows = [], []
    cpu_used = wall_used = 0.0
    w_t0, w_n = time.perf_counter(), 0
    for budget in stages_s:
        while cpu_used < budget:
            c0, t0 = time.process_time(), time.perf_counter()
            trainer.step()
            cpu_used += time.process_time() - c0
            wall_used += time.perf_counter() - t0
            w_n += 1
            if w_n == window:
                now = time.perf_counter()
                windows.append(window / (now - w_t0))
                w_t0, w_n = now, 0
        t_eval = time.perf_counter()
        psnr_db.append(trainer.evaluate())
        w_t0 += time.perf_counter() - t_eval  # evaluation is not a step
    return {"iterations": trainer.state.step, "cpu_s": cpu_used, "wall_s": wall_used, "psnr_db": psnr_db,
            "window_it_per_s": windows, "gaussians": trainer.num_gaussians,
            "corrections": trainer.corrections_summary()}


def fmt(values: list[float], digits: int = 1, worst=min) -> str:
    """Median, and the worst in brackets when there are several."""
    vals = [v for v in values if v == v]
    if not vals:
        return "–"
    med = f"{statistics.median(vals):.{digits}f}"
    return med if len(vals) == 1 else f"{med} ({worst(vals):.{digits}f})"


def speedups(torch_runs: list[dict], fused_runs: list[dict]) -> list[float]:
    """Window-by-window it/s ratios fused / torch over the windows both runs of a seed ran."""
    out = []
    for t, f in zip(torch_runs, fused_runs, strict=True):
        k = min(len(t["window_it_per_s"]), len(f["window_it_per_s"]))
        out += [f["window_it_per_s"][i] / t["window_it_per_s"][i] for i in range(k)]
    return out


# ---------------------------------------------------------------------------------------------- profile
class TorchTimers:
    """Wall time of the torch engine's pieces, by wrapping the functions its step calls (restored on exit)."""

    def __init__(self) -> None:
        self.t: dict[str, float] = {}
        self._saved: list[tuple[object, str, object]] = []

    def _wrap(self, owner, name: str, label: str, static: bool = False) -> None:
        fn = getattr(owner, name)
        inner = fn.__func__ if isinstance(fn, staticmethod) else fn

        def timed(*a, **kw):
            t0 = time.perf_counter()
            try:
                return inner(*a, **kw)
            finally:
                self.t[label] = self.t.get(label, 0.0) + time.perf_counter() - t0

        self._saved.append((owner, name, owner.__dict__[name] if static else fn))
        setattr(owner, name, staticmethod(timed) if static else timed)

    def __enter__(self) -> TorchTimers:
        self._wrap(train_module, "render_torch", "render_torch")
        self._wrap(diffrender, "project_numpy", "project (numba cull)")
        self._wrap(diffrender, "depth_order", "sort")
        self._wrap(diffrender, "rasterize_packed", "raster forward")
        self._wrap(diffrender.RasterizeFunction, "backward", "raster backward", static=True)
        self._wrap(train_module, "train_loss", "loss forward")
        self._wrap(torch.Tensor, "backward", "autograd backward")
        self._wrap(train_module, "adam_step", "adam")
        return self

    def __exit__(self, *exc) -> None:
        for owner, name, fn in reversed(self._saved):
            setattr(owner, name, fn)

    def phases(self) -> dict[str, float]:
        """Exclusive phases: projection + SH in torch = render_torch − its numba parts; backward = autograd −
        the rasterizer's backward (i.e. SSIM, projection and SH backward and the graph)."""
        t = dict(self.t)
        render_t = t.pop("render_torch", 0.0)
        backward_t = t.pop("autograd backward", 0.0)
        out = {k: t.get(k, 0.0) for k in ("project (numba cull)", "sort", "raster forward")}
        out["projection + SH (torch)"] = render_t - sum(out.values())
        out["loss forward"] = t.get("loss forward", 0.0)
        out["raster backward"] = t.get("raster backward", 0.0)
        out["autograd backward (SSIM, projection, SH)"] = backward_t - out["raster backward"]
        out["adam"] = t.get("adam", 0.0)
        return out


def profile(train, held, cfg_for, at: int, steps: int, threads: list[int]) -> None:
    """Per-phase median ms per step of both engines from one state (module docstring)."""
    with tempfile.TemporaryDirectory(prefix="gsrmr-train-bench-") as tmp:
        numba.set_num_threads(max(threads))
        warm = Trainer(train, cfg_for("fused"), held)
        for _ in range(at):
            warm.step()
        ck = warm.save_checkpoint(Path(tmp) / "state.ckpt")
        for n in threads:
            numba.set_num_threads(n)
            trainers = {}
            for engine in ("torch", "fused"):
                tr = Trainer(train, replace(cfg_for(engine), densify_until=0), held)
                tr.load_checkpoint(ck)
                tr.step()  # compiled and warm
                trainers[engine] = tr
            per = {"torch": [], "fused": []}
            totals = {"torch": [], "fused": []}
            load = os.getloadavg()[0]
            for _ in range(steps):
                for engine, tr in trainers.items():
                    if engine == "fused":
                        tr._fused.timings = {}
                        t0 = time.perf_counter()
                        tr.step()
                        totals[engine].append(time.perf_counter() - t0)
                        per[engine].append(dict(tr._fused.timings))
                    else:
                        with TorchTimers() as timers:
                            t0 = time.perf_counter()
                            tr.step()
                            totals[engine].append(time.perf_counter() - t0)
                        per[engine].append(timers.phases())
            print(f"\n## profile: {warm.num_gaussians} Gaussians after {at} fused steps, {n} numba thread(s), load "
                  f"{load:.1f} → {os.getloadavg()[0]:.1f}; median ms per step over {steps} steps of each engine "
                  f"(alternating)\n")
            print("| engine | phase | ms |\n|---|---|---|")
            for engine in ("torch", "fused"):
                rows = per[engine]
                med = {k: 1e3 * statistics.median(r.get(k, 0.0) for r in rows) for k in rows[0]}
                total = 1e3 * statistics.median(totals[engine])
                for k, v in med.items():
                    print(f"| {engine} | {k} | {v:.2f} |")
                print(f"| {engine} | rest (density statistics, Python) | {max(total - sum(med.values()), 0.0):.2f} |")
                print(f"| {engine} | **step** | **{total:.2f}** |")


# ---------------------------------------------------------------------------------------------- main
def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--datasets", nargs="+", choices=["garden", "sandbox"], default=["garden"])
    ap.add_argument("--widths", type=int, nargs="+", default=[160])
    ap.add_argument("--threads", type=int, nargs="+", default=[2])
    ap.add_argument("--engines", nargs="+", choices=ENGINES, default=list(ENGINES))
    ap.add_argument("--pose-opt-threads", type=int, nargs="*", default=[2],
                    help="thread counts of the sandbox rows with pose refinement on (none: no such rows)")
    ap.add_argument("--stages-min", type=float, nargs="+", default=[0.5, 1.0],
                    help="CPU-minutes of training at which the held-out PSNR is measured (the last ends a run)")
    ap.add_argument("--iterations", type=int, default=4000, help="steps of the schedule (a run may stop earlier)")
    ap.add_argument("--window", type=int, default=100, help="steps per timing window")
    ap.add_argument("--runs", type=int, default=1, help="seeds per row and engine")
    ap.add_argument("--profile", action="store_true", help="also the per-phase profile (module docstring)")
    ap.add_argument("--profile-at", type=int, default=2000)
    ap.add_argument("--profile-steps", type=int, default=40)
    ap.add_argument("--no-table", action="store_true", help="the profile only")
    ap.add_argument("--json", default=None, help="write every run's figures here")
    ap.add_argument("--quick", action="store_true", help="a tiny smoke run of the script (measures nothing)")
    args = ap.parse_args()
    stages_s = [60.0 * m for m in args.stages_min]
    widths, frames_n, sandbox_size, garden_views = args.widths, None, None, GARDEN_VIEWS
    if args.quick:
        widths, frames_n, sandbox_size, garden_views = [48], 16, (96, 72), 12
        stages_s, args.window, args.iterations = [1.0, 2.0], 10, 200
        args.profile_at, args.profile_steps = 30, 3
    max_threads = numba.config.NUMBA_NUM_THREADS
    threads = [t for t in args.threads if t <= max_threads]
    print(f"# bench/perf/train.py{' --quick' if args.quick else ''} (before: {machine_line()} "
          f"(gsrmr_sim.machine_probe)); numba threads {threads} of {max_threads}, torch 1 thread; commit {commit()}")
    print(f"# stages {[s / 60 for s in stages_s]} CPU-min, schedule {args.iterations} steps, windows of {args.window} "
          f"steps, {args.runs} run(s) per row and engine")
    rows = [Row(d, w, n) for d in args.datasets for w in widths for n in threads]
    rows += [Row("sandbox", w, n, True) for w in widths for n in args.pose_opt_threads if "sandbox" in args.datasets
             and n <= max_threads]
    everything: list[dict] = []
    table: list[str] = []
    t_start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="gsrmr-train-bench-") as tmp:
        data: dict[tuple[str, int], tuple[list, list]] = {}

        def dataset(name: str, width: int):
            key = (name, width if name == "garden" else 0)
            if key not in data:
                data[key] = garden_frames(width, garden_views) if name == "garden" else \
                    sandbox_frames(Path(tmp), frames_n, sandbox_size)
            return data[key]

        if args.profile:
            for name in args.datasets:
                for w in widths:
                    train, held = dataset(name, w)
                    print(f"\n# profile: {name} at {w} px ({len(train)} training views)")
                    profile(train, held, lambda e, n=name, w=w: config(n, w, args.iterations, 0, e, False, args.quick),
                            args.profile_at, args.profile_steps, threads)
        if args.no_table:
            return 0
        for row in rows:
            train, held = dataset(row.dataset, row.width)
            numba.set_num_threads(row.threads)
            results: dict[str, list[dict]] = {e: [] for e in args.engines}
            loads = []
            for r in range(args.runs):
                order = list(args.engines) if r % 2 == 0 else list(reversed(args.engines))
                loads.append(os.getloadavg()[0])
                for engine in order:
                    cfg = config(row.dataset, row.width, args.iterations, r, engine, row.pose_opt, args.quick)
                    res = run(train, held, cfg, stages_s, args.window)
                    res.update({"row": row.__dict__, "engine": engine, "seed": r, "load_before": loads[-1]})
                    results[engine].append(res)
                    everything.append(res)
            for engine in args.engines:
                rs = results[engine]
                wins = [w for x in rs for w in x["window_it_per_s"]]
                stages = " | ".join(fmt([x["psnr_db"][i] for x in rs], 2) for i in range(len(stages_s)))
                ratio = "–"
                if engine == "fused" and "torch" in results:
                    ratio = fmt(speedups(results["torch"], rs), 2)
                table.append(f"| {row.dataset} | {row.width} | {row.threads} | {'on' if row.pose_opt else 'off'} | "
                             f"{engine} | {fmt(wins)} | {fmt([x['iterations'] for x in rs], 0)} | "
                             f"{fmt([x['gaussians'] for x in rs], 0)} | {stages} | {ratio} | "
                             f"{statistics.median(loads):.1f} |")
            print(table[-1] if len(args.engines) == 1 else "\n".join(table[-len(args.engines):]), flush=True)
    stage_cols = " | ".join(f"held-out PSNR dB @ {s / 60:g} CPU-min" for s in stages_s)
    print(f"\n| dataset | width px | numba threads | pose-opt | engine | it/s median (worst window) | iterations | "
          f"Gaussians | {stage_cols} | speed-up fused/torch, windows: median (worst) | load avg |")
    print("|" + "---|" * (10 + len(stages_s)))
    print("\n".join(table))
    print(f"\n# after: load average {os.getloadavg()[0]:.1f}; {time.perf_counter() - t_start:.0f} s wall in all")
    if args.json:
        Path(args.json).write_text(json.dumps({"runs": everything, "stages_s": stages_s}, indent=1))
    return 0


def commit() -> str:
    """The repository's HEAD (short), '+dirty' when the work tree differs."""
    import subprocess

    root = Path(__file__).resolve().parents[2]
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "gsrmr_splat", "bench/perf/train.py"],
                               cwd=root, capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("+dirty" if dirty else "")


if __name__ == "__main__":
    sys.exit(main())
