"""Compaction benchmark: Gaussians vs held-out PSNR vs render speed vs CPU time, for each compaction round.

Scenes:

* ``sandbox`` — the demo's model: the sandbox's round-1 dataset (144 frames at 320×240) trained as
  ``make demo`` trains it (``gsrmr_sim.models``, SH 0, 160 px wide, 75 s, every 8th frame held out),
  taken from the demo's cache when it is there;
* ``garden`` — the dataset ``bench/perf/train.py`` builds from the garden test model (48 views at 160×120,
  every 6th held out), trained for ``--garden-cpu-s`` of CPU time with SH degree 1.

Every accepted or rejected compaction round is a row: its Gaussians and SH degree, held-out PSNR (at
the dataset's training resolution), the render time at 320×240 and 648×420 with 1 and 2 numba threads
(median of ``--repeats`` renders of 3 held-out views), and the process CPU seconds spent so far
(training, then each step's fine-tuning and evaluation; the contribution ranking is in the total only).
The knee marked is the smallest model within the tolerance (the last accepted round). A plot goes to
``--plot`` (PNG), the rows to ``--json``.

Usage: .venv/bin/python bench/perf/compact.py [--scenes sandbox garden] [--max-psnr-drop-db 0.3]

The default run (what ``make bench`` runs) is the sandbox alone: 71 s on the 2 cores idle, 161 s at load 3–4, with
the demo's model cached (without it the model is trained first, as ``make demo`` does). Both scenes, ``--scenes sandbox
garden`` (the default before 2026-11-29; docs/splatting.md's tables), add the garden's 300 CPU-seconds of training and
its compaction: 618 s in all (load 0.4–7 from other jobs).
"""

from __future__ import annotations

import argparse
import json
import math
import os
from pathlib import Path
import time

import numba
import numpy as np

from gsrmr_common.camera import Camera, Intrinsics
from gsrmr_common.nerfstudio import holdout_split
from gsrmr_splat.compact import CompactConfig, Compactor
from gsrmr_splat.model import GaussianModel
from gsrmr_splat.render import render
from gsrmr_splat.train import TrainConfig, Trainer

REPO = Path(__file__).resolve().parents[2]
SIZES = ((320, 240), (648, 420))


def render_ms(model: GaussianModel, cams: list[Camera], threads: int, repeats: int,
              background: tuple[float, float, float]) -> float:
    """Median wall ms of one render (after a warm-up render) at ``threads`` numba threads."""
    numba.set_num_threads(threads)
    render(model, cams[0], background)
    times = []
    for _ in range(repeats):
        for cam in cams:
            t0 = time.perf_counter()
            render(model, cam, background)
            times.append(time.perf_counter() - t0)
    numba.set_num_threads(os.cpu_count() or 1)
    return 1e3 * float(np.median(times))


def scaled(cams: list[Camera], width: int, height: int) -> list[Camera]:
    """The same poses at another image size (same horizontal field of view)."""
    out = []
    for cam in cams:
        hfov = 2 * math.atan(0.5 * cam.intrinsics.width / cam.intrinsics.fx)
        out.append(Camera(Intrinsics.from_fov(width, height, hfov), cam.world_to_camera))
    return out


def sandbox_inputs(args: argparse.Namespace) -> tuple[GaussianModel, list, list, TrainConfig, float]:
    """The demo's model and its dataset split (built like ``make demo``, cached in the demo's cache)."""
    from gsrmr_common.nerfstudio import read_dataset
    from gsrmr_sim.models import live_model, live_recipe

    t0 = time.process_time()
    built = live_model(live_recipe("sandbox"), REPO / ".cache" / "gsrmr", max_psnr_drop_db=None)
    cpu = float(built.info.get("cpu_s") or (time.process_time() - t0))
    train, test = holdout_split(read_dataset(built.folder / "round1"), 8)
    cfg = TrainConfig(resolution=160, sh_degree=built.model.sh_degree)
    return built.model, train, test, cfg, cpu


def garden_inputs(args: argparse.Namespace) -> tuple[GaussianModel, list, list, TrainConfig, float]:
    """bench/perf/train.py's garden dataset, trained here with SH degree 1 for ``--garden-cpu-s``."""
    from gsrmr_sim.shared_data import garden_model
    from gsrmr_splat.datasets import orbit_cameras, render_views

    frames = render_views(garden_model(), orbit_cameras(48, Intrinsics.from_fov(160, 120, math.radians(68.0))),
                          with_depth=True)
    test = frames[5::6]
    train = [f for i, f in enumerate(frames) if i % 6 != 5]
    cfg = TrainConfig(iterations=6000, sh_degree=1, init_points=30_000, densify_until=4000, checkpoint_every=0)
    t0 = time.process_time()
    model = Trainer(train, cfg, test).train(progress=False, cpu_budget_s=args.garden_cpu_s)
    return model, train, test, cfg, time.process_time() - t0


