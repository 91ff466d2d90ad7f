"""``gsrmr-survey MODEL DATASET --out loss_map.json``: the scheduler's seed loss map from the mapping round.

What it surveys, how, and what it writes: docs/scheduling.md, "Seeding the loss map from the mapping round:
``gsrmr-survey``"; its defaults come from the package's parameter files, as the nodes load them (``--help``).
"""

from __future__ import annotations

import argparse
from dataclasses import fields
from pathlib import Path
import sys
from typing import Any

import numpy as np
import yaml

from gsrmr_common.camera import CameraMount
from gsrmr_common.config_files import resolve_config
from gsrmr_offline.deployment_survey import (
    TRAINING,
    Selection,
    SurveyedFrame,
    SurveyInputError,
    TrainSplit,
    read_survey_dataset,
    recorded_split,
    route_time_s,
    select_frames,
    survey_frames,
    survey_loss_map,
    write_frames_csv,
)
from gsrmr_scheduler.loss_map import LossMap
from gsrmr_scheduler.planner.route import RoutePredictor
from gsrmr_scheduler.scheduler_params import SchedulerParameters, route_waypoints
from gsrmr_server.compose import MRComposer
from gsrmr_server.server_params import ServerParameters
from gsrmr_server.slot_core import WARM_UP_INTRINSICS, build_composer
from gsrmr_splat.cli import rgb_arg
from gsrmr_splat.model import GaussianModel

PROG = "gsrmr-survey"
#: The robot's defaults where ``config/robot.yaml`` cannot be read (the robot side is not imported here).
ROBOT_JPEG_QUALITY, ROBOT_UPLINK_WIDTH_PX = 80, 320


def file_parameters(path: str | Path) -> dict[str, Any]:
    """The ``ros__parameters`` of every section of a node parameter file (``/**``-keyed YAML), merged."""
    data = yaml.safe_load(Path(path).read_text()) or {}
    if not isinstance(data, dict):
        raise ValueError(f"{path}: not a ROS parameter file (a mapping of node keys)")
    out: dict[str, Any] = {}
    for section in data.values():
        out.update((section or {}).get("ros__parameters", {}) if isinstance(section, dict) else {})
    return out


def config_parameters(name: str) -> dict[str, Any]:
    """``config/<name>.yaml``'s parameters (source tree, ament share or ``sys.prefix``); {} where none is found."""
    try:
        return file_parameters(resolve_config(name, "", f"{name} parameters"))
    except (OSError, ValueError, yaml.YAMLError):
        return {}


def default_config_path(name: str, kind: str = "") -> str:
    """The path of the package's ``config/<kind>/<name>.yaml`` ('' where it is not installed)."""
    try:
        return str(resolve_config(name, kind, name))
    except FileNotFoundError:
        return ""


def mount_from_file(path: str | Path) -> CameraMount:
    """The ``camera_mount.*`` parameters of a parameter file (``config/camera_mount.yaml``) as a mount."""
    names = {f.name for f in fields(CameraMount)}
    values = {k.removeprefix("camera_mount."): v for k, v in file_parameters(path).items()
              if k.startswith("camera_mount.")}
    unknown = sorted(set(values) - names)
    if unknown:
        raise ValueError(f"{path}: unknown camera_mount parameters {unknown}")
    return CameraMount(**{k: float(v) for k, v in values.items()})


def route_from_file(path: str | Path) -> RoutePredictor:
    """The route of a scheduler route file (``route_waypoints_m``, ``route_speed_mps``)."""
    params = file_parameters(path)
    if "route_waypoints_m" not in params:
        raise ValueError(f"{path}: no route_waypoints_m (a route file is config/routes/*.yaml)")
    speed = float(params.get("route_speed_mps", SchedulerParameters().route_speed_mps))
    return RoutePredictor(route_waypoints(params["route_waypoints_m"]), speed)


