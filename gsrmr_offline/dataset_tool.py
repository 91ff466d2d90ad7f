"""``gsrmr-dataset BAG --out DIR``: a robot's recorded mapping round → a nerfstudio dataset in the ``map`` frame.

Reads a rosbag2 (MCAP or sqlite3) or ROS 1 bag with rosbags — no ROS install needed —, takes the camera's
images, its calibration and its poses (``/tf`` + ``/tf_static``, or a pose topic and the camera mount), keeps
the frames whose poses bracket their stamps, rejects blur, spaces the keyframes and writes the rectified images
(and aligned depth) with their camera→world poses as ``DIR/transforms.json``, plus ``DIR/frames.csv`` saying
what became of every image. docs/dataset_tool.md has the rules, the columns and what to record on a robot.
"""

from __future__ import annotations

import argparse
from pathlib import Path
import sys

from gsrmr_common.tf_tree import BASE_FRAME, MAP_FRAME
from gsrmr_offline.bag_dataset import BagDatasetOptions, DatasetInputError, build_dataset

PROG = "gsrmr-dataset"


def _number(kind: type, low: float, low_inclusive: bool):
    def parse(text: str):
        try:
            value = kind(text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from exc
        ok = value >= low if low_inclusive else value > low
        if not ok or value != value or value == float("inf"):
            raise argparse.ArgumentTypeError(f"expected a finite number {'≥' if low_inclusive else '>'} {low}, "
                                             f"got {text!r}")
        return value
    return parse


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows a default only where there is one and the help does not already say it."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if action.default in (None, False) or "default" in text:
            return text
        return super()._get_help_string(action)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``gsrmr-dataset``."""
    d = BagDatasetOptions(Path("."), Path("."))
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[1].replace("``", ""),
                                 formatter_class=_HelpFormatter)
    ap.add_argument("bag", type=Path, help="rosbag2 folder, .mcap or .db3 file, or ROS 1 .bag")
    ap.add_argument("--out", type=Path, required=True, metavar="DIR",
                    help="dataset folder to write (transforms.json, images/, depths/, frames.csv; an earlier run's "
                         "files are replaced)")
    src = ap.add_argument_group("topics")
    src.add_argument("--image-topic", default=None, metavar="TOPIC",
                     help="colour Image or CompressedImage topic (default: the bag's only colour image topic)")
    src.add_argument("--camera-info-topic", default=None, metavar="TOPIC",
                     help="CameraInfo topic (default: the image topic's sibling camera_info)")
    src.add_argument("--camera-info", type=Path, default=None, dest="camera_info_file", metavar="FILE",
                     help="calibration YAML (camera_calibration / camera_info_manager) instead of a CameraInfo topic")
    src.add_argument("--depth-topic", default=None, metavar="TOPIC",
                     help="depth registered to the colour camera (default: auto-detected, see docs/dataset_tool.md)")
    src.add_argument("--no-depth", action="store_true", help="write no depth even if the bag has aligned depth")
    poses = ap.add_argument_group("poses")
    poses.add_argument("--world-frame", default=MAP_FRAME, metavar="FRAME", help="frame the dataset's poses are in")
    poses.add_argument("--base-frame", default=BASE_FRAME, metavar="FRAME",
                       help="robot frame whose planar pose (a, b, θ) is written as gsrmr_pose, where it exists")
    poses.add_argument("--camera-frame", default=None, metavar="FRAME",
                       help="the images' optical frame (default: their header.frame_id)")
    poses.add_argument("--pose-topic", default=None, metavar="TOPIC",
                       help="take poses from this Odometry / PoseStamped / PoseWithCovarianceStamped topic instead of "
                            "/tf (composed with the camera mount)")
    poses.add_argument("--camera-mount", type=Path, default=None, dest="camera_mount_file", metavar="FILE",
                       help="camera mount parameter file (camera_mount.* as config/camera_mount.yaml) for a camera "
                            "the bag's TF does not place on the robot (default with --pose-topic: "
                            "config/camera_mount.yaml)")
    poses.add_argument("--max-gap-s", type=_number(float, 0.0, False), default=d.max_gap_s,
                       help="keep a frame only if pose samples at most this far apart bracket its stamp on every "
                            "moving TF edge")
    keys = ap.add_argument_group("keyframes")
    keys.add_argument("--blur-ratio", type=_number(float, 0.0, True), default=d.blur_ratio,
                      help="drop a frame whose sharpness is below this × the median of its neighbours (0: off)")
    keys.add_argument("--blur-window", type=_number(int, 1, True), default=d.blur_window,
                      help="neighbours on each side for the blur rule")
    keys.add_argument("--min-translation-m", type=_number(float, 0.0, True), default=d.min_translation_m,
                      help="keep a frame once the camera moved this far from the last kept one …")
    keys.add_argument("--min-rotation-deg", type=_number(float, 0.0, True), default=d.min_rotation_deg,
                      help="… or turned this much (both 0: keep every sharp frame)")
    keys.add_argument("--max-frames", type=_number(int, 1, True), default=None, metavar="N",
                      help="at most this many frames, evenly thinned")
    keys.add_argument("--depth-max-offset-s", type=_number(float, 0.0, True), default=d.depth_max_offset_s,
                      help="pair a frame with the depth image nearest its stamp within this")
    return ap


def options_from_args(args: argparse.Namespace) -> BagDatasetOptions:
    """The parsed command line as :class:`BagDatasetOptions`."""
    return BagDatasetOptions(
        bag=args.bag, out=args.out, image_topic=args.image_topic, camera_info_topic=args.camera_info_topic,
        camera_info_file=args.camera_info_file, depth_topic=args.depth_topic, use_depth=not args.no_depth,
        world_frame=args.world_frame, base_frame=args.base_frame, camera_frame=args.camera_frame,
        pose_topic=args.pose_topic, camera_mount_file=args.camera_mount_file, max_gap_s=args.max_gap_s,
        blur_ratio=args.blur_ratio, blur_window=args.blur_window, min_translation_m=args.min_translation_m,
        min_rotation_deg=args.min_rotation_deg, max_frames=args.max_frames,
        depth_max_offset_s=args.depth_max_offset_s)


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``gsrmr-dataset``: 0 when a dataset was written, 2 with a one-line reason on bad input."""
    args = build_parser().parse_args(argv)
    if args.depth_topic is not None and args.no_depth:
        print(f"{PROG}: --depth-topic and --no-depth contradict each other — pass one of them", file=sys.stderr)
        return 2
    try:
        report = build_dataset(options_from_args(args))
    except DatasetInputError as err:
        print(f"{PROG}: {' '.join(str(err).splitlines())}", file=sys.stderr)
        return 2
    for note in report.notes:
        print(f"{PROG}: warning: {note}", file=sys.stderr)
    print(f"{PROG}: {report.summary_line()}")
    return 0
