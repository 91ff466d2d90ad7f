"""The scheduler's seed loss map from what the robot saw (pure, no ROS): the library behind ``gsrmr-survey``.

Which frames (:func:`select_frames`), how each is scored (:func:`survey_frames`), its content time
(:func:`route_time_s`) and the map (:func:`seed_loss_map`): docs/scheduling.md, "Seeding the loss map from the mapping
round: ``gsrmr-survey``". Units: metres, radians (degrees where named ``_deg``), seconds; ``gsrmr_pose`` =
[a_m, b_m, theta_rad], ``base_link`` in ``map``; losses are the MR loss 0.8·L1 + 0.2·(1 − SSIM).
"""

from __future__ import annotations

from collections.abc import Sequence
import csv
from dataclasses import dataclass
import json
import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from gsrmr_common.camera import Camera, CameraMount, camera_to_world_from_pose
from gsrmr_common.nerfstudio import DatasetFrame, holdout_split, read_dataset
from gsrmr_common.pose2d import Pose2D
from gsrmr_common.tf_tree import planar_transform, transform_matrix
from gsrmr_common.wire import PoseKey
from gsrmr_offline.frame_loss import FrameLoss, frame_loss
from gsrmr_scheduler.loss_map import LossMap
from gsrmr_scheduler.planner.route import RoutePredictor
from gsrmr_server.compose import MRComposer, to_u8
from gsrmr_splat.initialise import resize_frames

#: What the model's training wrote beside its .ply (``gsrmr_sim.models.build_model``): the held-out split.
TRAIN_RECORD = "train.json"
#: How a surveyed frame relates to the model: held out of its training, one of its training views, or from a
#: dataset it was not trained on (``all_frames``).
HELD_OUT, TRAINING, UNSEEN = "held-out", "training", "unseen"
#: nerfstudio camera models that are a pinhole (with every distortion coefficient zero).
PINHOLE_MODELS = frozenset({"OPENCV", "PINHOLE", "SIMPLE_PINHOLE"})
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2")
#: The per-frame CSV's columns (``<out>.frames.csv``).
CSV_COLUMNS = ("file", "a_m", "b_m", "theta_rad", "split", "content_time_s", "width_px", "height_px", "loss",
               "psnr_db", "ssim", "image_loss", "sample_bias", "camera_vs_mount_m", "camera_vs_mount_deg")


class SurveyInputError(ValueError):
    """Input the survey cannot use: the message says what is wrong and how to fix it (one line)."""


@dataclass(frozen=True)
class TrainSplit:
    """The held-out split a model's ``train.json`` records: every ``holdout_every``-th frame (0 = none) and,
    when recorded, how many training and held-out views that made."""

    holdout_every: int
    train_frames: int | None = None
    heldout_frames: int | None = None
    source: str = ""


@dataclass(frozen=True)
class SelectedFrame:
    """A frame to survey: its index in the dataset, the frame (camera, image, ``gsrmr_pose``) and its split."""

    index: int
    frame: DatasetFrame
    split: str


@dataclass(frozen=True)
class Selection:
    """The frames to survey, the rule that chose them (for the summary) and the frames skipped for want of a
    ``gsrmr_pose``."""

    frames: list[SelectedFrame]
    rule: str
    without_pose: int


@dataclass(frozen=True)
class SurveyedFrame:
    """One surveyed frame: where it is (``gsrmr_pose`` in ``map``), when (MR content time [s]), the size it was
    scored at [px], its scores, and how far its camera is from the one the live server renders at the same pose
    key (pose key ∘ the configured mount: centre distance [m], rotation angle [deg])."""

    index: int
    file_path: str
    split: str
    pose: Pose2D
    content_time_s: float
    width_px: int
    height_px: int
    score: FrameLoss
    camera_vs_mount_m: float
    camera_vs_mount_deg: float


