"""The real robot's path end to end, as a user with hardware runs it, on a bag the simulator records as a LIMO does.

``write_robot_bag`` (96×72, 24 images: 2 before and 2 after the odometry's span, 2 motion-blurred, drift off, JPEG,
plumb_bob distortion, image stamps between the 50 Hz TF samples) → ``gsrmr-dataset`` (keyframing off) → every kept
frame's camera and planar pose against ``truth.json``, the dropped frames and their reasons in ``frames.csv``, a
second run byte for byte → ``gsrmr-train`` (a tiny model) → ``gsrmr-survey`` on its held-out frames → the map loaded
the way the scheduler loads its ``loss_map_file`` and planned with. No live round here: that is
``bench/acceptance/demo.py`` with ``gsrmr-demo --model … --loss-map …`` (docs/hardware.md).
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest

from gsrmr_common.nerfstudio import holdout_split, read_dataset
from gsrmr_offline import dataset_tool, survey_cli
from gsrmr_scheduler.loss_map import LossMap
from gsrmr_scheduler.planner import OnlinePlanner
from gsrmr_scheduler.scheduler_params import SchedulerParameters
from gsrmr_sim.robot_bag import RobotBagRecipe, load_truth, write_robot_bag
from gsrmr_splat.model import GaussianModel
from gsrmr_splat.train_cli import train_main

# 5.5 s into the route: the robot drives into the first corner, so the poses turn as well as move
RECIPE = RobotBagRecipe(frames=24, width_px=96, height_px=72, drive_start_s=5.5, drift=False, blurred_frames=2,
                        frames_outside=2, seed=0)
KEYFRAMING_OFF = ("--min-translation-m", "0", "--min-rotation-deg", "0")
HOLDOUT_EVERY = 4
#: The server's background_rgb (config/server.yaml), which gsrmr-survey composes with: the model is trained against it.
SERVER_BACKGROUND = "0.5,0.55,0.6"
POSITION_TOLERANCE_M, ROTATION_TOLERANCE_DEG = 0.01, 0.5


def rotation_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle [deg] of the rotation between two 3×3 rotations."""
    cos = (np.trace(a.T @ b) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, cos))))


