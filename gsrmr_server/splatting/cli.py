"""Command-line tools: ``gsrmr-train`` (dataset → .ply) and ``gsrmr-render`` (.ply → PNGs).

``gsrmr-render MODEL.ply --cameras CAMERAS.json --out DIR`` renders every camera of CAMERAS.json, a
list of ``{"width", "height", "K" (3×3, pixel centres at +0.5 as in 3DGS/COLMAP), "world_to_camera"
(4×4, OpenCV axes)}``, to DIR/000.png, 001.png, … in list order. ``--pose a,b,θ`` (metres, metres,
radians; repeatable) renders robot poses instead, with the camera mount ``--mount-height-m``,
``--mount-pitch-rad`` (positive = looking down), ``--mount-forward-m``, ``--mount-left-m`` and
intrinsics ``--width --height --hfov-deg`` (see :mod:`gsrmr_common.camera`).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
import sys
import time

import cv2
import numpy as np

from gsrmr_common.camera import Camera, CameraMount, Intrinsics, camera_from_pose
from gsrmr_server.splatting.model import GaussianModel


def _floats(text: str, n: int, what: str) -> tuple[float, ...]:
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"{what}: expected {n} comma-separated numbers, got {text!r}") from exc
    if len(vals) != n or not all(math.isfinite(v) for v in vals):
        raise argparse.ArgumentTypeError(f"{what}: expected {n} finite comma-separated numbers, got {text!r}")
    return vals


def _pose(text: str) -> tuple[float, ...]:
    return _floats(text, 3, "--pose a,b,theta")


def _rgb(text: str) -> tuple[float, ...]:
    return _floats(text, 3, "--background r,g,b")


def load_cameras_json(path: str | Path) -> list[Camera]:
    """Parse a CAMERAS.json list; raises ValueError naming the bad entry."""
    data = json.loads(Path(path).read_text())
    if not isinstance(data, list):
        raise ValueError(f"{path}: expected a JSON list of cameras")
    cams = []
    for i, entry in enumerate(data):
        try:
            k = np.asarray(entry["K"], dtype=np.float64)
            w2c = np.asarray(entry["world_to_camera"], dtype=np.float64)
            if k.shape != (3, 3) or w2c.shape != (4, 4):
                raise ValueError("K must be 3×3 and world_to_camera 4×4")
            cams.append(Camera(Intrinsics.from_k(k, int(entry["width"]), int(entry["height"])), w2c))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{path}: camera {i}: {exc}") from exc
    return cams


def render_main(argv: list[str] | None = None) -> int:
    """Entry point of ``gsrmr-render``."""
    ap = argparse.ArgumentParser(prog="gsrmr-render", description=__doc__.split("\n\n")[1],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("model", help="3DGS .ply model")
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--cameras", help="CAMERAS.json (list of width/height/K/world_to_camera)")
    src.add_argument("--pose", type=_pose, action="append", help="robot pose a_m,b_m,theta_rad (repeatable)")
    ap.add_argument("--out", required=True, help="output directory (000.png, 001.png, …)")
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--hfov-deg", type=float, default=70.0, help="horizontal field of view for --pose")
    ap.add_argument("--mount-height-m", type=float, default=CameraMount.height_m)
    ap.add_argument("--mount-pitch-rad", type=float, default=CameraMount.pitch_rad)
    ap.add_argument("--mount-forward-m", type=float, default=CameraMount.forward_m)
    ap.add_argument("--mount-left-m", type=float, default=CameraMount.left_m)
    ap.add_argument("--background", type=_rgb, default=(0.0, 0.0, 0.0), help="r,g,b in [0, 1]")
    ap.add_argument("--depth", action="store_true", help="also write DIR/NNN_depth.png (uint16 mm)")
    args = ap.parse_args(argv)
    from gsrmr_server.splatting.render import render

    try:
        model = GaussianModel.load_ply(args.model)
        if args.cameras:
            cams = load_cameras_json(args.cameras)
        else:
            mount = CameraMount(args.mount_height_m, args.mount_pitch_rad, args.mount_forward_m, args.mount_left_m)
            k = Intrinsics.from_fov(args.width, args.height, math.radians(args.hfov_deg))
            cams = [camera_from_pose(a, b, th, mount, k) for a, b, th in args.pose]
    except (ValueError, FileNotFoundError) as exc:
        print(f"gsrmr-render: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for i, cam in enumerate(cams):
        t0 = time.perf_counter()
        res = render(model, cam, args.background)
        dt = time.perf_counter() - t0
        u8 = np.clip(np.round(res.rgb * 255.0), 0, 255).astype(np.uint8)
        cv2.imwrite(str(out / f"{i:03d}.png"), cv2.cvtColor(u8, cv2.COLOR_RGB2BGR))
        if args.depth:
            mm = np.clip(np.round(res.depth * 1000.0), 0, 65535).astype(np.uint16)
            cv2.imwrite(str(out / f"{i:03d}_depth.png"), mm)
        print(f"{out / f'{i:03d}.png'}: {cam.width}×{cam.height}, {res.num_visible} visible Gaussians, "
              f"{dt * 1000:.1f} ms")
    return 0


def train_main(argv: list[str] | None = None) -> int:
    """Entry point of ``gsrmr-train``."""
    from gsrmr_server.splatting.train import TrainConfig, Trainer

    ap = argparse.ArgumentParser(prog="gsrmr-train", description="Train a Gaussian-splatting model from a "
                                 "nerfstudio dataset (transforms.json) and write a 3DGS .ply.",
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("dataset", help="dataset folder or its transforms.json")
    ap.add_argument("--out", required=True, help="output MODEL.ply")
    d = TrainConfig()
    ap.add_argument("--iterations", type=int, default=d.iterations)
    ap.add_argument("--budget", type=int, default=d.budget, help="maximum number of Gaussians")
    ap.add_argument("--resolution", type=int, default=None, help="train at this image width (px)")
    ap.add_argument("--sh-degree", type=int, default=d.sh_degree, choices=range(4))
    ap.add_argument("--init-points", type=int, default=d.init_points)
    ap.add_argument("--background", type=_rgb, default=d.background, help="r,g,b in [0, 1]")
    ap.add_argument("--densify-until", type=int, default=None, help="default: 2/3 of --iterations")
    ap.add_argument("--holdout-every", type=int, default=0, help="every Nth frame is a test view (0 = none)")
    ap.add_argument("--checkpoint", default=None, help="checkpoint file (default: MODEL.ply + .ckpt)")
    ap.add_argument("--resume", action="store_true", help="continue from --checkpoint")
    ap.add_argument("--time-budget-s", type=float, default=None, help="stop after this wall time")
    ap.add_argument("--cpu-budget-s", type=float, default=None, help="stop after this process CPU time")
    ap.add_argument("--seed", type=int, default=d.seed)
    ap.add_argument("--max-psnr-drop-db", type=float, default=None,
                    help="compact at the end (gsrmr-compact): the smallest model within this many dB of the "
                         "held-out PSNR (needs --holdout-every)")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    if args.max_psnr_drop_db is not None and args.holdout_every <= 0:
        print("gsrmr-train: --max-psnr-drop-db needs held-out views (--holdout-every N)", file=sys.stderr)
        return 2
    densify_until = args.densify_until if args.densify_until is not None else (2 * args.iterations) // 3
    cfg = TrainConfig(iterations=args.iterations, budget=args.budget, resolution=args.resolution,
                      sh_degree=args.sh_degree, init_points=args.init_points, background=args.background,
                      densify_until=densify_until, seed=args.seed)
    ckpt = Path(args.checkpoint) if args.checkpoint else Path(str(args.out) + ".ckpt")
    try:
        trainer = Trainer.from_dataset(args.dataset, cfg, holdout_every=args.holdout_every)
        if args.resume:
            if not ckpt.exists():
                raise FileNotFoundError(f"--resume: no checkpoint at {ckpt}")
            trainer.load_checkpoint(ckpt)
    except (ValueError, FileNotFoundError) as exc:
        print(f"gsrmr-train: {exc}", file=sys.stderr)
        return 2
    print(f"gsrmr-train: {len(trainer.frames)} training views, {len(trainer.test_frames)} test views, "
          f"scene extent {trainer.extent:.3f} m, {trainer.num_gaussians} initial Gaussians")
    model = trainer.train(checkpoint=ckpt, progress=not args.no_progress, time_budget_s=args.time_budget_s,
                          cpu_budget_s=args.cpu_budget_s)
    h = trainer.state.history[-1]
    print(f"gsrmr-train: trained {h.num_gaussians} Gaussians (budget {cfg.budget}), {h.iteration} "
          f"iterations, {h.wall_s:.1f} s wall, {h.cpu_s:.1f} s CPU, final loss {h.loss:.4f}, "
          f"held-out PSNR {h.test_psnr_db:.2f} dB")
    if args.max_psnr_drop_db is not None:
        from gsrmr_server.splatting.compact import CompactConfig, Compactor

        result = Compactor(trainer.frames, trainer.test_frames, cfg,
                           CompactConfig(max_psnr_drop_db=args.max_psnr_drop_db)).run(model)
        model = result.model
        print(f"gsrmr-train: compacted to {result.gaussians_after} Gaussians, SH degree {result.sh_degree_after}, "
              f"held-out PSNR {result.heldout_psnr_after_db:.2f} dB ({result.wall_s:.1f} s)")
    model.save_ply(args.out)
    print(f"gsrmr-train: wrote {args.out}")
    return 0


def compact_main(argv: list[str] | None = None) -> int:
    """Entry point of ``gsrmr-compact``: the last line printed is one JSON object of the figures."""
    from gsrmr_common.nerfstudio import read_dataset
    from gsrmr_server.splatting.compact import CompactConfig, Compactor
    from gsrmr_server.splatting.train import TrainConfig, holdout_split

    d, c = TrainConfig(), CompactConfig()
    ap = argparse.ArgumentParser(prog="gsrmr-compact", description="Prune a trained 3DGS model to the smallest "
                                 "one within a held-out PSNR tolerance (contribution ranking + fine-tuning, "
                                 "then lower SH degrees).", formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("model", help="trained 3DGS .ply")
    ap.add_argument("dataset", help="its nerfstudio dataset (folder or transforms.json)")
    ap.add_argument("--out", required=True, help="output SMALL.ply")
    ap.add_argument("--max-psnr-drop-db", type=float, default=c.max_psnr_drop_db)
    ap.add_argument("--holdout-every", type=int, default=8, help="every Nth frame is a held-out view, as in "
                    "gsrmr-train --holdout-every (the views the PSNR is measured on)")
    ap.add_argument("--resolution", type=int, default=None, help="train/measure at this image width (px)")
    ap.add_argument("--background", type=_rgb, default=d.background, help="r,g,b in [0, 1]")
    ap.add_argument("--prune-fraction", type=float, default=c.prune_fraction)
    ap.add_argument("--finetune-iterations", type=int, default=c.finetune_iterations)
    ap.add_argument("--max-rounds", type=int, default=c.max_rounds)
    ap.add_argument("--keep-sh", action="store_true", help="do not try lower SH degrees")
    ap.add_argument("--seed", type=int, default=d.seed)
    args = ap.parse_args(argv)
    try:
        model = GaussianModel.load_ply(args.model)
        cfg = TrainConfig(resolution=args.resolution, background=args.background, seed=args.seed,
                          sh_degree=model.sh_degree)
        train, test = holdout_split(read_dataset(args.dataset), args.holdout_every)
        compactor = Compactor(train, test, cfg, CompactConfig(
            max_psnr_drop_db=args.max_psnr_drop_db, prune_fraction=args.prune_fraction,
            finetune_iterations=args.finetune_iterations, max_rounds=args.max_rounds, lower_sh=not args.keep_sh))
    except (ValueError, FileNotFoundError) as exc:
        print(f"gsrmr-compact: {exc}", file=sys.stderr)
        return 2
    result = compactor.run(model)
    for s in result.steps:
        print(f"gsrmr-compact: {s.kind}: {s.gaussians} Gaussians, SH {s.sh_degree}, held-out PSNR "
              f"{s.heldout_psnr_db:.2f} dB, {'kept' if s.accepted else 'over the tolerance: stop'} ({s.wall_s:.1f} s)")
    result.model.save_ply(args.out)
    print(json.dumps(result.summary()))
    return 0