def recorded_split(model_path: str | Path) -> TrainSplit | None:
    """The held-out split ``train.json`` beside ``model_path`` records (``holdout_every`` at the top level or in
    its ``recipe``), or None without a record. SurveyInputError for a record that names no split."""
    path = Path(model_path).parent / TRAIN_RECORD
    if not path.is_file():
        return None
    try:
        info = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise SurveyInputError(f"{path} is not JSON ({err}): remove it, or repair it") from err
    recipe = info.get("recipe") if isinstance(info.get("recipe"), dict) else {}
    every = info.get("holdout_every", recipe.get("holdout_every"))
    if not isinstance(every, int) or isinstance(every, bool):
        raise SurveyInputError(f"{path} records no holdout_every: give the dataset's held-out split with "
                               f"--holdout-every N (as passed to gsrmr-train), or remove {path.name}")

    def count(key: str) -> int | None:
        value = info.get(key)
        return value if isinstance(value, int) and not isinstance(value, bool) else None

    return TrainSplit(every, count("train_frames"), count("heldout_frames"), str(path))


def has_pose(frame: DatasetFrame) -> bool:
    """Whether the frame carries a usable ``gsrmr_pose`` (three finite numbers)."""
    pose = frame.pose
    return pose is not None and len(pose) == 3 and all(isinstance(v, int | float) and math.isfinite(v)
                                                       for v in pose)


def select_frames(frames: list[DatasetFrame], *, split: TrainSplit | None, all_frames: bool = False,
                  allow_training_views: bool = False) -> Selection:
    """The frames to survey: every frame with ``all_frames`` (a lap the model was not trained on), else the
    held-out split ``split`` names — and its training views too with ``allow_training_views``. SurveyInputError when
    nothing is left to survey or the split does not fit."""
    if all_frames:
        chosen = [SelectedFrame(i, f, UNSEEN) for i, f in enumerate(frames)]
        rule = "every frame (--all-frames: a lap the model was not trained on)"
    else:
        if split is None:
            raise SurveyInputError("the model's held-out split is unknown (no train.json beside the model): give "
                                   "--holdout-every N as passed to gsrmr-train, or --all-frames with a lap the "
                                   "model was not trained on")
        train, held = holdout_split(frames, split.holdout_every)
        recorded = (split.train_frames, split.heldout_frames)
        if None not in recorded and recorded != (len(train), len(held)):
            raise SurveyInputError(
                f"the dataset's {len(frames)} frames split every {split.holdout_every} give {len(train)} training + "
                f"{len(held)} held-out views, {split.source} records {recorded[0]} + {recorded[1]}: give the "
                "dataset the model was trained on (or --all-frames with a lap it was not trained on)")
        held_ids = {id(f) for f in held}
        if allow_training_views:
            chosen = [SelectedFrame(i, f, HELD_OUT if id(f) in held_ids else TRAINING) for i, f in enumerate(frames)]
            rule = (f"every frame, {len(train)} training views included (--allow-training-views: optimistic, the "
                    f"model was fitted to them)")
        elif not held:
            raise SurveyInputError(
                f"the model held out no frame of the dataset (holdout_every {split.holdout_every}): a survey of "
                "training views is optimistic; give a second recorded lap with --all-frames, or "
                "--allow-training-views to survey the training views anyway")
        else:
            chosen = [SelectedFrame(i, f, HELD_OUT) for i, f in enumerate(frames) if id(f) in held_ids]
            rule = f"the held-out views: the last of every {split.holdout_every} frames"
    keyed = [s for s in chosen if has_pose(s.frame)]
    if not keyed:
        raise SurveyInputError(f"none of the {len(chosen)} frames to survey carries gsrmr_pose (the robot's planar "
                               "pose [a_m, b_m, theta_rad] in transforms.json), so none can be keyed in the loss map: "
                               "record the dataset with gsrmr or add gsrmr_pose to its frames")
    return Selection(keyed, rule, len(chosen) - len(keyed))


def distortion_problem(meta: dict[str, Any]) -> str | None:
    """Why a transforms.json (``meta``) does not describe rectified pinhole frames, or None."""
    model = meta.get("camera_model")
    if model is not None and model not in PINHOLE_MODELS:
        return f"camera_model {model!r} is not a pinhole"
    for where, entry in [("", meta), *((f"frame {i}: ", f) for i, f in enumerate(meta.get("frames") or []))]:
        if not isinstance(entry, dict):
            continue
        bent = {k: entry[k] for k in DISTORTION_KEYS if isinstance(entry.get(k), int | float) and entry[k] != 0}
        if bent:
            return f"{where}distortion {bent}"
    return None


