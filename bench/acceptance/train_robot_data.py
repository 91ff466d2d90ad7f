"""Training on what a robot records (docs/splatting.md, "Training on what a robot records"): held-out PSNR of the
sandbox's mapping round when its recorded poses and exposure are a robot's, with and without ``--pose-opt`` and
``--exposure-opt``, RGB-D against RGB-only initialisation, at 160 and 320 px, against CPU time.

**The round.** ``gsrmr_sim.world.recorder.record_round1``: the sandbox scene's 144 mapping frames at the scene
camera's 320×240 with depth (the true images and true poses); every 8th frame is held out (``holdout_split``), as
the live model does. Written once per bench run in a temporary folder.

**Conditions** (what the *recorded* data of the training frames get; the held-out *images* are always the true
ones, so the PSNR is against the truth):

* ``clean`` — the true poses and images.
* ``noise`` — each training frame's recorded camera pose moved by exactly 2 cm and 1° in seeded random
  directions (6 DOF, :func:`gsrmr_splat.camera_opt.corrected_world_to_camera_np`); held-out poses true.
* ``drift`` — odometry drift as ``gsrmr_sim.robot_bag`` models it (``odometry_poses``: every increment scaled by
  1.02 and its yaw grown by 0.03 rad per metre travelled), integrated from the first frame's pose along the route
  (≈ 8.4 m: ≈ 0.25 rad of yaw by the end of the lap); every frame's recorded pose, training *and* held-out, is the
  drifted one (the camera on its mount there), as a robot records them. The held-out PSNR is then measured at
  drifted poses, as the live server renders at the robot's pose keys.
* ``exposure`` — each training image scaled by a seeded gain in [0.8, 1.2] (one per frame, all channels),
  clipped and re-quantised to 8 bit; poses true.

**Initialisation**: ``rgbd`` (the frames' depth: ``--init auto`` picks depth) or ``rgb`` (depth dropped, no point
cloud: random points).

**Training**: the live model's settings (``gsrmr_sim.models.live_recipe``: SH degree 0, at most 100k Gaussians, no
opacity reset) at ``--iterations`` steps of schedule (position-rate decay and densification to 2/3 of it), the
pose and exposure rates of :class:`TrainConfig`; one run per row and ``--runs`` seeds (run r: trainer seed r,
perturbation seed r). The run is stopped at each ``--stages-min`` CPU-minutes of training (process CPU time,
both threads; ``Trainer.train(cpu_budget_s=…)`` continues the same run) and the held-out PSNR measured there
(``Trainer.evaluate``: the held-out frames at their *recorded* poses, no exposure model — the fair figure). With
pose optimisation the last stage also reports the PSNR after ``--test-pose-steps`` steps of test-time pose
refinement per held-out frame (model frozen; labelled, not the fair figure), and the learned corrections' size.

``--fit-schedule``: the sandbox's 4000-step schedule ends well inside 3 CPU-minutes on the fused engine, so the
one-run stages above measure a finished model at 3 and 10. With the flag every stage is its own run whose schedule
is sized to the stage's budget (:func:`run_row_fitted`): what a user who gives training B CPU-minutes gets; the
stage's iterations are printed beside its PSNR.

Each row: condition, init, width, pose-opt, exposure-opt; iterations and CPU s at the last stage, it/s, held-out PSNR
at each stage — the median over the runs with the worst in brackets.

    .venv/bin/python bench/acceptance/train_robot_data.py [--runs 3] [--widths 160 320] [--stages-min 1 3 10]
        [--conditions clean noise drift exposure] [--iterations 4000] [--test-pose-steps 20] [--fit-schedule]
        [--json OUT]

``--quick``: 24 frames at 96×72, one width (48 px), stages of 2 and 4 CPU seconds, a few rows — checks the
script, measures nothing.
"""

from __future__ import annotations

import argparse
from dataclasses import asdict, dataclass, replace
import json
import math
import os
from pathlib import Path
import statistics
import sys
import tempfile
import time

import numba
import numpy as np

