"""Acceptance of ``gsrmr-align`` (docs/hardware.md): the sandbox model and its dataset moved into a foreign frame
by a random similarity (scale 0.2–5), aligned back into ``map``, then the live demo on the aligned model within L_th.

1. The live sandbox model as ``gsrmr-demo`` builds it (``gsrmr_sim.models.live_model(live_recipe("sandbox"))``,
   compacted; cached in ``.cache/gsrmr``) and its round-1 dataset (144 frames, cameras in ``map``).
2. A seeded random similarity x_foreign = s·R·x_map + t — s log-uniform in [0.2, 5], R uniform on SO(3), t uniform
   in ±5·s per axis — applied to the model (``transform_model``: means, rotations, scales, SH) and to every camera of
   the dataset, written as a nerfstudio ``transforms.json`` (OpenGL camera axes, the same image names): what a model
   trained elsewhere and its pose file look like.
3. ``gsrmr-align FOREIGN.ply --model-poses transforms.json --map-dataset round1 --out ALIGNED.ply`` brings it back.
   Printed: its report (pairs, inliers, RMS/max camera-centre error in m, rotation error in deg), the recovered
   similarity against the inverse of the applied one (scale, rotation, translation errors), the largest distance
   between an aligned Gaussian and its original (m) and the PSNR of the aligned model's renders against the
   original's at the held-out cameras (320×240; ``gsrmr_common.metrics.psnr`` caps at 100 dB, MSE ≤ 1e-10).
4. The seed loss map: ``gsrmr-survey ALIGNED.ply round1 --holdout-every 8`` (default, the deployment's way) or, with
   ``--loss-map seed``, the demo's own mapping-round survey of the original model.
5. ``gsrmr-demo --model ALIGNED.ply --loss-map MAP`` ``--runs`` times (channel seeds ``--seeds`` + k); per run its
   mean MR loss against L_th and the demo's other figures.

    .venv/bin/python bench/acceptance/align_demo.py [--seed 0] [--runs 1] [--seeds 1] [--loss-map survey|seed]
                                         [--loss-threshold 0.03] [--out DIR] [--quick] [-- DEMO_ARGS...]

``--quick``: a tiny model (24 frames, 100 steps at 80 px, cached), alignment and survey only, no demo — checks the
script, measures nothing.
"""

from __future__ import annotations

import argparse
import json
import math
import os
from pathlib import Path
import shutil
import statistics
import sys
import tempfile
import time

import numpy as np

from gsrmr_common.camera import Camera, opencv_w2c_to_opengl_c2w
from gsrmr_common.metrics import psnr
from gsrmr_common.nerfstudio import holdout_split, read_dataset
from gsrmr_offline import survey_cli
from gsrmr_sim.demo import ensure_survey
from gsrmr_sim.demo_runs import run_once
from gsrmr_sim.machine_probe import machine_line
from gsrmr_sim.models import BuiltModel, ModelRecipe, build_model, live_model, live_recipe
from gsrmr_sim.world.scene import load_scene
from gsrmr_splat.align import Similarity, rotation_angle_deg, transform_model
from gsrmr_splat.align_cli import main as align_main
from gsrmr_splat.model import GaussianModel
from gsrmr_splat.render import render
from gsrmr_splat.train_config import TrainConfig

REPO = Path(__file__).resolve().parents[2]
SCENE = "sandbox"
SCALE_RANGE = (0.2, 5.0)
TRANSLATION_PER_SCALE = 5.0  # each axis of t uniform in ±5·s (foreign units)
RENDER_SIZE = (320, 240)  # the live render size
QUICK_RECIPE = ModelRecipe(scene=SCENE, frames=24, holdout_every=8, iterations=100, config=TrainConfig(
    iterations=100, resolution=80, sh_degree=0, budget=4000, init_points=1500, densify_until=66))


def random_similarity(seed: int) -> Similarity:
    """map → foreign: scale log-uniform in :data:`SCALE_RANGE`, a uniform random rotation (QR of a Gaussian
    matrix, sign-fixed), translation uniform in ±:data:`TRANSLATION_PER_SCALE`·s per axis."""
    rng = np.random.default_rng(seed)
    scale = float(np.exp(rng.uniform(math.log(SCALE_RANGE[0]), math.log(SCALE_RANGE[1]))))
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return Similarity(scale, q, rng.uniform(-1.0, 1.0, 3) * TRANSLATION_PER_SCALE * scale)