def read_survey_dataset(root: str | Path) -> list[DatasetFrame]:
    """The dataset's frames (cameras, ``gsrmr_pose``, file paths) without their images (:func:`load_image` loads
    a surveyed one). SurveyInputError for a missing or unreadable dataset or frames that are not rectified."""
    path = Path(root)
    transforms = path if path.is_file() else path / "transforms.json"
    if not transforms.is_file():
        raise SurveyInputError(f"no transforms.json at {transforms}: give the mapping round's nerfstudio dataset "
                               "(its folder or its transforms.json)")
    try:
        meta = json.loads(transforms.read_text())
        frames = read_dataset(transforms, load_images=False)
    except (ValueError, OSError) as err:
        raise SurveyInputError(f"cannot read the dataset: {err}") from err
    problem = distortion_problem(meta)
    if problem:
        raise SurveyInputError(f"{transforms}: the frames are not rectified ({problem}): the server renders a "
                               "pinhole camera; rectify the frames first")
    return frames


def load_image(root: str | Path, frame: DatasetFrame) -> DatasetFrame:
    """``frame`` with its image (float32 RGB in [0, 1], as :func:`~gsrmr_common.nerfstudio.read_dataset` gives
    it); SurveyInputError when the file is missing or has another size than its camera."""
    path = Path(root)
    base = path.parent if path.is_file() else path
    bgr = cv2.imread(str(base / frame.file_path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise SurveyInputError(f"cannot read image {base / frame.file_path}: the dataset is incomplete")
    k = frame.camera.intrinsics
    if bgr.shape[:2] != (k.height, k.width):
        raise SurveyInputError(f"{base / frame.file_path} is {bgr.shape[1]}×{bgr.shape[0]}, transforms.json says "
                               f"{k.width}×{k.height}")
    image = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0
    return DatasetFrame(frame.camera, image, None, frame.pose, frame.file_path)


def frame_at_width(frame: DatasetFrame, width_px: int) -> DatasetFrame:
    """``frame`` scaled to ``width_px`` (aspect kept, height rounded, never enlarged; the trainer's resize:
    ``cv2.INTER_AREA``, intrinsics scaled)."""
    if width_px < 1:
        raise SurveyInputError(f"the render width must be ≥ 1 px, got {width_px}")
    return resize_frames([frame], min(int(width_px), frame.camera.width))[0]


def frame_mount(camera: Camera, pose: Pose2D) -> CameraMount:
    """The mount that puts ``camera`` (in ``map``) on a robot at ``pose`` (a_m, b_m, theta_rad): pose ∘ mount is
    the frame's own camera. ValueError for a camera looking straight up or down."""
    map_from_base = transform_matrix(planar_transform(*pose))
    return CameraMount.from_optical_pose(np.linalg.inv(map_from_base) @ camera.camera_to_world)


def composer_for_frame(base: MRComposer, camera: Camera, pose: Pose2D) -> MRComposer:
    """``base``'s composer (model, MR content, background, render threads) rendering at ``camera`` for pose key
    ``pose``: the frame's intrinsics and its :func:`frame_mount`."""
    return MRComposer(base.model, base.virtual, camera.intrinsics, frame_mount(camera, pose),
                      tuple(float(c) for c in base.background_rgb),  # type: ignore[arg-type]
                      render_threads=base.render_threads)


def camera_vs_mount(camera: Camera, pose: Pose2D, mount: CameraMount) -> tuple[float, float]:
    """(centre distance [m], rotation angle [deg]) between ``camera`` and pose ∘ ``mount``, the camera the live
    server renders for this pose key."""
    live = camera_to_world_from_pose(*pose, mount)
    own = camera.camera_to_world
    turn = live[:3, :3].T @ own[:3, :3]
    cos = float(np.clip((np.trace(turn) - 1.0) / 2.0, -1.0, 1.0))
    return float(np.linalg.norm(live[:3, 3] - own[:3, 3])), math.degrees(math.acos(cos))


def route_time_s(route: RoutePredictor, pose: Pose2D) -> float:
    """The content time of a frame at ``pose``: arc length from the route's start to the
    route point nearest (a_m, b_m), over the nominal speed [s]."""
    return route.nearest_s(pose[0], pose[1]) / route.speed_mps


def survey_frames(selected: Sequence[SelectedFrame], base: MRComposer, *, dataset: str | Path, width_px: int,
                  jpeg_quality: int | None, content_times_s: Sequence[float],
                  mount: CameraMount) -> list[SurveyedFrame]:
    """Score every selected frame: its image loaded from ``dataset``, scaled to
    ``width_px``, composed by ``base``'s pipeline at its own camera and content time (``content_times_s``, one per
    frame) and scored (:func:`~gsrmr_offline.frame_loss.frame_loss`); ``mount`` is the configured camera mount,
    compared with the frame's camera."""
    if len(content_times_s) != len(selected):
        raise ValueError(f"{len(content_times_s)} content times for {len(selected)} frames")
    out = []
    for sel, time_s in zip(selected, content_times_s, strict=True):
        frame = frame_at_width(load_image(dataset, sel.frame), width_px)
        pose = tuple(float(v) for v in sel.frame.pose)  # type: ignore[union-attr]
        try:
            composer = composer_for_frame(base, frame.camera, pose)  # type: ignore[arg-type]
        except ValueError as err:
            raise SurveyInputError(f"frame {sel.index} ({sel.frame.file_path}): {err}") from err
        score = frame_loss(composer, to_u8(frame.image), PoseKey(sel.index, *pose), content_time_s=float(time_s),
                           jpeg_quality=jpeg_quality)
        offset_m, turn_deg = camera_vs_mount(frame.camera, pose, mount)  # type: ignore[arg-type]
        k = frame.camera.intrinsics
        out.append(SurveyedFrame(sel.index, sel.frame.file_path, sel.split, pose,  # type: ignore[arg-type]
                                 float(time_s), k.width, k.height, score, offset_m, turn_deg))
    return out


def seed_loss_map(poses: Sequence[Sequence[float]], losses: Sequence[float], image_losses: Sequence[float] = (),
                  sample_biases: Sequence[float] = (), **settings: Any) -> LossMap:
    """A :class:`~gsrmr_scheduler.loss_map.LossMap` (``settings``: its cell size, heading bins, radius, prior,
    forgetting) holding each loss at its pose (a_m, b_m, theta_rad), in order, the mean of the finite
    ``image_losses`` as its ``image_loss`` and the mean of the finite ``sample_biases`` as its ``sample_offset``
    (None without any)."""
    lm = LossMap(**settings)
    for pose, loss in zip(poses, losses, strict=True):
        lm.add(float(pose[0]), float(pose[1]), float(pose[2]), float(loss))
    measured = [v for v in image_losses if np.isfinite(v)]
    if measured:
        lm.image_loss = float(np.mean(measured))
    biases = [v for v in sample_biases if np.isfinite(v)]
    if biases:
        lm.sample_offset = float(np.mean(biases))
    return lm


def survey_loss_map(surveyed: Sequence[SurveyedFrame], **settings: Any) -> LossMap:
    """:func:`seed_loss_map` of the surveyed frames: L at each ``gsrmr_pose``, the mean J as ``image_loss``, the
    mean sample bias as ``sample_offset``."""
    return seed_loss_map([s.pose for s in surveyed], [s.score.loss for s in surveyed],
                         [s.score.image_loss for s in surveyed], [s.score.sample_bias for s in surveyed], **settings)


def write_frames_csv(path: str | Path, surveyed: Sequence[SurveyedFrame]) -> Path:
    """Every surveyed frame as a CSV row (:data:`CSV_COLUMNS`); returns the path."""
    path = Path(path)
    with path.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(CSV_COLUMNS)
        for s in surveyed:
            q = s.score
            writer.writerow([s.file_path, *(f"{v:.6f}" for v in s.pose), s.split, f"{s.content_time_s:.3f}",
                             s.width_px, s.height_px, f"{q.loss:.6f}", f"{q.psnr_db:.3f}", f"{q.ssim:.6f}",
                             f"{q.image_loss:.6f}", f"{q.sample_bias:.6f}", f"{s.camera_vs_mount_m:.4f}",
                             f"{s.camera_vs_mount_deg:.3f}"])
    return path