from gsrmr_common.camera import Camera, camera_from_pose
from gsrmr_common.nerfstudio import DatasetFrame, holdout_split, read_dataset
from gsrmr_common.pose2d import Pose2D
from gsrmr_sim.machine_probe import machine_line
from gsrmr_sim.models import live_recipe
from gsrmr_sim.robot_bag import OdometryDrift, odometry_poses
from gsrmr_sim.world.recorder import record_round1, with_resolution
from gsrmr_sim.world.scene import Scene, load_scene
from gsrmr_splat.camera_opt import corrected_world_to_camera_np
from gsrmr_splat.train import Trainer
from gsrmr_splat.train_config import TrainConfig

SCENE = "sandbox"
HOLDOUT_EVERY = 8
NOISE_CM, NOISE_DEG = 2.0, 1.0
DRIFT = OdometryDrift(yaw_rad_per_m=0.03, scale_error=0.02)
GAIN_RANGE = (0.8, 1.2)
CONDITIONS = ("clean", "noise", "drift", "exposure")


@dataclass(frozen=True)
class Row:
    """One configuration of the table."""

    condition: str
    init: str  # rgbd | rgb
    width: int
    pose_opt: bool
    exposure_opt: bool


#: (condition, init, pose-opt, exposure-opt) of the default grid, each at every width: every condition without
#: the options and with the one meant for it, clean with both (do they cost anything?), RGB-only on clean and noise.
GRID = (("clean", "rgbd", False, False), ("clean", "rgbd", True, True),
        ("noise", "rgbd", False, False), ("noise", "rgbd", True, False),
        ("drift", "rgbd", False, False), ("drift", "rgbd", True, False),
        ("exposure", "rgbd", False, False), ("exposure", "rgbd", False, True),
        ("clean", "rgb", False, False), ("noise", "rgb", False, False), ("noise", "rgb", True, False))
QUICK_GRID = (("clean", "rgbd", False, False), ("noise", "rgbd", True, False), ("drift", "rgb", True, False),
              ("exposure", "rgbd", False, True))
QUICK = {"frames": 24, "width": 96, "height": 72, "widths": [48], "stages_s": [2.0, 4.0], "iterations": 200,
         "init_points": 1500, "budget": 4000, "holdout_every": 4, "test_pose_steps": 2}


def record(scene: Scene, folder: Path, frames: int) -> list[DatasetFrame]:
    """The sandbox's round 1 (true images, depth and poses), written under ``folder`` and read back."""
    return read_dataset(record_round1(scene, folder / "round1", frames=frames, seed=0))


def pose_perturbation(rng: np.random.Generator) -> np.ndarray:
    """(ω rad, τ m) of exactly NOISE_DEG and NOISE_CM in uniformly random directions."""
    w, t = rng.normal(size=3), rng.normal(size=3)
    return np.concatenate([w / np.linalg.norm(w) * math.radians(NOISE_DEG), t / np.linalg.norm(t) * NOISE_CM / 100])


def drifted_cameras(frames: list[DatasetFrame], scene: Scene) -> list[Camera]:
    """Each frame's camera at the dead-reckoned pose: DRIFT integrated along the frames' true planar poses from the
    first one (``map → odom`` at the first pose), the scene's mount on it."""
    truth = [tuple(float(v) for v in f.pose) for f in frames]
    odom = odometry_poses(truth, DRIFT)
    return [camera_from_pose(*Pose2D.of(truth[0]).compose(o), scene.camera.mount, f.camera.intrinsics)
            for f, o in zip(frames, odom, strict=True)]


def with_camera(frame: DatasetFrame, camera: Camera) -> DatasetFrame:
    return DatasetFrame(camera, frame.image, frame.depth_m, frame.pose, frame.file_path)