def add_composition_arguments(ap: argparse.ArgumentParser) -> None:
    """The "composition, as the server and the robot do it" options (MR content, background, JPEG quality, width,
    route, camera mount, render threads), their defaults from the package's parameter files."""
    server, robot = config_parameters("server"), config_parameters("robot")
    s = ServerParameters()
    comp = ap.add_argument_group("composition, as the server and the robot do it")
    comp.add_argument("--mr-content", default=str(server.get("mr_content", s.mr_content)),
                      help="MR content: a name in config/mr or a YAML path (the server's mr_content)")
    comp.add_argument("--background", type=rgb_arg, default=tuple(server.get("background_rgb", s.background_rgb)),
                      help="r,g,b in [0, 1] where the model has no density (the server's background_rgb)")
    comp.add_argument("--jpeg-quality", type=int, default=int(robot.get("jpeg_quality", ROBOT_JPEG_QUALITY)),
                      help="the robot's JPEG quality (image_loss)")
    comp.add_argument("--width", type=int, default=int(robot.get("uplink_width_px", ROBOT_UPLINK_WIDTH_PX)),
                      help="render width [px]: the robot's uplink width (aspect kept, never enlarged)")
    comp.add_argument("--route-file", default=default_config_path("sandbox", "routes"),
                      help="the route the content time follows (the scheduler's route file)")
    comp.add_argument("--camera-mount", default=default_config_path("camera_mount"),
                      help="the mount the server renders with: the CSV and summary compare each frame's camera "
                           "with gsrmr_pose ∘ mount")
    comp.add_argument("--render-threads", type=int, default=0, help="GS render threads (0 = every core)")


def base_composer(model: GaussianModel, args: argparse.Namespace, mount: CameraMount) -> MRComposer:
    """The server's composer for ``model`` as the composition options say (rendering at each frame's own camera is
    :func:`~gsrmr_offline.deployment_survey.composer_for_frame`'s)."""
    return build_composer(model, WARM_UP_INTRINSICS, mr_content=args.mr_content, mount=mount,
                          background_rgb=tuple(args.background), render_threads=args.render_threads or None,
                          warm_up=False)


def parser() -> argparse.ArgumentParser:
    """The command line (defaults read from the package's parameter files)."""
    scheduler = config_parameters("scheduler")
    lm = LossMap()
    ap = argparse.ArgumentParser(
        prog=PROG, formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        description="Seed the scheduler's loss map from the mapping round: score the dataset's views the model was "
                    "not trained on as the live server composes them (GS loss L keyed by gsrmr_pose, image_loss of "
                    "the robot's JPEG) and write the LossMap JSON for the scheduler's loss_map_file.")
    ap.add_argument("model", help="trained 3DGS .ply")
    ap.add_argument("dataset", help="the robot's frames: nerfstudio dataset folder or its transforms.json, frames "
                    "with gsrmr_pose")
    ap.add_argument("--out", required=True, help="output loss map JSON (the CSV goes to OUT.frames.csv)")
    which = ap.add_argument_group("which frames")
    which.add_argument("--holdout-every", type=int, default=None,
                       help="the held-out split of gsrmr-train --holdout-every N, where no train.json beside MODEL "
                            "records it")
    which.add_argument("--all-frames", action="store_true",
                       help="survey every frame: DATASET is a lap the model was not trained on")
    which.add_argument("--allow-training-views", action="store_true",
                       help="survey the training views too (optimistic: the model was fitted to them)")
    add_composition_arguments(ap)
    grid = ap.add_argument_group("loss map (LossMap; the prior is the scheduler's loss_prior)")
    grid.add_argument("--cell-m", type=float, default=lm.cell_m, help="grid cell size [m]")
    grid.add_argument("--heading-bins", type=int, default=lm.heading_bins, help="heading sectors")
    grid.add_argument("--radius-m", type=float, default=lm.radius_m, help="neighbour radius of a prediction [m]")
    grid.add_argument("--forgetting", type=float, default=lm.forgetting, help="weight of a cell's newest sample")
    grid.add_argument("--prior", type=float, default=float(scheduler.get("loss_prior", lm.prior)),
                      help="loss predicted where the map knows nothing")
    return ap


