"""Experiment data per scene, made by the live pipeline: the live model, round 2 at the live camera, L_t and
J_t from the live slot core, the simulator's channel realisation, the poses the robot would report.

Each part, its cache file and what the paper assumes: docs/experiments.md, "Data pipeline".
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
import json
from pathlib import Path
import shutil
import time

import numpy as np

from gsrmr_common.link_model import LinkBudget
from gsrmr_scheduler.problem import Problem
from gsrmr_sim.models import LIVE_MAX_PSNR_DROP_DB, live_model, live_recipe
from gsrmr_sim.offline_server import OfflineServer
from gsrmr_sim.sim_stack import config_dir, link_budget, robot_jpeg_quality
from gsrmr_sim.survey import SURVEY_VERSION, gs_losses
from gsrmr_sim.world import Round2Record, Scene, load_scene, record_round2
from gsrmr_sim.world.kinematics import drive_route, start_pose
from gsrmr_sim.world.reported_pose import pose_errors, reported_poses
from gsrmr_splat.model import GaussianModel


@dataclass(frozen=True)
class DataSettings:
    """How one scene's data is built. ``None`` takes the live system's value (scene file, config/*.yaml)."""

    scene: str = "sandbox"
    frames: int | None = None  # H, round-1 frames (None: the scene's)
    slots: int | None = None  # T, round-2 slots (None: the scene's)
    train_iterations: int | None = None  # GS training steps (None: the scene's model.train_iterations …)
    train_seconds: float | None = None  # … or wall-time budget (None: the scene's step count, else 2000 steps)
    train_width: int | None = None  # px, the training resolution (None: the scene's, else 160; frames are
    #                                 recorded at the camera's size)
    budget: int | None = None  # max Gaussians (None: the scene's, else 100k)
    max_psnr_drop_db: float | None = LIVE_MAX_PSNR_DROP_DB  # compaction tolerance (None: the trained model)
    jpeg_quality: int | None = None  # the robot's JPEG quality (None: config/robot.yaml's)
    seed: int = 0  # round-2 start jitter seed
    channel_seed: int | None = None  # fading realisation (None: config/link.yaml's)


@dataclass
class SceneData:
    """Everything the experiments need about one scene (arrays indexed by slot t = 0..T−1)."""

    settings: DataSettings
    scene: Scene
    folder: Path
    model: GaussianModel
    record: Round2Record
    gs_loss: np.ndarray  # L_t (3DGS image loss of the key-slot composite at the true pose)
    gs_psnr_db: np.ndarray
    gs_ssim: np.ndarray
    image_loss: np.ndarray  # J_t (loss of the image-slot composite: the robot's JPEG)
    distance_m: np.ndarray  # robot–server distance (m, planar, ≥ the link's minimum)
    channel_gain: np.ndarray  # |h_t|² (dimensionless)
    reported_poses: np.ndarray  # T×3 the robot's odometry poses in map (m, m, rad)
    pose_error: dict[str, float]  # reported vs true: position (m) and heading (rad), mean and max
    server: OfflineServer  # the live slot core over this record (scores any delivery pattern)
    train: dict  # train.json content (the trained model's history)
    model_info: dict  # the model used: train.json, or the compaction's record
    link: LinkBudget
    jpeg_quality: int

    @property
    def background(self) -> tuple[float, float, float]:
        """GS render background colour (RGB in [0, 1])."""
        return tuple(self.scene.background)  # type: ignore[return-value]

    @property
    def heldout_psnr_db(self) -> float:
        """Held-out PSNR (dB) of the model used, at its training resolution."""
        return float(self.model_info.get("heldout_psnr_db", float("nan")))

    def problem(self, loss_threshold: float, **kwargs) -> Problem:
        """P_GS with the link constants (τ 0.1 s, I 67.2 kbit, S 192 bit, B 1 MHz, σ² −60 dBm) and L_t."""
        return Problem(channel_gain=self.channel_gain, gs_loss=self.gs_loss, loss_threshold=loss_threshold,
                       slot_s=self.record.slot_s, bandwidth_hz=self.link.bandwidth_hz, noise_w=self.link.noise_w,
                       **kwargs)


def channel_gains(link: LinkBudget, positions_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(distance_m, g_k) of round slots k = 0 … len−1 at the robot's true planar positions (map, m): the
    simulator's realisation (:meth:`LinkBudget.gain`)."""
    xy = np.asarray(positions_xy, np.float64).reshape(-1, 2)
    dist = np.array([link.distance_m(p) for p in xy])
    gains = np.array([link.gain(k, p) for k, p in enumerate(xy)])
    return dist, gains


def build_scene_data(settings: DataSettings, cache: str | Path, log: Callable[[str], None] = print) -> SceneData:
    """Build (or load from ``cache``) the model, round-2 record, L_t/J_t and channel gains of one scene."""
    scene = load_scene(settings.scene)
    recipe = live_recipe(settings.scene, frames=settings.frames, train_seconds=settings.train_seconds,
                         iterations=settings.train_iterations, width=settings.train_width, budget=settings.budget)
    built = live_model(recipe, cache, max_psnr_drop_db=settings.max_psnr_drop_db, log=log)
    folder, model = built.folder, built.model
    train = built.info if settings.max_psnr_drop_db is None else _json(folder / "train.json")
    slots = int(settings.slots or scene.slots)
    quality = settings.jpeg_quality or robot_jpeg_quality(str(config_dir() / "robot.yaml"))
    link = link_budget(str(config_dir() / "link.yaml"), settings.channel_seed)
    tag = f"T{slots}-s{settings.seed}"
    r2 = folder / f"round2-{tag}"
    if not (r2 / "index.json").exists():
        if r2.exists():
            shutil.rmtree(r2)
        t0 = time.perf_counter()
        tmp = folder / f"round2-{tag}.tmp"
        shutil.rmtree(tmp, ignore_errors=True)
        record_round2(scene, tmp, slots=slots, seed=settings.seed)
        tmp.replace(r2)
        log(f"{settings.scene}: round 2 recorded ({slots} slots at {scene.camera.intrinsics.width}×"
            f"{scene.camera.intrinsics.height}, {time.perf_counter() - t0:.1f} s)")
    record = Round2Record(r2)
    drive = drive_route(scene.route, slots, scene.slot_s, pose0=start_pose(scene.route, scene.route.start_jitter_m,
                                                                          settings.seed))
    if not np.allclose(drive.poses, record.poses, atol=1e-9):
        raise RuntimeError(f"{r2}: the recorded poses are not the route's drive (stale cache?)")
    reported = reported_poses(drive, scene.slot_s)
    server = OfflineServer(record, model, mr_content=scene.mr_content, background_rgb=tuple(scene.background),
                           jpeg_quality=quality, reported_poses=reported)
    loss_path = folder / f"losses-{tag}-{Path(built.ply_name).stem}-q{quality}-v{SURVEY_VERSION}.npz"
    if loss_path.exists():
        with np.load(loss_path) as z:
            loss, psnr_db, ssim, jloss = z["gs_loss"], z["gs_psnr_db"], z["gs_ssim"], z["image_loss"]
    else:
        t0 = time.perf_counter()
        sl = gs_losses(record, model, tuple(scene.background), mr_content=scene.mr_content, jpeg_quality=quality,
                       server=server)
        loss, psnr_db, ssim, jloss = (np.array([getattr(s, k) for s in sl])
                                      for k in ("loss", "psnr_db", "ssim", "image_loss"))
        tmp_path = loss_path.with_suffix(".tmp.npz")
        np.savez(tmp_path, gs_loss=loss, gs_psnr_db=psnr_db, gs_ssim=ssim, image_loss=jloss)
        tmp_path.replace(loss_path)
        log(f"{settings.scene}: L_t surveyed by the live slot core (mean {loss.mean():.4f}; image slots J_t "
            f"mean {jloss.mean():.4f} at JPEG q{quality}; {time.perf_counter() - t0:.1f} s)")
    dist, gains = channel_gains(link, record.poses[:, :2])
    return SceneData(settings, scene, folder, model, record, np.maximum(loss, 0.0), psnr_db, ssim, jloss, dist, gains,
                     reported, pose_errors(reported, record.poses), server, train, built.info, link, quality)


def _json(path: Path) -> dict:
    return json.loads(path.read_text())