def condition_frames(frames: list[DatasetFrame], scene: Scene, condition: str, init: str, seed: int,
                     holdout_every: int) -> tuple[list[DatasetFrame], list[DatasetFrame]]:
    """(training frames as recorded under ``condition``, held-out frames: true images at their recorded poses)."""
    rng = np.random.default_rng((seed, CONDITIONS.index(condition)))
    recorded = list(frames)
    if condition == "drift":
        recorded = [with_camera(f, c) for f, c in zip(frames, drifted_cameras(frames, scene), strict=True)]
    train, held = holdout_split(recorded, holdout_every)
    if condition == "noise":
        train = [with_camera(f, Camera(f.camera.intrinsics, corrected_world_to_camera_np(
            f.camera.world_to_camera, pose_perturbation(rng)))) for f in train]
    elif condition == "exposure":
        gains = rng.uniform(*GAIN_RANGE, len(train))
        train = [DatasetFrame(f.camera, (np.round(np.clip(f.image * g, 0.0, 1.0) * 255) / 255).astype(np.float32),
                              f.depth_m, f.pose, f.file_path) for f, g in zip(train, gains, strict=True)]
    if init == "rgb":
        train = [DatasetFrame(f.camera, f.image, None, f.pose, f.file_path) for f in train]
    return train, held


def train_config(row: Row, seed: int, iterations: int, quick: bool) -> TrainConfig:
    """The live recipe's config at the row's width and options (see the module docstring)."""
    live = live_recipe(SCENE, iterations=iterations, width=row.width).config
    cfg = replace(live, seed=seed, final_prune=False, pose_opt=row.pose_opt, exposure_opt=row.exposure_opt)
    if quick:
        cfg = replace(cfg, init_points=QUICK["init_points"], budget=QUICK["budget"])
    return cfg


def run_row(row: Row, train: list[DatasetFrame], held: list[DatasetFrame], cfg: TrainConfig, stages_s: list[float],
            test_pose_steps: int) -> dict:
    """Train in CPU-time stages; the held-out PSNR at each, iterations, CPU s, it/s and the corrections."""
    trainer = Trainer(train, cfg, held)
    psnr_db = []
    for budget in stages_s:
        trainer.train(cpu_budget_s=budget, progress=False)
        psnr_db.append(trainer.state.history[-1].test_psnr_db)
    return row_result(row, trainer, psnr_db, test_pose_steps)


def row_result(row: Row, trainer: Trainer, psnr_db: list[float], test_pose_steps: int, **extra) -> dict:
    """A row's figures from its (last) trainer: iterations, CPU s, it/s, Gaussians, corrections, test-time PSNR."""
    last = trainer.state.history[-1]
    out = {"row": asdict(row), "init_source": trainer.init_source, "iterations": int(last.iteration),
           "cpu_s": float(last.cpu_s), "it_per_s": last.iteration / max(last.cpu_s, 1e-9), "psnr_db": psnr_db,
           "gaussians": int(last.num_gaussians), "corrections": trainer.corrections_summary(), **extra}
    if row.pose_opt and test_pose_steps > 0:
        out["test_pose_refined_psnr_db"] = trainer.evaluate_pose_refined(test_pose_steps)[0]
    return out


#: --fit-schedule: the first stage's schedule is sized from a probe of this many CPU-s of the default schedule at
#: this fraction of its rate (densification slows the later steps); a stage may overrun its budget by OVERRUN.
PROBE_S, PROBE_RATE_FRACTION, OVERRUN = 15.0, 0.7, 1.15


_warmed_up: set[tuple[bool, bool]] = set()


def warm_up(row: Row, train: list[DatasetFrame], held: list[DatasetFrame], run: int, iterations: int,
            quick: bool) -> None:
    """Once per process and option set: a throwaway run past the first densification, so that numba's compilation
    (tens of CPU-seconds in a fresh checkout, whose kernel cache is empty) falls in no probe and no stage's budget
    (it once left a 1-CPU-minute stage 10 iterations)."""
    key = (row.pose_opt, row.exposure_opt)
    if key in _warmed_up:
        return
    cfg = train_config(row, run, iterations, quick)
    Trainer(train, cfg, held).train(iterations=min(cfg.iterations, cfg.densify_from + cfg.densify_interval + 1),
                                    progress=False)
    _warmed_up.add(key)