def train_split(args: argparse.Namespace) -> TrainSplit | None:
    """The held-out split: the model's record, else ``--holdout-every``; SurveyInputError when they disagree."""
    recorded = recorded_split(args.model)
    if recorded is None:
        return None if args.holdout_every is None else TrainSplit(args.holdout_every, source="--holdout-every")
    if args.holdout_every is not None and args.holdout_every != recorded.holdout_every:
        raise SurveyInputError(f"{recorded.source} records holdout_every {recorded.holdout_every}, --holdout-every "
                               f"says {args.holdout_every}: drop --holdout-every")
    return recorded


def summary_line(selection: Selection, surveyed: list[SurveyedFrame], loss_map: LossMap, args: argparse.Namespace,
                 csv_path: Path) -> str:
    """The one-line summary: frames, cells, loss statistics, image_loss and sample_offset, the cameras' offset, the
    files."""
    loss = np.array([s.score.loss for s in surveyed])
    size = f"{surveyed[0].width_px}×{surveyed[0].height_px}"
    image = "not measured" if loss_map.image_loss is None else f"{loss_map.image_loss:.4f} (JPEG q{args.jpeg_quality})"
    if loss_map.sample_offset is not None:
        image += f", sample_offset {loss_map.sample_offset:+.4f}"
    offset_m = max(s.camera_vs_mount_m for s in surveyed)
    turn_deg = max(s.camera_vs_mount_deg for s in surveyed)
    return (f"{PROG}: {len(surveyed)} frames surveyed ({selection.rule}; {selection.without_pose} without gsrmr_pose "
            f"skipped) at {size}, {len(loss_map.cells)} cells, loss mean {loss.mean():.4f} median "
            f"{np.median(loss):.4f} max {loss.max():.4f}, image_loss {image}; cameras vs gsrmr_pose∘mount up to "
            f"{offset_m:.3f} m, {turn_deg:.1f}°; wrote {args.out} and {csv_path}")


def run(args: argparse.Namespace) -> tuple[str, int]:
    """Survey as ``args`` say, write the map and the CSV: (the summary line, how many training views were
    surveyed). SurveyInputError for bad input."""
    model_path, out = Path(args.model), Path(args.out)
    if not model_path.is_file():
        raise SurveyInputError(f"model {model_path} does not exist: give the trained 3DGS .ply (gsrmr-train --out)")
    if not out.parent.is_dir():
        raise SurveyInputError(f"--out {out}: folder {out.parent} does not exist: create it first")
    if not 1 <= args.jpeg_quality <= 100:
        raise SurveyInputError(f"--jpeg-quality {args.jpeg_quality} is not in 1..100: give the robot's jpeg_quality")
    frames = read_survey_dataset(args.dataset)
    selection = select_frames(frames, split=None if args.all_frames else train_split(args),
                              all_frames=args.all_frames, allow_training_views=args.allow_training_views)
    try:
        route = route_from_file(args.route_file)
        mount = mount_from_file(args.camera_mount)
        settings = {"cell_m": args.cell_m, "heading_bins": args.heading_bins, "radius_m": args.radius_m,
                    "prior": args.prior, "forgetting": args.forgetting}
        LossMap(**settings)  # refuses bad settings before anything is rendered
        model = GaussianModel.load_ply(model_path)
        base = base_composer(model, args, mount)
    except (OSError, ValueError, yaml.YAMLError) as err:
        raise SurveyInputError(str(err)) from err
    times = [route_time_s(route, s.frame.pose) for s in selection.frames]  # type: ignore[arg-type]
    surveyed = survey_frames(selection.frames, base, dataset=args.dataset, width_px=args.width,
                             jpeg_quality=args.jpeg_quality, content_times_s=times, mount=mount)
    loss_map = survey_loss_map(surveyed, **settings)
    loss_map.save(out)
    csv_path = write_frames_csv(Path(f"{out}.frames.csv"), surveyed)
    return summary_line(selection, surveyed, loss_map, args, csv_path), sum(s.split == TRAINING for s in surveyed)


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``gsrmr-survey``: 0 on success, 2 on bad input (one line on stderr)."""
    args = parser().parse_args(argv)
    try:
        line, training_views = run(args)
    except SurveyInputError as err:
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 2
    if training_views:
        print(f"{PROG}: warning: {training_views} training views surveyed: their losses are optimistic (the model "
              "was fitted to them)", file=sys.stderr)
    print(line)
    return 0
