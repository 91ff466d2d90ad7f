"""Acceptance of the real robot's path (docs/hardware.md): a bag recorded as a LIMO records one, through
``gsrmr-dataset``, against the simulator's own dataset of the same frames.

**(a) Model quality through the bag path.** ``gsrmr_sim.robot_bag`` writes a bag of ``--frames`` images at the live
size (320×240; JPEG q90, plumb_bob distortion really in the frames, image stamps between the 50 Hz TF samples) with
odometry drift OFF and no blurred frames; ``gsrmr-dataset`` converts it with keyframing and blur rejection off
(``--min-translation-m 0 --min-rotation-deg 0 --blur-ratio 0``), so it keeps every image inside the odometry's span.
The simulator's own dataset holds exactly those frames: each rendered as the true pinhole view at the bag's rectified
camera (its CameraInfo's P, the camera the bag dataset is rectified to) from the true camera pose in ``truth.json``,
no depth in either (the bag has none: both trainings start from the same random initialisation). Both are trained
with one :class:`TrainConfig` (the live model's: ``gsrmr_sim.models.live_recipe``, same seed, steps, width) and the
same held-out split, and both models are scored on the simulator dataset's held-out frames — the true images — at
full size: mean PSNR over the frames of ``render(model, camera)`` against the true image. Acceptance: the bag-path
model within 0.5 dB of the simulator-dataset model. Also printed: the bag dataset's images against the true ones
(what the bag path does to the input: JPEG, distortion, rectification).

**(b) Pose accuracy.** Every kept frame's camera (``transforms.json``, map) and planar pose (``gsrmr_pose``) against
``truth.json``: centre error [cm] and rotation error [deg], max and median, drift off (the bag of (a)) and drift on (the
same recipe with ``drift``: the odometry's seeded yaw-per-metre and scale errors; how far the poses in ``/tf`` are
from the truth, for the record — one similarity cannot undo it, docs/splatting.md "Limits").

    .venv/bin/python bench/acceptance/robot_path.py [--frames N] [--iterations N] [--out DIR] [--quick]

``--quick``: 24 images at 96×72, 100 steps at 48 px, a few hundred Gaussians — checks the script, measures nothing.
"""

from __future__ import annotations

import argparse
import csv
from dataclasses import dataclass, replace
import math
import os
from pathlib import Path
import resource
import shutil
import statistics
import sys
import tempfile
import time

import numpy as np

from gsrmr_common.camera import camera_from_pose
from gsrmr_common.metrics import psnr
from gsrmr_common.nerfstudio import DatasetFrame, holdout_split, read_dataset, write_dataset
from gsrmr_offline import dataset_tool
from gsrmr_sim.machine_probe import machine_line
from gsrmr_sim.models import live_recipe
from gsrmr_sim.robot_bag import RobotBag, RobotBagRecipe, write_robot_bag
from gsrmr_sim.world.points import make_world
from gsrmr_sim.world.recorder import with_resolution
from gsrmr_sim.world.scene import load_scene
from gsrmr_splat.align import rotation_angle_deg
from gsrmr_splat.model import GaussianModel
from gsrmr_splat.render import render
from gsrmr_splat.train import Trainer
from gsrmr_splat.train_config import TrainConfig

ACCEPT_DB = 0.5
FRAMES_OUTSIDE = 2  # images before and after the odometry's span (dropped as out_of_range)
CONVERT_ALL = ("--min-translation-m", "0", "--min-rotation-deg", "0", "--blur-ratio", "0")
QUICK = {"frames": 24, "width": 96, "height": 72, "iterations": 100, "train_width": 48, "init_points": 1500,
         "budget": 4000, "holdout_every": 4}


@dataclass(frozen=True)
class Converted:
    """A bag written and converted: its truth, the dataset folder and the truth index of each kept frame."""

    bag: RobotBag
    dataset: Path
    kept: list[int]
    seconds: float  # wall time of writing the bag and converting it


@dataclass(frozen=True)
class Trained:
    """One training: its model, wall and process CPU seconds, the held-out PSNR on its own dataset (training
    width) and the mean PSNR against the true images (full size)."""

    model: GaussianModel
    wall_s: float
    cpu_s: float
    own_heldout_psnr_db: float
    true_psnr_db: float


