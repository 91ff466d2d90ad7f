"""``gsrmr-align``: bring a Gaussian-splatting model trained elsewhere into the robot's ``map`` frame.

Pairs the model's camera poses (a nerfstudio, COLMAP or 3DGS file) with the map-frame poses of the same images in a
gsrmr nerfstudio dataset by image name, fits x_map = s·R·x_model + t to the camera centres (RANSAC + Umeyama) and writes
the transformed model. Formats and report: docs/splatting.md, "Aligning a model trained elsewhere".
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
import sys

from gsrmr_splat.align import (
    DEFAULT_THRESHOLD_FRACTION,
    MIN_RANDOM_SAMPLES,
    align_poses,
    transform_model,
)
from gsrmr_splat.external_poses import read_map_dataset, read_model_poses, shift_frame_numbers
from gsrmr_splat.model import GaussianModel

PROG = "gsrmr-align"
# Camera orientations disagreeing by more than this (RMS over the inliers) after the fit earn a warning: the
# centres fit, but one side's camera axes are probably in another convention.
ROTATION_WARNING_DEG = 5.0
# Map cameras whose second principal spread is below this fraction of the first are nearly on one line: the roll
# about it rests on little.
SPREAD_WARNING_RATIO = 0.05


def _positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}") from exc
    if not 0.0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"expected a finite number > 0, got {text!r}")
    return value


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``gsrmr-align``."""
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[1],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("model", help="3DGS .ply trained elsewhere (in the frame of --model-poses)")
    ap.add_argument("--model-poses", required=True,
                    help="the model's camera poses: transforms.json, ns-export cameras JSON, 3DGS cameras.json "
                         "or COLMAP images.txt (format from the name and content)")
    ap.add_argument("--dataparser-transforms", default=None,
                    help="nerfstudio dataparser_transforms.json of the run (splatfacto): carries the "
                         "transforms.json poses into the frame the Gaussians live in")
    ap.add_argument("--map-dataset", required=True, help="gsrmr nerfstudio dataset (folder) with the map-frame poses")
    ap.add_argument("--out", required=True, help="output OUT.ply, the model in map")
    ap.add_argument("--report", default=None, help="write the alignment report (JSON) here")
    ap.add_argument("--threshold-m", type=_positive, default=None,
                    help="RANSAC inlier distance in map metres (default: "
                         f"{100 * DEFAULT_THRESHOLD_FRACTION:.0f}%% of the map cameras' median distance from their "
                         "median)")
    ap.add_argument("--rotation-threshold-deg", type=_positive, default=None,
                    help="also require inliers' camera orientations to agree within this angle")
    ap.add_argument("--iterations", type=int, default=2000,
                    help=f"RANSAC samples at most (stops earlier, after at least {MIN_RANDOM_SAMPLES}, once "
                         "confident)")
    ap.add_argument("--min-inliers", type=int, default=None, help="default: a majority of the pairs")
    ap.add_argument("--model-frame-offset", type=int, default=0,
                    help="add this to the trailing number of every model-side image name before pairing "
                         "(-1 for images renumbered from frame_00001 by ns-process-data)")
    ap.add_argument("--seed", type=int, default=0, help="RANSAC seed (the result is deterministic for a seed)")
    return ap


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``gsrmr-align``: 0 on success, 2 with a one-line reason on bad input."""
    args = build_parser().parse_args(argv)
    try:
        model_poses = read_model_poses(args.model_poses, args.dataparser_transforms)
        if args.model_frame_offset:
            model_poses = shift_frame_numbers(model_poses, args.model_frame_offset)
        map_poses = read_map_dataset(args.map_dataset)
        report = align_poses(model_poses, map_poses, threshold_m=args.threshold_m, iterations=args.iterations,
                             seed=args.seed, min_inliers=args.min_inliers,
                             rotation_threshold_deg=args.rotation_threshold_deg)
        model = GaussianModel.load_ply(args.model)
    except (ValueError, FileNotFoundError) as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 2
    aligned = transform_model(model, report.similarity)
    aligned.save_ply(args.out)
    if args.report:
        Path(args.report).parent.mkdir(parents=True, exist_ok=True)
        Path(args.report).write_text(json.dumps({"model": str(args.model), "model_poses": str(args.model_poses),
                                                 "map_dataset": str(args.map_dataset), "out": str(args.out),
                                                 **report.to_dict()}, indent=1))
    if report.rms_rotation_error_deg > ROTATION_WARNING_DEG:
        print(f"{PROG}: warning: the camera orientations disagree by {report.rms_rotation_error_deg:.1f}° RMS "
              "although the centres fit: is the pose file in the axes its format says (OpenGL for nerfstudio, "
              "OpenCV for COLMAP/3DGS)?", file=sys.stderr)
    if report.spread_ratio < SPREAD_WARNING_RATIO:
        print(f"{PROG}: warning: the map cameras are nearly on one line (spread ratio {report.spread_ratio:.3f}): "
              "the rotation about it is poorly determined by the centres; drive a wider route", file=sys.stderr)
    print(f"{PROG}: {report.summary()}; wrote {args.out} ({aligned.num_gaussians} Gaussians)")
    return 0