def write_foreign_transforms(dataset: Path, to_foreign: Similarity, path: Path) -> int:
    """The dataset's cameras carried by ``to_foreign``, as a nerfstudio transforms.json (camera→world, OpenGL axes,
    the dataset's image names and intrinsics); returns the number of frames."""
    frames = read_dataset(dataset, load_images=False)
    k = frames[0].camera.intrinsics
    out = []
    for f in frames:
        c2w = to_foreign.apply_camera_to_world(f.camera.camera_to_world)  # OpenCV axes
        w2c = np.linalg.inv(c2w)
        out.append({"file_path": f.file_path, "transform_matrix": opencv_w2c_to_opengl_c2w(w2c).tolist()})
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"camera_model": "OPENCV", "fl_x": k.fx, "fl_y": k.fy, "cx": k.cx, "cy": k.cy,
                                "w": k.width, "h": k.height, "frames": out}, indent=1))
    return len(out)


def similarity_errors(recovered: Similarity, truth: Similarity) -> dict[str, float]:
    """How far ``recovered`` (foreign → map) is from ``truth``: relative scale error, rotation angle [deg],
    translation error [m]."""
    return {"scale_rel_error": abs(recovered.scale / truth.scale - 1.0),
            "rotation_error_deg": float(rotation_angle_deg((recovered.rotation.T @ truth.rotation)[None])[0]),
            "translation_error_m": float(np.linalg.norm(recovered.translation - truth.translation))}


def render_agreement_db(aligned: GaussianModel, original: GaussianModel, dataset: Path, holdout_every: int) -> float:
    """Mean PSNR [dB] of the aligned model's renders against the original's at the held-out cameras (live size)."""
    _train, held_out = holdout_split(read_dataset(dataset, load_images=False), holdout_every)
    values = []
    for f in held_out:
        camera = Camera(f.camera.intrinsics.scaled(*RENDER_SIZE), f.camera.world_to_camera)
        values.append(psnr(render(aligned, camera).rgb, render(original, camera).rgb))
    return float(np.mean(values))


def the_model(quick: bool, cache: Path) -> BuiltModel:
    """The live sandbox model (compacted, as the demo runs it) or, quick, a tiny one; both cached."""
    if quick:
        return build_model(QUICK_RECIPE, cache=cache, log=lambda m: print(f"# {m}", flush=True))
    return live_model(live_recipe(SCENE), cache, log=lambda m: print(f"# {m}", flush=True))