def run_row_fitted(row: Row, train: list[DatasetFrame], held: list[DatasetFrame], run: int, iterations: int,
                   quick: bool, stages_s: list[float], test_pose_steps: int) -> dict:
    """``--fit-schedule``: every stage is its own run from scratch, its schedule (position-rate decay, densification
    to 2/3) sized to the stage's CPU budget, as a user who gives training B CPU-minutes would size it: iterations =
    budget × the rate of the stage before (the first: a probe of the default schedule, at PROBE_RATE_FRACTION of its
    rate, after :func:`warm_up`); stopped at OVERRUN × budget if the schedule is not done by then. The held-out PSNR
    of each stage's end, its iterations and CPU s (``stages``); the last stage's trainer gives the rest of the row."""
    warm_up(row, train, held, run, iterations, quick)
    probe = Trainer(train, train_config(row, run, iterations, quick), held)
    probe.train(cpu_budget_s=PROBE_S if not quick else 1.0, progress=False)
    rate = PROBE_RATE_FRACTION * probe.state.history[-1].iteration / max(probe.state.history[-1].cpu_s, 1e-9)
    psnr_db, stages, trainer = [], [], probe
    for budget in stages_s:
        planned = max(10, int(rate * budget))
        trainer = Trainer(train, train_config(row, run, planned, quick), held)
        trainer.train(cpu_budget_s=OVERRUN * budget, progress=False)
        last = trainer.state.history[-1]
        psnr_db.append(last.test_psnr_db)
        stages.append({"budget_s": budget, "planned": planned, "iterations": int(last.iteration),
                       "cpu_s": float(last.cpu_s)})
        rate = last.iteration / max(last.cpu_s, 1e-9)
    return row_result(row, trainer, psnr_db, test_pose_steps, stages=stages)


def stage_steps(results: list[dict], i: int) -> str:
    """`` (N it)``: the iterations run 0's stage ``i`` ran (--fit-schedule; its own schedule), else nothing."""
    stages = results[0].get("stages")
    return f" ({stages[i]['iterations']} it)" if stages else ""


def fmt(values: list[float], digits: int = 2) -> str:
    """Median, and the worst (lowest) in brackets when there are several."""
    vals = [v for v in values if v == v]
    if not vals:
        return "–"
    med = f"{statistics.median(vals):.{digits}f}"
    return med if len(vals) == 1 else f"{med} ({min(vals):.{digits}f})"


def cpu_time_text(seconds: float) -> str:
    """``10 CPU-min``, or ``4 CPU-s`` below a minute."""
    return f"{seconds / 60:g} CPU-min" if seconds >= 60 else f"{seconds:g} CPU-s"


