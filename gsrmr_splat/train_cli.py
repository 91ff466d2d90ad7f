"""``gsrmr-train`` (nerfstudio dataset → 3DGS .ply, and ``train.json`` beside it: :func:`train_record`) and
``gsrmr-compact`` (.ply → the smallest .ply within a held-out PSNR tolerance), the torch tools of the splatting engine;
``gsrmr-render`` is :mod:`.cli`. Options: docs/splatting.md, "CLIs".
"""

from __future__ import annotations

import argparse
from dataclasses import replace
import json
import math
from pathlib import Path
import sys

from gsrmr_common.nerfstudio import holdout_split, read_dataset
from gsrmr_splat.cli import rgb_arg
from gsrmr_splat.compact import CompactConfig, Compactor
from gsrmr_splat.initialise import INIT_METHODS
from gsrmr_splat.model import GaussianModel
from gsrmr_splat.train import Trainer
from gsrmr_splat.train_config import ENGINES, TrainConfig

#: The record ``gsrmr-train`` writes beside its .ply (the name ``gsrmr-survey`` looks for).
TRAIN_RECORD = "train.json"


def train_record(trainer: Trainer, *, dataset: str, holdout_every: int, heldout_psnr_db: float | None,
                 extra: dict | None = None) -> dict:
    """What a training run did, JSON-ready: the split (``holdout_every`` and the training / held-out frames'
    counts and file names), the config, the initialisation, the last history row's iterations, times and
    held-out PSNR (dB, at the held-out frames' recorded poses, no exposure model), the history and the
    corrections (their summary per history row and per training frame) when pose or exposure optimisation is on.
    ``heldout_psnr_db`` is the delivered model's (after compaction, if any). NaN is written as null."""
    st = trainer.state
    last = st.history[-1] if st.history else None
    info: dict = {
        "dataset": dataset, "holdout_every": int(holdout_every),
        "train_frames": len(trainer.frames), "heldout_frames": len(trainer.test_frames),
        "train_files": [f.file_path for f in trainer.frames],
        "heldout_files": [f.file_path for f in trainer.test_frames],
        "config": trainer.config.to_dict(), "init": trainer.init_source,
        "iterations": int(last.iteration) if last else 0, "cpu_s": float(last.cpu_s) if last else 0.0,
        "wall_s": float(last.wall_s) if last else 0.0, "gaussians": trainer.num_gaussians,
        "heldout_psnr_db": heldout_psnr_db,
        "history": [{"iteration": int(h.iteration), "elapsed_s": float(h.wall_s), "cpu_s": float(h.cpu_s),
                     "train_loss": _json_number(float(h.loss)), "heldout_psnr_db": _json_number(float(h.test_psnr_db)),
                     "gaussians": int(h.num_gaussians)} for h in st.history]}
    if st.pose is not None or st.exposure is not None:
        info["corrections"] = trainer.corrections_summary()
        info["corrections_history"] = [dict(r) for r in st.correction_history]
        info["corrections_per_frame"] = trainer.corrections_per_frame()
    info.update(extra or {})
    return info


