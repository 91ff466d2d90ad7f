"""``gsrmr-localize``: every frame of a nerfstudio dataset registered against a model (:mod:`gsrmr_splat.localize`).

Refine each frame's camera against MODEL: six degrees of freedom by default, or (``--planar``) the robot's x, y and
yaw with the camera mount fixed. Writes OUT/transforms.json (the same frames, refined) and OUT/localize.csv.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
from pathlib import Path
import shutil
import sys
import time

import cv2
import numpy as np

from gsrmr_common.camera import Camera, opencv_w2c_to_opengl_c2w
from gsrmr_common.interrupts import console_main
from gsrmr_common.nerfstudio import read_dataset, transforms_path
from gsrmr_common.pose2d import Pose2D, wrap_angle
from gsrmr_splat.localize import LocalizeConfig, register
from gsrmr_splat.model import GaussianModel, PlyFormatError

PROG = "gsrmr-localize"
CSV_COLUMNS = ("index", "file_path", "status", "dx", "dy", "dz", "rotation_deg", "loss_before", "loss_after",
               "inliers", "seconds")
NO_IMAGE = "no_image"
NO_ROBOT_POSE = "no_robot_pose"


def _planar_pose(matrix: np.ndarray) -> Pose2D:
    """(x, y, yaw) of a 4×4 pose in its parent (z, roll and pitch dropped)."""
    return Pose2D(float(matrix[0, 3]), float(matrix[1, 3]), math.atan2(matrix[1, 0], matrix[0, 0]))


def _planar_matrix(pose: Pose2D) -> np.ndarray:
    c, s = math.cos(pose.theta_rad), math.sin(pose.theta_rad)
    out = np.eye(4)
    out[:2, :2] = [[c, -s], [s, c]]
    out[:2, 3] = pose[:2]
    return out


def planar_refinement(guess: Camera, refined: Camera, robot_pose: Pose2D) -> tuple[Camera, Pose2D]:
    """The planar part of a 6-DoF refinement: the robot's refined (x, y, yaw), the camera mount (its pose in the
    robot's frame, from ``guess`` and ``robot_pose``) fixed. Returns the camera there and the robot's pose."""
    base_from_camera = np.linalg.inv(_planar_matrix(robot_pose)) @ guess.camera_to_world
    measured = _planar_pose(refined.camera_to_world @ np.linalg.inv(base_from_camera))
    pose = Pose2D(measured.x_m, measured.y_m, wrap_angle(measured.theta_rad))
    camera_to_world = _planar_matrix(pose) @ base_from_camera
    return Camera(guess.intrinsics, np.linalg.inv(camera_to_world)), pose


def _angle_deg(rotation: np.ndarray) -> float:
    return math.degrees(math.acos(max(-1.0, min(1.0, (float(np.trace(rotation)) - 1.0) / 2.0))))


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[1])
    ap.add_argument("model", help="the model (.ply, 3DGS layout), in the dataset's frame and units")
    ap.add_argument("dataset", help="a nerfstudio dataset folder (or its transforms.json)")
    ap.add_argument("--out", required=True, help="output folder: a dataset with the refined poses")
    ap.add_argument("--planar", action="store_true", help="refine the robot's x, y and yaw only (needs each "
                    "frame's gsrmr_pose); the camera mount stays as the frame's pose implies it")
    ap.add_argument("--background", default="0,0,0", help="the model's background, R,G,B in [0, 1]")
    ap.add_argument("--max-correction-m", type=float, default=LocalizeConfig.max_correction_m,
                    help="a larger correction is refused (dataset units)")
    ap.add_argument("--max-correction-deg", type=float, default=math.degrees(LocalizeConfig.max_correction_rad))
    return ap


def _copy_files(entries: list[dict], src: Path, dst: Path) -> None:
    for entry in entries:
        for key in ("file_path", "depth_file_path", "mask_path"):
            rel = entry.get(key)
            if isinstance(rel, str) and (src / rel).is_file():
                target = dst / rel
                target.parent.mkdir(parents=True, exist_ok=True)
                if target.resolve() != (src / rel).resolve():  # --out the dataset itself: nothing to copy
                    shutil.copy2(src / rel, target)


def _fail(message: str) -> int:
    print(f"{PROG}: {message}", file=sys.stderr)
    return 2


@console_main
def main(argv: list[str] | None = None) -> int:
    """Console script ``gsrmr-localize``; exit 0 when at least one frame was registered (refused frames keep their
    poses), 2 with one line on bad input."""
    args = build_parser().parse_args(argv)
    try:
        background = tuple(float(v) for v in args.background.split(","))
        if len(background) != 3:
            raise ValueError("three numbers")
    except ValueError as err:
        return _fail(f"--background {args.background!r}: {err}")
    try:
        model = GaussianModel.load_ply(args.model)
    except (OSError, PlyFormatError, ValueError) as err:
        return _fail(f"cannot load the model {args.model}: {err}")
    src_json = transforms_path(args.dataset)
    try:
        meta = json.loads(src_json.read_text())
        frames = read_dataset(src_json, load_images=False)
    except (OSError, ValueError, json.JSONDecodeError) as err:
        return _fail(f"cannot read the dataset {args.dataset}: {err}")
    config = LocalizeConfig(max_correction_m=args.max_correction_m,
                            max_correction_rad=math.radians(args.max_correction_deg))
    src = src_json.parent
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows, registered, readable = [], 0, 0
    for i, (frame, entry) in enumerate(zip(frames, meta["frames"], strict=True)):
        t0 = time.perf_counter()
        bgr = cv2.imread(str(src / entry["file_path"]), cv2.IMREAD_COLOR)
        row = {"index": i, "file_path": entry["file_path"], "seconds": 0.0}
        if bgr is None or bgr.shape[:2] != (frame.camera.height, frame.camera.width):
            rows.append({**row, "status": NO_IMAGE})
            continue
        readable += 1
        if args.planar and frame.pose is None:
            rows.append({**row, "status": NO_ROBOT_POSE})
            continue
        image = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0
        reg = register(model, image, frame.camera, config=config, background=background)
        camera = reg.camera
        if reg.accepted and args.planar:
            camera, pose = planar_refinement(frame.camera, reg.camera, Pose2D.of(frame.pose))
            entry["gsrmr_pose"] = list(pose)
        elif reg.accepted and frame.pose is not None:  # the robot's pose moves with its camera
            base = _planar_matrix(Pose2D.of(frame.pose))
            moved = camera.camera_to_world @ frame.camera.world_to_camera @ base
            entry["gsrmr_pose"] = list(_planar_pose(moved))
        if reg.accepted:
            registered += 1
            entry["transform_matrix"] = opencv_w2c_to_opengl_c2w(camera.world_to_camera).tolist()
        delta = camera.camera_to_world[:3, 3] - frame.camera.camera_to_world[:3, 3]
        turned = camera.world_to_camera[:3, :3] @ frame.camera.world_to_camera[:3, :3].T
        rows.append({**row, "status": "accepted" if reg.accepted else reg.refused,
                     "dx": f"{delta[0]:.6f}", "dy": f"{delta[1]:.6f}", "dz": f"{delta[2]:.6f}",
                     "rotation_deg": f"{_angle_deg(turned):.4f}",
                     "loss_before": f"{reg.loss_before:.6f}", "loss_after": f"{reg.loss_after:.6f}",
                     "inliers": reg.inliers, "seconds": f"{time.perf_counter() - t0:.3f}"})
    if readable == 0:
        return _fail(f"no frame of {src_json} has a readable image of its stated size")
    _copy_files(meta["frames"], src, out)
    (out / "transforms.json").write_text(json.dumps(meta, indent=2))
    with (out / "localize.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=CSV_COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    refused = len(rows) - registered
    print(f"{PROG}: {registered} of {len(rows)} frames registered, {refused} refused (kept their poses); wrote "
          f"{out / 'transforms.json'} and {out / 'localize.csv'}")
    if registered == 0:
        return _fail("no frame could be registered (localize.csv says why for each)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