def corrections_text(results: list[dict]) -> str:
    c = results[0]["corrections"]
    parts = []
    if "pose_delta_mean_cm" in c:
        parts.append(f"pose {c['pose_delta_mean_cm']:.1f}/{c['pose_delta_max_cm']:.1f} cm, "
                     f"{c['pose_delta_mean_deg']:.2f}/{c['pose_delta_max_deg']:.2f}° (mean/max)")
    if "exposure_gain_min" in c:
        parts.append(f"gains {c['exposure_gain_min']:.2f}–{c['exposure_gain_max']:.2f}")
    return "; ".join(parts) or "–"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--widths", type=int, nargs="+", default=[160, 320])
    ap.add_argument("--stages-min", type=float, nargs="+", default=[1.0, 3.0, 10.0],
                    help="CPU-minutes of training at which the held-out PSNR is measured")
    ap.add_argument("--conditions", nargs="+", choices=CONDITIONS, default=list(CONDITIONS))
    ap.add_argument("--iterations", type=int, default=4000, help="steps of the schedule (a stage may stop earlier)")
    ap.add_argument("--test-pose-steps", type=int, default=20)
    ap.add_argument("--frames", type=int, default=None, help="mapping frames (default: the scene's, 144)")
    ap.add_argument("--json", default=None, help="write every run's figures here")
    ap.add_argument("--fit-schedule", action="store_true",
                    help="each stage its own run, its schedule sized to the stage's CPU budget (run_row_fitted), "
                         "instead of one run of --iterations measured as it passes each stage")
    ap.add_argument("--quick", action="store_true", help="a tiny smoke run of the script (measures nothing)")
    args = ap.parse_args()
    scene = load_scene(SCENE)
    grid, widths = GRID, args.widths
    stages_s = [60.0 * m for m in args.stages_min]
    frames_n, holdout_every, iterations, tps = args.frames or scene.frames, HOLDOUT_EVERY, args.iterations, \
        args.test_pose_steps
    if args.quick:
        scene = with_resolution(scene, QUICK["width"], QUICK["height"])
        grid, widths, stages_s = QUICK_GRID, QUICK["widths"], QUICK["stages_s"]
        frames_n, holdout_every, iterations, tps = QUICK["frames"], QUICK["holdout_every"], QUICK["iterations"], \
            QUICK["test_pose_steps"]
        args.runs = 1
    rows = [Row(c, i, w, p, e) for w in widths for (c, i, p, e) in grid if c in args.conditions]
    k = scene.camera.intrinsics
    print(f"# bench/acceptance/train_robot_data.py{' --quick' if args.quick else ''} (before: {machine_line()} "
          f"(gsrmr_sim.machine_probe)); numba {numba.get_num_threads()} threads, torch 1 thread")
    print(f"# {SCENE} round 1: {frames_n} frames at {k.width}×{k.height}, every {holdout_every}th held out; "
          f"{len(rows)} rows × {args.runs} runs × {cpu_time_text(stages_s[-1])} = "
          f"{cpu_time_text(len(rows) * args.runs * stages_s[-1])} of training (+ recording and evaluation)")
    print(f"# noise {NOISE_CM} cm / {NOISE_DEG}° per training frame; drift {DRIFT.yaw_rad_per_m} rad/m yaw, "
          f"{100 * DRIFT.scale_error:.0f} % scale (all frames); exposure gains U{GAIN_RANGE} per training frame")
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="gsrmr-train-robot-") as tmp:
        frames = record(scene, Path(tmp), frames_n)
    cfg0 = train_config(rows[0], 0, iterations, args.quick)
    print(f"# recorded in {time.perf_counter() - t0:.0f} s; config: iterations {cfg0.iterations}, densify until "
          f"{cfg0.densify_until}, SH {cfg0.sh_degree}, budget {cfg0.budget}, init points {cfg0.init_points}, "
          f"lr_pose {cfg0.lr_pose} → {cfg0.lr_pose_final}, pose_reg {cfg0.pose_reg}, lr_exposure "
          f"{cfg0.lr_exposure} → {cfg0.lr_exposure_final}, exposure_reg {cfg0.exposure_reg}")
    stage_cols = " | ".join(f"held-out PSNR dB @ {cpu_time_text(s)}" for s in stages_s)
    if args.fit_schedule:
        print(f"# --fit-schedule: each stage its own run, its schedule sized to the stage's budget (probe "
              f"{PROBE_S:g} CPU-s at {PROBE_RATE_FRACTION:g}× its rate, then the stage before's rate; stop at "
              f"{OVERRUN:g}× the budget); iterations, CPU s and it/s are the last stage's")
    print(f"\n| condition | init | width | pose-opt | exposure-opt | iterations | CPU s | it/s | {stage_cols} | "
          f"test-time pose-refined PSNR dB | corrections (run 0) |")
    print("|" + "---|" * (10 + len(stages_s)))
    everything = []
    for row in rows:
        results = []
        for run in range(args.runs):
            train, held = condition_frames(frames, scene, row.condition, row.init, run, holdout_every)
            if args.fit_schedule:
                results.append(run_row_fitted(row, train, held, run, iterations, args.quick, stages_s, tps))
            else:
                results.append(run_row(row, train, held, train_config(row, run, iterations, args.quick), stages_s,
                                       tps))
        everything.extend(results)
        stages = " | ".join(fmt([r["psnr_db"][i] for r in results]) + stage_steps(results, i)
                            for i in range(len(stages_s)))
        tto = fmt([r.get("test_pose_refined_psnr_db", float("nan")) for r in results])
        print(f"| {row.condition} | {row.init} | {row.width} | {'on' if row.pose_opt else 'off'} | "
              f"{'on' if row.exposure_opt else 'off'} | {fmt([r['iterations'] for r in results], 0)} | "
              f"{fmt([r['cpu_s'] for r in results], 0)} | {fmt([r['it_per_s'] for r in results], 1)} | {stages} | "
              f"{tto} | {corrections_text(results)} |", flush=True)
    print(f"\n# after: load average {os.getloadavg()[0]:.1f}; {time.perf_counter() - t0:.0f} s wall in all")
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": everything, "stages_s": stages_s, "runs": args.runs},
                                              indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