def plot(results: dict, path: str) -> None:
    """Held-out PSNR (kept rounds joined, rejected ones as crosses) and 1-thread 320×240 fps vs Gaussians."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(results), figsize=(6 * len(results), 4), squeeze=False)
    for ax, (name, res) in zip(axes[0], results.items(), strict=True):
        rows = res["rows"]
        kept = sorted((r for r in rows if r["accepted"]), key=lambda r: r["gaussians"])
        rejected = [r for r in rows if not r["accepted"]]
        ax.plot([r["gaussians"] for r in kept], [r["heldout_psnr_db"] for r in kept], "o-",
                label="held-out PSNR (kept)")
        ax.plot([r["gaussians"] for r in rejected], [r["heldout_psnr_db"] for r in rejected], "x", color="C3",
                label="over the tolerance (rejected)")
        k = rows[res["knee"]]
        ax.plot([k["gaussians"]], [k["heldout_psnr_db"]], "r*", ms=14, label="knee (smallest within tolerance)")
        ax.set_xlabel("Gaussians")
        ax.set_ylabel("held-out PSNR [dB]")
        ax.set_title(f"{name}: trained {rows[0]['gaussians']} → {k['gaussians']} Gaussians")
        ax2 = ax.twinx()
        ax2.plot([r["gaussians"] for r in kept], [1e3 / r["ms_320x240_t1"] for r in kept], "s--", color="grey",
                 label="fps 320×240, 1 thread")
        ax2.set_ylabel("render fps (320×240, 1 thread)")
        ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=["sandbox"], choices=["sandbox", "garden"])
    ap.add_argument("--max-psnr-drop-db", type=float, default=0.3)
    ap.add_argument("--prune-fraction", type=float, default=CompactConfig.prune_fraction)
    ap.add_argument("--finetune-iterations", type=int, default=CompactConfig.finetune_iterations)
    ap.add_argument("--max-rounds", type=int, default=CompactConfig.max_rounds)
    ap.add_argument("--garden-cpu-s", type=float, default=300.0)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--plot", default=str(REPO / "reports" / "compact.png"))
    ap.add_argument("--json", default=str(REPO / "reports" / "compact.json"))
    ap.add_argument("--plot-only", action="store_true", help="redraw --plot from --json, measure nothing")
    args = ap.parse_args()
    if args.plot_only:
        plot(json.loads(Path(args.json).read_text()), args.plot)
        return 0
    load = os.getloadavg()
    print(f"# compaction benchmark: {os.cpu_count()} CPUs, load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}, "
          f"tolerance {args.max_psnr_drop_db} dB, prune {args.prune_fraction:.0%} per round, "
          f"{args.finetune_iterations} fine-tuning iterations, render times median of {args.repeats} × 3 views")
    results = {}
    for name in args.scenes:
        model, train, test, cfg, train_cpu_s = (sandbox_inputs if name == "sandbox" else garden_inputs)(args)
        # Round 0 = the trained model; then every compaction step, accepted or not, re-measured here.
        compactor = Compactor(train, test, cfg, CompactConfig(
            max_psnr_drop_db=args.max_psnr_drop_db, prune_fraction=args.prune_fraction,
            finetune_iterations=args.finetune_iterations, max_rounds=args.max_rounds))
        cpu0 = time.process_time()
        models = [("trained", model, True)]
        orig_finetune = compactor.finetune

        def recording_finetune(m: GaussianModel, _orig=orig_finetune, _models=models) -> tuple:
            c0 = time.process_time()
            out, psnr_db = _orig(m)
            _models.append(("step", out, time.process_time() - c0))
            return out, psnr_db

        compactor.finetune = recording_finetune  # type: ignore[method-assign]
        result = compactor.run(model)
        compact_cpu_s = time.process_time() - cpu0
        cams = [f.camera for f in test[:3]]
        rows = []
        step_iter = iter(result.steps)
        cum_cpu = train_cpu_s
        for kind, m, step_cpu_s in models:
            step = None if kind == "trained" else next(step_iter)
            if step is not None:
                cum_cpu += step_cpu_s  # this step's fine-tuning and evaluation (ranking excluded)
            row = {"step": "trained" if step is None else step.kind, "gaussians": m.num_gaussians,
                   "sh_degree": m.sh_degree,
                   "heldout_psnr_db": result.heldout_psnr_before_db if step is None else step.heldout_psnr_db,
                   "accepted": True if step is None else step.accepted, "cpu_s": cum_cpu}
            for w, h in SIZES:
                for threads in (1, 2):
                    row[f"ms_{w}x{h}_t{threads}"] = render_ms(m, scaled(cams, w, h), threads, args.repeats,
                                                              cfg.background)
            rows.append(row)
        accepted = [i for i, r in enumerate(rows) if r["accepted"]]
        knee = accepted[-1]
        results[name] = {"rows": rows, "knee": knee, "summary": result.summary(), "train_cpu_s": train_cpu_s}
        print(f"\n## {name}: {result.gaussians_before} → {result.gaussians_after} Gaussians "
              f"({result.gaussians_after / result.gaussians_before:.0%}), SH {result.sh_degree_before} → "
              f"{result.sh_degree_after}, held-out PSNR {result.heldout_psnr_before_db:.2f} → "
              f"{result.heldout_psnr_after_db:.2f} dB; training {train_cpu_s:.0f} s CPU, compaction "
              f"{compact_cpu_s:.0f} s CPU ({result.wall_s:.0f} s wall)\n")
        print("| step | Gaussians | SH | held-out PSNR dB | kept | 320×240 fps (1 thr / 2 thr) | "
              "648×420 fps (1 thr / 2 thr) | CPU s so far |")
        print("|---|---|---|---|---|---|---|---|")
        for i, r in enumerate(rows):
            mark = " ← knee" if i == knee else ""
            print(f"| {r['step']}{mark} | {r['gaussians']} | {r['sh_degree']} | {r['heldout_psnr_db']:.2f} | "
                  f"{'yes' if r['accepted'] else 'no (over the tolerance)'} | "
                  f"{1e3 / r['ms_320x240_t1']:.1f} / {1e3 / r['ms_320x240_t2']:.1f} | "
                  f"{1e3 / r['ms_648x420_t1']:.1f} / {1e3 / r['ms_648x420_t2']:.1f} | {r['cpu_s']:.0f} |", flush=True)
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(results, indent=1))
    plot(results, args.plot)
    print(f"\nplot: {args.plot}; data: {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
