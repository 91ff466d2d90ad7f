"""``gsrmr-update MODELS --received DATASET…``: between rounds, the model learns from the images the robot sent.

MODELS is a folder of versions (:mod:`gsrmr_offline.model_update`). The options and the last stdout line (the new
version's record as JSON, with ``model``: the .ply to set as the server's ``model_path``): docs/model_update.md,
"3. Update"; the exit codes: :func:`main`.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
import sys

from gsrmr_common.nerfstudio import DatasetFrame
from gsrmr_common.wire import PoseKey
from gsrmr_offline.change_confirmation import ConfirmConfig
from gsrmr_offline.deployment_survey import (
    SurveyInputError,
    composer_for_frame,
    frame_at_width,
    load_image,
    read_survey_dataset,
    route_time_s,
)
from gsrmr_offline.frame_loss import frame_loss
from gsrmr_offline.model_update import (
    UpdateConfig,
    in_use,
    update_model,
    version_paths,
    versions,
    write_version,
)
from gsrmr_offline.survey_cli import add_composition_arguments, base_composer, mount_from_file, route_from_file
from gsrmr_server.compose import to_u8
from gsrmr_splat.model import GaussianModel
from gsrmr_splat.train import TrainConfig

PROG = "gsrmr-update"
#: The live model's training width and budget (the simulator's recipe: gsrmr_sim.models, not imported here).
TRAIN_WIDTH_PX, TRAIN_BUDGET = 160, 100_000


def parser() -> argparse.ArgumentParser:
    """The command line."""
    d = UpdateConfig()
    ap = argparse.ArgumentParser(prog=PROG, formatter_class=argparse.ArgumentDefaultsHelpFormatter,
                                 description=__doc__.split("\n\n")[0].split(": ", 1)[1])
    ap.add_argument("models", type=Path, help="folder of model versions (model_vN.ply + model_vN.json)")
    ap.add_argument("--init", type=Path, default=None, metavar="MODEL.ply",
                    help="the mapping round's model, version 0 of an empty MODELS folder")
    ap.add_argument("--received", type=Path, nargs="+", required=True, metavar="DATASET",
                    help="gsrmr-dataset folders of what the server received, oldest first (frames with gsrmr_pose)")
    ap.add_argument("--mapping", type=Path, default=None, metavar="DATASET",
                    help="the mapping round's dataset: the replay buffer (none: the received frames only)")
    up = ap.add_argument_group("update")
    up.add_argument("--steps", type=int, default=d.finetune_steps, help="fine-tuning steps")
    up.add_argument("--holdout", type=int, default=d.holdout_frames, help="most recent received frames held out")
    up.add_argument("--min-holdout", type=int, default=d.min_holdout_frames,
                    help="fewer held-out frames give no verdict (refused)")
    up.add_argument("--replay", type=int, default=d.replay_frames, help="mapping frames replayed at most")
    up.add_argument("--growth", type=float, default=d.growth,
                    help="densification adds at most this share of the version in use's Gaussians")
    up.add_argument("--significance-z", type=float, default=d.significance_z,
                    help="accept when the mean held-out improvement exceeds this many standard errors")
    up.add_argument("--no-compact", action="store_true", help="do not compact the fine-tuned model")
    up.add_argument("--no-confirm", action="store_true",
                    help="train on every received pixel: a change seen in one round only (a person crossing) is "
                         "learned too (default: only changes another --received round confirms)")
    up.add_argument("--change-threshold", type=float, default=d.confirm.threshold,
                    help="a cell of a received frame is changed when its mean |image − render| exceeds this "
                         "(colour in [0, 1])")
    up.add_argument("--max-psnr-drop-db", type=float, default=d.max_psnr_drop_db, help="compaction's tolerance")
    up.add_argument("--train-width", type=int, default=TRAIN_WIDTH_PX, help="training width [px]")
    up.add_argument("--budget", type=int, default=TRAIN_BUDGET, help="at most this many Gaussians")
    up.add_argument("--seed", type=int, default=d.seed)
    add_composition_arguments(ap)
    return ap


def _frames(dataset: Path) -> list[DatasetFrame]:
    """The dataset's frames with a ``gsrmr_pose``, their images loaded (rectified pinhole frames only)."""
    posed = [f for f in read_survey_dataset(dataset) if f.pose is not None]
    if not posed:
        raise SurveyInputError(f"{dataset}: no frame with gsrmr_pose (make it with gsrmr-dataset --pose-topic)")
    return [load_image(dataset, f) for f in posed]


