"""Experiment data per scene: round 1 → trained GS model, round 2 → per-slot GS loss L_t, channel gains.

The model is built by the one model pipeline (:func:`gsrmr_sim.models.build_model`, cached under
``cache/<scene>-<key>/`` where ``key`` hashes the scene file and the recipe :meth:`DataSettings.recipe`
makes, so a changed setting never reuses a stale model); beside it::

    round1/, model.ply, train.json      gsrmr_sim.models.build_model
    round2-T<slots>-s<seed>/            T operating slots (r_t, v_t, d_t, s_t)    gsrmr_sim.world.record_round2
    losses-T<slots>-s<seed>.npz         per slot: gs_loss, gs_psnr_db, gs_ssim    gsrmr_sim.survey.gs_losses

Channel: ``|h_t|²`` from :class:`gsrmr_server.scheduling.ChannelModel` (paper Rician model, ρ0 = −30 dB,
α = 3, K = 1, seeded by ``channel_seed``) at the robot–server distance of each round-2 slot: robot at
(a_t, b_t, 0) m in the map frame, server at the scene's ``server.position`` (x, y, z) m.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
import shutil
import time

import numpy as np

from gsrmr_server.scheduling import ChannelModel, Problem
from gsrmr_server.splatting.model import GaussianModel
from gsrmr_server.splatting.train import TrainConfig
from gsrmr_sim.models import ModelRecipe, build_model
from gsrmr_sim.world import Round2Record, Scene, load_scene, record_round2, with_resolution


@dataclass(frozen=True)
class DataSettings:
    """How one scene's data is built (image size in pixels, counts, training budget, seeds)."""

    scene: str = "sandbox"
    width: int = 160
    height: int = 120
    frames: int = 144  # H, round-1 frames
    slots: int = 288  # T, round-2 slots
    train_iterations: int = 1500
    train_seconds: float = 480.0  # wall-time cap of the GS training (whichever comes first)
    init_points: int = 20_000
    sh_degree: int = 1
    eval_every: int = 200
    holdout_every: int = 8
    seed: int = 0  # round-2 start jitter seed and trainer seed
    channel_seed: int = 1

    def recipe(self) -> ModelRecipe:
        """How this scene's model is built (recording size, frames, seed and the training schedule)."""
        iters = int(self.train_iterations)
        background = tuple(load_scene(self.scene).background)
        cfg = TrainConfig(iterations=iters, sh_degree=self.sh_degree, init_points=self.init_points, seed=self.seed,
                          densify_from=min(300, iters // 5), densify_until=(2 * iters) // 3,
                          densify_interval=max(10, min(100, iters // 20)), sh_increase_interval=max(1, iters // 4),
                          opacity_reset_interval=max(3000, iters + 1), checkpoint_every=0,
                          background=background)  # type: ignore[arg-type]
        return ModelRecipe(scene=self.scene, frames=self.frames, width=self.width, height=self.height,
                           seed=self.seed, config=cfg, time_budget_s=self.train_seconds,
                           holdout_every=self.holdout_every, eval_every=self.eval_every)


@dataclass
class SceneData:
    """Everything the experiments need about one scene (arrays indexed by slot t = 0..T−1)."""

    settings: DataSettings
    scene: Scene
    folder: Path
    model: GaussianModel
    record: Round2Record
    gs_loss: np.ndarray  # L_t (dimensionless MR loss)
    gs_psnr_db: np.ndarray
    gs_ssim: np.ndarray
    distance_m: np.ndarray
    channel_gain: np.ndarray  # |h_t|² (dimensionless)
    train: dict  # train.json content

    @property
    def background(self) -> tuple[float, float, float]:
        """GS render background colour (RGB in [0, 1])."""
        return tuple(self.scene.background)  # type: ignore[return-value]

    def problem(self, loss_threshold: float, **kwargs) -> Problem:
        """P_GS with the paper's link constants (τ 0.1 s, I 67.2 kbit, S 192 bit, B 1 MHz, σ² −60 dBm)."""
        return Problem(channel_gain=self.channel_gain, gs_loss=self.gs_loss, loss_threshold=loss_threshold,
                       slot_s=self.record.slot_s, **kwargs)


def distances_m(record: Round2Record) -> np.ndarray:
    """Robot (a_t, b_t, 0) → server distance (m) for every slot of a round-2 record."""
    poses = record.poses
    srv = np.asarray(record.server_position_m, dtype=np.float64)
    robot = np.zeros((poses.shape[0], srv.size))
    robot[:, :2] = poses[:, :2]
    return np.maximum(np.linalg.norm(robot - srv, axis=1), 1e-3)


def build_scene_data(settings: DataSettings, cache: str | Path, log: Callable[[str], None] = print) -> SceneData:
    """Build (or load from ``cache``) the model, round-2 record, L_t and channel gains of one scene."""
    scene = with_resolution(load_scene(settings.scene), settings.width, settings.height)
    built = build_model(settings.recipe(), cache=cache, log=log)
    folder, model, info = built.folder, built.model, built.info
    tag = f"T{settings.slots}-s{settings.seed}"
    r2 = folder / f"round2-{tag}"
    if not (r2 / "index.json").exists():
        if r2.exists():
            shutil.rmtree(r2)
        t0 = time.perf_counter()
        record_round2(scene, folder / f"round2-{tag}.tmp", slots=settings.slots, seed=settings.seed)
        (folder / f"round2-{tag}.tmp").replace(r2)
        log(f"{settings.scene}: round 2 recorded ({settings.slots} slots, {time.perf_counter() - t0:.1f} s)")
    record = Round2Record(r2)
    loss_path = folder / f"losses-{tag}.npz"
    if loss_path.exists():
        with np.load(loss_path) as z:
            loss, psnr_db, ssim = z["gs_loss"], z["gs_psnr_db"], z["gs_ssim"]
    else:
        from gsrmr_sim.survey import gs_losses

        t0 = time.perf_counter()
        sl = gs_losses(record, model, tuple(scene.background))
        loss = np.array([s.loss for s in sl])
        psnr_db = np.array([s.psnr_db for s in sl])
        ssim = np.array([s.ssim for s in sl])
        np.savez(folder / f"losses-{tag}.tmp.npz", gs_loss=loss, gs_psnr_db=psnr_db, gs_ssim=ssim)
        (folder / f"losses-{tag}.tmp.npz").replace(loss_path)
        log(f"{settings.scene}: L_t surveyed (mean {loss.mean():.4f}, {time.perf_counter() - t0:.1f} s)")
    dist = distances_m(record)
    gains = ChannelModel(seed=settings.channel_seed).gains(dist)
    return SceneData(settings, scene, folder, model, record, np.maximum(loss, 0.0), psnr_db, ssim, dist, gains, info)