def holdout_every_of(built: BuiltModel) -> int:
    """The held-out split the model was trained with (its train.json's recipe)."""
    train_json = json.loads((built.folder / "train.json").read_text())
    return int(train_json["recipe"]["holdout_every"])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0, help="seed of the random similarity")
    ap.add_argument("--runs", type=int, default=1, help="gsrmr-demo runs on the aligned model")
    ap.add_argument("--seeds", type=int, default=1, metavar="BASE", help="run k uses --channel-seed BASE + k")
    ap.add_argument("--loss-map", choices=("survey", "seed"), default="survey",
                    help="survey: gsrmr-survey of the aligned model on the round-1 held-out frames; seed: the demo's "
                         "own mapping-round survey of the original model")
    ap.add_argument("--loss-threshold", type=float, default=0.03, help="L_th of the demo runs")
    ap.add_argument("--cache", default=str(REPO / ".cache" / "gsrmr"))
    ap.add_argument("--out", default="", help="keep the foreign and aligned models, maps and reports here")
    ap.add_argument("--quick", action="store_true", help="tiny model, alignment and survey only, no demo")
    ap.add_argument("demo_args", nargs="*", help="passed to gsrmr-demo (after --)")
    args = ap.parse_args()
    print(f"# bench/acceptance/align_demo.py{' --quick' if args.quick else ''} (before: {machine_line()} "
          "(gsrmr_sim.machine_probe))", flush=True)
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="align_demo-"))
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    built = the_model(args.quick, Path(args.cache))
    dataset, holdout_every = built.folder / "round1", holdout_every_of(built)

    to_foreign = random_similarity(args.seed)
    foreign = out / "foreign"
    foreign.mkdir(exist_ok=True)
    transform_model(built.model, to_foreign).save_ply(foreign / "model.ply")
    n_frames = write_foreign_transforms(dataset, to_foreign, foreign / "transforms.json")
    aligned_path, report_path = out / "aligned.ply", out / "align_report.json"
    t0 = time.perf_counter()
    code = align_main([str(foreign / "model.ply"), "--model-poses", str(foreign / "transforms.json"), "--map-dataset",
                       str(dataset), "--out", str(aligned_path), "--report", str(report_path), "--seed", "0"])
    align_s = time.perf_counter() - t0
    if code != 0:
        print(f"gsrmr-align failed (exit {code})", file=sys.stderr)
        return 1
    report = json.loads(report_path.read_text())
    s = report["similarity"]
    errors = similarity_errors(Similarity(s["scale"], np.array(s["rotation"]), np.array(s["translation"])),
                               to_foreign.inverse())
    aligned = GaussianModel.load_ply(aligned_path)
    max_shift_m = float(np.max(np.linalg.norm(aligned.means - built.model.means, axis=1)))
    agreement_db = render_agreement_db(aligned, built.model, dataset, holdout_every)
    angle_deg = float(rotation_angle_deg(to_foreign.rotation[None])[0])
    print(f"\n## alignment: {built.path.name} ({built.model.num_gaussians} Gaussians, {n_frames} cameras) through "
          f"map → foreign s = {to_foreign.scale:.4f}, R by {angle_deg:.1f}°, |t| = "
          f"{np.linalg.norm(to_foreign.translation):.3f} (seed {args.seed}) and back with gsrmr-align ({align_s:.1f} s "
          "wall)\n")
    print("| pairs | inliers | RMS / max centre error m | RMS / max rotation error deg | scale rel. error | "
          "rotation error deg | translation error m | max Gaussian shift m | aligned vs original renders dB |")
    print("|---|---|---|---|---|---|---|---|---|")
    print(f"| {report['pairs']} | {report['inliers']} | {report['rms_center_error_m']:.3g} / "
          f"{report['max_center_error_m']:.3g} | {report['rms_rotation_error_deg']:.3g} / "
          f"{report['max_rotation_error_deg']:.3g} | {errors['scale_rel_error']:.3g} | "
          f"{errors['rotation_error_deg']:.3g} | {errors['translation_error_m']:.3g} | {max_shift_m:.3g} | "
          f"{agreement_db:.1f} |", flush=True)

    if args.loss_map == "survey":
        loss_map = out / "loss_map.json"
        if survey_cli.main([str(aligned_path), str(dataset), "--out", str(loss_map), "--holdout-every",
                            str(holdout_every)]) != 0:
            print("gsrmr-survey failed", file=sys.stderr)
            return 1
    else:
        loss_map = ensure_survey(SCENE, built.path, load_scene(SCENE).slots)
    print(f"# seed loss map: {loss_map} ({args.loss_map})", flush=True)
    if args.quick:
        print(f"\n# --quick: no demo run; {time.perf_counter() - t_start:.0f} s wall, load average "
              f"{os.getloadavg()[0]:.1f}")
        if not args.out:
            shutil.rmtree(out, ignore_errors=True)
        return 0

    print(f"\n## gsrmr-demo --model {aligned_path.name} --loss-map {loss_map.name}, L_th {args.loss_threshold}\n")
    columns = ("mean_loss", "images_sent", "slots", "energy_ratio_vs_upload_all", "regret", "psnr_db", "ssim",
               "slots_on_time")
    print("| run | channel seed | " + " | ".join(columns) + " | mean_loss ≤ L_th | wall s |")
    print("|" + "---|" * (len(columns) + 4))
    losses = []
    for k in range(args.runs):
        summary = run_once(["--model", str(aligned_path), "--loss-map", str(loss_map), "--loss-threshold",
                            str(args.loss_threshold), "--out", str(out / f"demo-{k + 1}"), *args.demo_args,
                            "--channel-seed", str(args.seeds + k)])
        losses.append(summary["mean_loss"])
        cells = " | ".join(f"{summary[c]:.4g}" if isinstance(summary[c], float) else str(summary[c]) for c in columns)
        within = "yes" if summary["mean_loss"] <= args.loss_threshold else "NO"
        print(f"| {k + 1} | {args.seeds + k} | {cells} | {within} | {summary['wall_s']:.0f} |", flush=True)
    print(f"\n# median mean loss {statistics.median(losses):.4f} vs L_th {args.loss_threshold}; "
          f"{time.perf_counter() - t_start:.0f} s wall, load average after {os.getloadavg()[0]:.1f}; files in {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
