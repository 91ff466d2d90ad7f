"""``gsrmr-train`` (nerfstudio dataset → 3DGS .ply) and ``gsrmr-compact`` (.ply → the smallest .ply within a
held-out PSNR tolerance): the torch tools of the splatting engine (``gsrmr-render`` is :mod:`.cli`, without torch).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
import sys

from gsrmr_common.nerfstudio import holdout_split, read_dataset
from gsrmr_server.splatting.cli import rgb_arg
from gsrmr_server.splatting.compact import CompactConfig, Compactor
from gsrmr_server.splatting.model import GaussianModel
from gsrmr_server.splatting.train import Trainer
from gsrmr_server.splatting.train_config import TrainConfig


def train_main(argv: list[str] | None = None) -> int:
    """Entry point of ``gsrmr-train``."""
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
    ap.add_argument("--background", type=rgb_arg, default=d.background, help="r,g,b in [0, 1]")
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
    ap.add_argument("--background", type=rgb_arg, default=d.background, help="r,g,b in [0, 1]")
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