def mr_loss_scorer(args: argparse.Namespace):
    """Per frame: the MR loss of the key slot the live server would compose at the frame's pose key (its own
    camera, the MR content at its route time), at the robot's uplink width (``--width``)."""
    mount = mount_from_file(args.camera_mount)
    route = route_from_file(args.route_file)

    def score(model: GaussianModel, frames: list[DatasetFrame]) -> list[float]:
        base = base_composer(model, args, mount)
        out = []
        for i, frame in enumerate(frames):
            small = frame_at_width(frame, args.width)
            pose = tuple(float(v) for v in frame.pose)  # type: ignore[union-attr]
            composer = composer_for_frame(base, small.camera, pose)  # type: ignore[arg-type]
            out.append(frame_loss(composer, to_u8(small.image), PoseKey(i, *pose),
                                  content_time_s=route_time_s(route, pose), jpeg_quality=None).loss)
        return out

    return score


def run(args: argparse.Namespace, log=print) -> dict:
    """Update as ``args`` say; the record of the new version (and ``model``, the .ply to use now)."""
    if args.init is not None and not versions(args.models):
        if not args.init.is_file():
            raise SurveyInputError(f"--init {args.init} does not exist: give the mapping round's model (.ply)")
        write_version(args.models, GaussianModel.load_ply(args.init),
                      {"parent": None, "accepted": True, "reason": f"the mapping round's model ({args.init})",
                       "rounds": [], "image_slots": 0})
    parent = in_use(args.models)
    if parent is None:
        raise SurveyInputError(f"{args.models} has no accepted model version: start it with --init MODEL.ply")
    try:
        config = UpdateConfig(holdout_frames=args.holdout, min_holdout_frames=args.min_holdout,
                              replay_frames=args.replay, finetune_steps=args.steps, growth=args.growth,
                              significance_z=args.significance_z, compact=not args.no_compact,
                              max_psnr_drop_db=args.max_psnr_drop_db, confirm_changes=not args.no_confirm,
                              confirm=ConfirmConfig(threshold=args.change_threshold), seed=args.seed)
    except ValueError as err:
        raise SurveyInputError(str(err)) from err
    per_round = [_frames(d) for d in args.received]
    received = [f for frames in per_round for f in frames]
    received_rounds = [k for k, frames in enumerate(per_round) for _ in frames]
    mapping = _frames(args.mapping) if args.mapping is not None else []
    current = GaussianModel.load_ply(version_paths(args.models, parent)[0])
    train = TrainConfig(resolution=args.train_width, sh_degree=current.sh_degree, budget=args.budget,
                        background=tuple(args.background), seed=args.seed)
    result = update_model(current, received, mapping, mr_loss_scorer(args), train, config, log=log,
                          received_rounds=received_rounds)
    v = result.verdict
    record = {"parent": parent, "accepted": v.accepted, "reason": v.reason,
              "rounds": [str(d) for d in args.received], "image_slots": len(received),
              "train_frames": result.train_frames, "replay_frames": result.replay_frames,
              "superseded_frames": result.superseded_frames, "heldout_frames": result.heldout_frames,
              "heldout_loss_before": v.as_dict()["loss_before"], "heldout_loss_after": v.as_dict()["loss_after"],
              "finetune_steps": config.finetune_steps, "finetune_cpu_s": round(result.finetune_cpu_s, 2),
              "compact_cpu_s": round(result.compact_cpu_s, 2), "confirmation": result.confirmation,
              "notes": result.notes}
    version = write_version(args.models, result.model, record)
    use = version if v.accepted else parent
    return {"version": version, **record, "model": str(version_paths(args.models, use)[0])}


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``gsrmr-update``: 0 when a version was written (accepted or refused), 2 on bad input."""
    args = parser().parse_args(argv)
    try:
        summary = run(args, log=lambda line: print(line, file=sys.stderr))
    except (SurveyInputError, OSError, ValueError) as err:
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 2
    print(json.dumps(summary, allow_nan=False))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