def cpu_seconds() -> float:
    """CPU seconds of this process and its finished children."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def convert(out: Path, recipe: RobotBagRecipe) -> Converted:
    """Write the bag of ``recipe`` into ``out`` and convert it with every frame kept (keyframing and blur off)."""
    t0 = time.perf_counter()
    bag = write_robot_bag(out, recipe)
    dataset = out / "dataset"
    if dataset_tool.main([str(bag.bag_path), "--out", str(dataset), *CONVERT_ALL]) != 0:
        raise SystemExit(f"gsrmr-dataset failed on {bag.bag_path}")
    with open(dataset / "frames.csv", newline="") as f:
        kept = [int(r["index"]) for r in csv.DictReader(f) if r["status"] == "kept"]
    expected = [fr.index for fr in bag.frames if fr.in_pose_range]
    if kept != expected:
        raise SystemExit(f"{dataset}: kept {kept}, expected every frame inside the odometry's span {expected}")
    return Converted(bag, dataset, kept, time.perf_counter() - t0)


def simulator_dataset(bag: RobotBag, kept: list[int], out: Path) -> Path:
    """The simulator's own dataset of the ``kept`` frames: the true pinhole view at the bag's rectified camera from
    each frame's true pose, at the time its image was taken (no depth, as the bag has none)."""
    recipe = bag.recipe
    world = make_world(with_resolution(load_scene(recipe.scene), recipe.width_px, recipe.height_px), 1)
    drive_start_ns = round(recipe.drive_start_s * 1e9)
    frames = []
    for index in kept:
        truth = bag.frames[index]
        camera = camera_from_pose(*truth.pose, bag.mount, bag.rectified)
        rgb, _depth = world.render(camera, (drive_start_ns + truth.stamp_ns - recipe.start_stamp_ns) / 1e9)
        frames.append(DatasetFrame(camera, rgb, None, truth.pose))
    write_dataset(out, frames)
    return out


def mean_psnr_db(model: GaussianModel, frames: list[DatasetFrame], config: TrainConfig) -> float:
    """Mean over ``frames`` of the PSNR [dB] of the model's render at each frame's camera against its image."""
    return float(np.mean([psnr(render(model, f.camera, config.background, near_m=config.near_m).rgb, f.image)
                          for f in frames]))


def train(dataset: Path, config: TrainConfig, holdout_every: int, true_heldout: list[DatasetFrame]) -> Trained:
    """Train on ``dataset``'s training split; score on its own held-out split and on the true held-out images."""
    t0, c0 = time.perf_counter(), cpu_seconds()
    trainer = Trainer.from_dataset(dataset, config, holdout_every=holdout_every)
    model = trainer.train(progress=False)
    wall_s, cpu_s = time.perf_counter() - t0, cpu_seconds() - c0
    return Trained(model, wall_s, cpu_s, trainer.evaluate(), mean_psnr_db(model, true_heldout, config))


def rotation_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle [deg] of the rotation between two 3×3 rotations (accurate near 0, unlike the arccos of the trace)."""
    return float(rotation_angle_deg((a.T @ b)[None])[0])


def pose_errors(converted: Converted) -> dict[str, list[float]]:
    """Per kept frame: camera centre [cm] and rotation [deg] errors against the truth, and the planar pose's."""
    out: dict[str, list[float]] = {"centre_cm": [], "rotation_deg": [], "planar_cm": [], "yaw_deg": []}
    frames = read_dataset(converted.dataset, load_images=False)
    for frame, index in zip(frames, converted.kept, strict=True):
        truth = converted.bag.frames[index]
        c2w = frame.camera.camera_to_world
        out["centre_cm"].append(100.0 * float(np.linalg.norm(c2w[:3, 3] - truth.map_from_optical[:3, 3])))
        out["rotation_deg"].append(rotation_deg(c2w[:3, :3], truth.map_from_optical[:3, :3]))
        a, b, theta = frame.pose
        out["planar_cm"].append(100.0 * math.hypot(a - truth.pose[0], b - truth.pose[1]))
        out["yaw_deg"].append(abs(math.degrees(math.remainder(theta - truth.pose[2], math.tau))))
    return out


def image_psnr_db(bag_dataset: Path, true_dataset: Path) -> tuple[float, float]:
    """(mean, worst) PSNR [dB] of the bag dataset's images against the true images of the same frames."""
    values = [psnr(a.image, b.image) for a, b in zip(read_dataset(bag_dataset), read_dataset(true_dataset),
                                                      strict=True)]
    return float(np.mean(values)), float(np.min(values))


def settings(args: argparse.Namespace) -> tuple[RobotBagRecipe, TrainConfig, int]:
    """The bag recipe (drift off, no blurred frames), the training config and the held-out split."""
    scene = load_scene("sandbox")
    lap_frames = round(scene.slots * scene.slot_s * scene.camera.rate_hz)  # one lap of the route at 10 Hz
    frames = args.frames or (QUICK["frames"] if args.quick else lap_frames + 2 * FRAMES_OUTSIDE)
    recipe = RobotBagRecipe(frames=frames, width_px=QUICK["width"] if args.quick else scene.camera.intrinsics.width,
                            height_px=QUICK["height"] if args.quick else scene.camera.intrinsics.height,
                            drift=False, blurred_frames=0, frames_outside=FRAMES_OUTSIDE, seed=args.seed)
    live = live_recipe("sandbox", iterations=args.iterations or (QUICK["iterations"] if args.quick else None))
    config = live.config
    if args.quick:
        config = replace(config, resolution=QUICK["train_width"], init_points=QUICK["init_points"],
                         budget=QUICK["budget"])
    return recipe, replace(config, seed=args.seed), QUICK["holdout_every"] if args.quick else live.holdout_every