def _json_number(value: float) -> float | None:
    """NaN/inf as JSON null (strict JSON has no NaN)."""
    return value if math.isfinite(value) else None


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
    ap.add_argument("--init", choices=INIT_METHODS, default=d.init,
                    help="initial Gaussians: auto = depth when the frames have depth, else the dataset's point cloud "
                         "(ply_file_path in transforms.json), else random")
    ap.add_argument("--pose-opt", action="store_true",
                    help="refine each training frame's camera pose (per-frame se(3) correction, mean held at zero)")
    ap.add_argument("--lr-pose", type=float, default=d.lr_pose, help="pose Adam step per update, rad and m")
    ap.add_argument("--lr-pose-final", type=float, default=d.lr_pose_final)
    ap.add_argument("--pose-reg", type=float, default=d.pose_reg, help="L2 penalty on the pose corrections")
    ap.add_argument("--exposure-opt", action="store_true",
                    help="learn a per-frame, per-channel gain and bias (training only; mean held at zero)")
    ap.add_argument("--lr-exposure", type=float, default=d.lr_exposure)
    ap.add_argument("--lr-exposure-final", type=float, default=d.lr_exposure_final)
    ap.add_argument("--exposure-reg", type=float, default=d.exposure_reg)
    ap.add_argument("--test-pose-steps", type=int, default=0,
                    help="also report the held-out PSNR after this many steps of test-time pose refinement per "
                         "held-out frame (model frozen; not the fair held-out figure)")
    ap.add_argument("--max-psnr-drop-db", type=float, default=None,
                    help="compact at the end (gsrmr-compact): the smallest model within this many dB of the "
                         "held-out PSNR (needs --holdout-every)")
    ap.add_argument("--engine", choices=ENGINES, default=d.engine,
                    help="training step: fused (numba kernels, no autograd) or torch (autograd; the reference)")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    if args.max_psnr_drop_db is not None and args.holdout_every <= 0:
        print("gsrmr-train: --max-psnr-drop-db needs held-out views (--holdout-every N)", file=sys.stderr)
        return 2
    densify_until = args.densify_until if args.densify_until is not None else (2 * args.iterations) // 3
    cfg = TrainConfig(iterations=args.iterations, budget=args.budget, resolution=args.resolution,
                      sh_degree=args.sh_degree, init_points=args.init_points, background=args.background,
                      densify_until=densify_until, seed=args.seed, init=args.init, pose_opt=args.pose_opt,
                      lr_pose=args.lr_pose, lr_pose_final=args.lr_pose_final, pose_reg=args.pose_reg,
                      exposure_opt=args.exposure_opt, lr_exposure=args.lr_exposure,
                      lr_exposure_final=args.lr_exposure_final, exposure_reg=args.exposure_reg, engine=args.engine)
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
          f"scene extent {trainer.extent:.3f} m, {trainer.num_gaussians} initial Gaussians "
          f"(init: {trainer.init_source})")
    model = trainer.train(checkpoint=ckpt, progress=not args.no_progress, time_budget_s=args.time_budget_s,
                          cpu_budget_s=args.cpu_budget_s)
    h = trainer.state.history[-1]
    print(f"gsrmr-train: trained {h.num_gaussians} Gaussians (budget {cfg.budget}), {h.iteration} "
          f"iterations, {h.wall_s:.1f} s wall, {h.cpu_s:.1f} s CPU, final loss {h.loss:.4f}, "
          f"held-out PSNR {h.test_psnr_db:.2f} dB (at the recorded poses)")
    summary = trainer.corrections_summary()
    if summary:
        print("gsrmr-train: corrections: " + ", ".join(f"{k} {v:.3f}" for k, v in summary.items()))
    extra: dict = {"heldout_psnr_trained_db": _json_number(h.test_psnr_db)}
    if args.test_pose_steps > 0 and trainer.test_frames:
        refined_db, _ = trainer.evaluate_pose_refined(args.test_pose_steps)
        extra.update({"heldout_psnr_test_pose_refined_db": _json_number(refined_db),
                      "test_pose_steps": args.test_pose_steps})
        print(f"gsrmr-train: held-out PSNR after {args.test_pose_steps} steps of test-time pose refinement "
              f"{refined_db:.2f} dB (model frozen; not the fair figure)")
    final_db = h.test_psnr_db
    if args.max_psnr_drop_db is not None:
        # fine-tune on the frames as the model saw them (refined poses, images at the model's exposure), without
        # learning new corrections
        result = Compactor(trainer.refined_frames(), trainer.test_frames,
                           replace(cfg, pose_opt=False, exposure_opt=False),
                           CompactConfig(max_psnr_drop_db=args.max_psnr_drop_db)).run(model)
        model = result.model
        final_db = result.heldout_psnr_after_db
        extra["compaction"] = result.summary()
        print(f"gsrmr-train: compacted to {result.gaussians_after} Gaussians, SH degree {result.sh_degree_after}, "
              f"held-out PSNR {result.heldout_psnr_after_db:.2f} dB ({result.wall_s:.1f} s)")
    model.save_ply(args.out)
    record = Path(args.out).parent / TRAIN_RECORD
    record.write_text(json.dumps(train_record(trainer, dataset=str(args.dataset), holdout_every=args.holdout_every,
                                              heldout_psnr_db=_json_number(final_db), extra=extra),
                                 indent=1, default=str))
    print(f"gsrmr-train: wrote {args.out} and {record}")
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