def tree_bytes(root: Path) -> dict[str, bytes]:
    """Every file under ``root`` (relative path → bytes)."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def pose_of(row: dict[str, str]) -> tuple[float, float, float]:
    """The planar pose (a_m, b_m, theta_rad) of a survey CSV row."""
    return float(row["a_m"]), float(row["b_m"]), float(row["theta_rad"])


def frames_csv(dataset: Path) -> list[dict[str, str]]:
    with open(dataset / "frames.csv", newline="") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> dict:
    """The bag, its dataset (after two runs: the second's bytes compared with the first's), the model and the map."""
    root = tmp_path_factory.mktemp("robot_path")
    bag = write_robot_bag(root / "round1", RECIPE)
    dataset = root / "dataset"
    assert dataset_tool.main([str(bag.bag_path), "--out", str(dataset), *KEYFRAMING_OFF]) == 0
    first = tree_bytes(dataset)
    assert dataset_tool.main([str(bag.bag_path), "--out", str(dataset), *KEYFRAMING_OFF]) == 0
    model = root / "model.ply"
    assert train_main([str(dataset), "--out", str(model), "--iterations", "150", "--resolution", "48",
                       "--sh-degree", "0", "--init-points", "1500", "--budget", "4000", "--background",
                       SERVER_BACKGROUND, "--holdout-every", str(HOLDOUT_EVERY), "--seed", "0", "--no-progress"]) == 0
    # an empty model (one faint Gaussian far outside the room): what the survey gives for the background alone
    empty = root / "empty.ply"
    GaussianModel.from_points(np.full((1, 3), 100.0), np.full((1, 3), 0.5), opacities=0.01).save_ply(empty)
    maps = {}
    for name, path in (("trained", model), ("empty", empty)):
        maps[name] = root / f"loss_map_{name}.json"
        assert survey_cli.main([str(path), str(dataset), "--out", str(maps[name]), "--holdout-every",
                                str(HOLDOUT_EVERY), "--render-threads", "1"]) == 0
    return {"bag": bag, "truth": load_truth(root / "round1"), "dataset": dataset, "first_run": first,
            "second_run": tree_bytes(dataset), "model": model, "loss_map": maps["trained"],
            "empty_loss_map": maps["empty"]}


def test_kept_frames_are_where_truth_says_and_the_rest_dropped_with_reasons(site):
    truth = site["truth"]
    rows = frames_csv(site["dataset"])
    status = {int(r["index"]): r["status"] for r in rows}
    outside = {f.index for f in truth.frames if not f.in_pose_range}
    blurred = {f.index for f in truth.frames if f.blurred}
    assert len(outside) == 2 * RECIPE.frames_outside and len(blurred) == RECIPE.blurred_frames
    assert {i for i, s in status.items() if s == "out_of_range"} == outside
    assert {i for i, s in status.items() if s == "blur"} == blurred
    kept = sorted(i for i, s in status.items() if s == "kept")
    assert kept == sorted(set(range(RECIPE.frames)) - outside - blurred)  # keyframing off: every other frame

    frames = read_dataset(site["dataset"])
    assert len(frames) == len(kept)
    by_index = {int(r["index"]): r for r in rows}
    worst_m = worst_deg = worst_planar_m = worst_yaw_deg = 0.0
    for frame, index in zip(frames, kept, strict=True):
        true = truth.frames[index]
        assert frame.file_path == by_index[index]["file_path"]
        c2w = frame.camera.camera_to_world  # OpenCV axes, map
        worst_m = max(worst_m, float(np.linalg.norm(c2w[:3, 3] - true.map_from_optical[:3, 3])))
        worst_deg = max(worst_deg, rotation_deg(c2w[:3, :3], true.map_from_optical[:3, :3]))
        a, b, theta = frame.pose
        worst_planar_m = max(worst_planar_m, math.hypot(a - true.pose[0], b - true.pose[1]))
        worst_yaw_deg = max(worst_yaw_deg, abs(math.degrees(math.remainder(theta - true.pose[2], math.tau))))
        assert (frame.camera.intrinsics.width, frame.camera.intrinsics.height) == (RECIPE.width_px, RECIPE.height_px)
    assert worst_m < POSITION_TOLERANCE_M and worst_deg < ROTATION_TOLERANCE_DEG, (worst_m, worst_deg)
    assert worst_planar_m < POSITION_TOLERANCE_M and worst_yaw_deg < ROTATION_TOLERANCE_DEG
    # the rectified camera is the calibration's P, the one the bag's truth records
    k = frames[0].camera.intrinsics
    assert (k.fx, k.fy, k.cx, k.cy) == pytest.approx((truth.rectified.fx, truth.rectified.fy, truth.rectified.cx,
                                                      truth.rectified.cy), abs=1e-9)


def test_a_second_run_writes_the_same_bytes(site):
    first, second = site["first_run"], site["second_run"]
    assert "transforms.json" in first and "frames.csv" in first
    assert sum(name.startswith("images/") for name in first) == len(read_dataset(site["dataset"], load_images=False))
    assert list(first) == list(second)
    assert [name for name in first if first[name] != second[name]] == []


def test_the_survey_map_is_what_the_scheduler_plans_with(site):
    lm = LossMap.load(site["loss_map"])  # what scheduler_node does with its loss_map_file
    params = SchedulerParameters()
    config = params.planner_config(lm)
    assert config.image_slot_loss == lm.image_loss and 0.0 < lm.image_loss < 0.2
    with open(f"{site['loss_map']}.frames.csv", newline="") as f:
        surveyed = list(csv.DictReader(f))
    _train, held_out = holdout_split(read_dataset(site["dataset"], load_images=False), HOLDOUT_EVERY)
    assert sorted(r["file"] for r in surveyed) == sorted(h.file_path for h in held_out)  # held-out views only
    planner = OnlinePlanner(config, survey_cli.route_from_file(survey_cli.default_config_path("sandbox", "routes")),
                            lm, params.link)
    cell_losses: dict[tuple[int, int, int], list[float]] = {}
    for row in surveyed:
        cell_losses.setdefault(lm.key(*pose_of(row)), []).append(float(row["loss"]))
    for row in surveyed:  # a frame alone in its cell is predicted as surveyed; frames sharing one, their mean
        members = cell_losses[lm.key(*pose_of(row))]
        predicted = planner.loss_map.predict(*pose_of(row))
        if len(members) == 1:
            assert predicted == pytest.approx(members[0], abs=1e-6)
        else:
            assert min(members) - 1e-6 <= predicted <= max(members) + 1e-6
    assert len(lm.cells) == len(cell_losses)
    losses = np.array([float(r["loss"]) for r in surveyed])
    assert np.all((losses > 0.0) & (losses < 1.0))
    # the trained model's held-out views lose far less than the background alone does
    with open(f"{site['empty_loss_map']}.frames.csv", newline="") as f:
        empty = {r["file"]: float(r["loss"]) for r in csv.DictReader(f)}
    for row in surveyed:
        assert float(row["loss"]) < 0.75 * empty[row["file"]], (row["file"], row["loss"], empty[row["file"]])
    assert GaussianModel.load_ply(site["model"]).num_gaussians <= 4000