def fmt(values: list[float]) -> str:
    """``max / median`` to three significant digits."""
    return f"{max(values):.3g} / {statistics.median(values):.3g}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=0, help="images in the bag (default: one lap at 10 Hz + 4 outside)")
    ap.add_argument("--iterations", type=int, default=0, help="training steps (default: the live model's)")
    ap.add_argument("--seed", type=int, default=0, help="bag and training seed")
    ap.add_argument("--out", default="", help="keep the bags, datasets and models here (default: a temporary folder)")
    ap.add_argument("--quick", action="store_true", help="tiny sizes: checks the script, measures nothing")
    args = ap.parse_args()
    recipe, config, holdout_every = settings(args)
    print(f"# bench/acceptance/robot_path.py{' --quick' if args.quick else ''} (before: {machine_line()} "
          "(gsrmr_sim.machine_probe))", flush=True)
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="robot_path-"))
    for sub in ("drift_off", "drift_on", "simulator"):
        shutil.rmtree(out / sub, ignore_errors=True)
    t_start = time.perf_counter()

    plain = convert(out / "drift_off", recipe)
    true_dataset = simulator_dataset(plain.bag, plain.kept, out / "simulator")
    _train, true_heldout = holdout_split(read_dataset(true_dataset), holdout_every)
    via_bag = train(plain.dataset, config, holdout_every, true_heldout)
    via_sim = train(true_dataset, config, holdout_every, true_heldout)
    input_mean_db, input_worst_db = image_psnr_db(plain.dataset, true_dataset)
    diff_db = via_bag.true_psnr_db - via_sim.true_psnr_db
    k = plain.bag.rectified
    n_train = len(plain.kept) - len(true_heldout)
    print(f"\n## (a) model through the bag path vs the simulator's own dataset of the same {len(plain.kept)} frames")
    print(f"bag: {recipe.frames} images at {recipe.width_px}×{recipe.height_px} (JPEG q{recipe.jpeg_quality}, "
          f"plumb_bob {recipe.distortion}), drift off, no blur, seed {recipe.seed}, converted with "
          f"{' '.join(CONVERT_ALL)}; "
          f"rectified camera fx {k.fx:.2f} fy {k.fy:.2f} cx {k.cx:.2f} cy {k.cy:.2f} ({k.width}×{k.height}); "
          f"{n_train} training / {len(true_heldout)} held-out frames (every {holdout_every}th)")
    print(f"training (both): {config.iterations} steps at {config.resolution} px, SH {config.sh_degree}, budget "
          f"{config.budget}, init_points {config.init_points}, background {config.background}, seed {config.seed}")
    print(f"bag dataset images vs the true images: {input_mean_db:.2f} dB mean, {input_worst_db:.2f} dB worst\n")
    print("| trained on | Gaussians | wall s | CPU s | own held-out PSNR dB (train width) | PSNR vs true images dB "
          f"({k.width}×{k.height}) |")
    print("|---|---|---|---|---|---|")
    for name, t in (("bag path (gsrmr-dataset)", via_bag), ("simulator's own dataset", via_sim)):
        print(f"| {name} | {t.model.num_gaussians} | {t.wall_s:.0f} | {t.cpu_s:.0f} | {t.own_heldout_psnr_db:.2f} | "
              f"{t.true_psnr_db:.2f} |")
    verdict = "yes" if abs(diff_db) <= ACCEPT_DB else "NO"
    print(f"\nbag path − simulator: {diff_db:+.2f} dB; within {ACCEPT_DB} dB: {verdict}", flush=True)

    drifting = convert(out / "drift_on", replace(recipe, drift=True))
    print("\n## (b) pose accuracy of the kept frames against truth.json (max / median)\n")
    print("| bag | kept | camera centre cm | camera rotation deg | planar pose cm | yaw deg |")
    print("|---|---|---|---|---|---|")
    for name, conv in (("drift off", plain), ("drift on", drifting)):
        e = pose_errors(conv)
        drift = conv.bag.drift
        label = name if drift is None else (f"{name} (yaw {drift.yaw_rad_per_m:+.4f} rad/m, scale "
                                            f"{drift.scale_error:+.4f})")
        print(f"| {label} | {len(conv.kept)} | {fmt(e['centre_cm'])} | {fmt(e['rotation_deg'])} | "
              f"{fmt(e['planar_cm'])} | {fmt(e['yaw_deg'])} |")
    print(f"\n# {time.perf_counter() - t_start:.0f} s wall, load average after {os.getloadavg()[0]:.1f}; files "
          f"{'in ' + str(out) if args.out else 'removed (--out DIR keeps them)'}")
    if not args.out:
        shutil.rmtree(out, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
