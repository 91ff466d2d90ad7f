"""Experiment data per scene: round 1 → trained GS model, round 2 → per-slot GS loss L_t, channel gains.

Everything expensive is cached under ``cache/<scene>-<key>/`` where ``key`` hashes the scene file and
the :class:`DataSettings` (so a changed setting never reuses a stale model)::

    round1/            nerfstudio dataset (H frames)            gsrmr_sim.world.record_round1
    model.ply          trained Gaussian model                    gsrmr_server.splatting.train.Trainer
    train.json         settings + Trainer history rows (iteration, elapsed_s, train_loss, heldout_psnr_db, gaussians)
    round2/            T operating slots (r_t, v_t, d_t, s_t)    gsrmr_sim.world.record_round2
    losses.npz         per slot: gs_loss, gs_psnr_db, gs_ssim    gsrmr_sim.survey.gs_losses

Channel: ``|h_t|²`` from :class:`gsrmr_server.scheduling.ChannelModel` (paper Rician model, ρ0 = −30 dB,
α = 3, K = 1, seeded by ``channel_seed``) at the robot–server distance of each round-2 slot: robot at
(a_t, b_t, 0) m in the map frame, server at the scene's ``server.position`` (x, y, z) m.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass
import hashlib
import json
from pathlib import Path
import shutil
import time

import numpy as np

from gsrmr_server.scheduling import ChannelModel, Problem
from gsrmr_server.splatting.model import GaussianModel
from gsrmr_sim.world import Round2Record, Scene, load_scene, record_round1, record_round2, with_resolution
from gsrmr_sim.world.scene import resolve_scene_path

#: Bump when the cache layout or the way a cached artefact is computed changes.
CACHE_VERSION = 1


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

    def key(self) -> str:
        """Cache key: hash of the scene file text, these settings (but the channel seed, which only changes
        the gains computed after loading) and :data:`CACHE_VERSION`."""
        text = resolve_scene_path(self.scene).read_text()
        fields = {k: v for k, v in asdict(self).items() if k != "channel_seed"}
        blob = text + json.dumps(fields, sort_keys=True) + f"v{CACHE_VERSION}"
        return hashlib.sha256(blob.encode()).hexdigest()[:12]


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


def history_rows(history: list) -> list[dict]:
    """Trainer history as dicts: iteration, elapsed_s (wall), cpu_s (None if not recorded), train_loss,
    heldout_psnr_db, gaussians. Accepts ``HistoryRow`` named tuples (iteration, wall_s, cpu_s, loss,
    test_psnr_db, num_gaussians) and the older 5-tuples (iteration, wall s, loss, PSNR, count)."""
    rows = []
    for h in history:
        if hasattr(h, "_fields"):
            rows.append({"iteration": int(h.iteration), "elapsed_s": float(h.wall_s), "cpu_s": float(h.cpu_s),
                         "train_loss": float(h.loss), "heldout_psnr_db": float(h.test_psnr_db),
                         "gaussians": int(h.num_gaussians)})
        elif len(h) == 5:
            rows.append({"iteration": int(h[0]), "elapsed_s": float(h[1]), "cpu_s": None, "train_loss": float(h[2]),
                         "heldout_psnr_db": float(h[3]), "gaussians": int(h[4])})
        else:
            raise ValueError(f"unknown Trainer history row {h!r}")
    return rows


def _train(settings: DataSettings, dataset: Path, background: tuple[float, float, float],
           log: Callable[[str], None]) -> tuple[GaussianModel, dict]:
    from gsrmr_server.splatting.train import TrainConfig, Trainer

    iters = int(settings.train_iterations)
    cfg = TrainConfig(iterations=iters, sh_degree=settings.sh_degree, init_points=settings.init_points,
                      seed=settings.seed, densify_from=min(300, iters // 5), densify_until=(2 * iters) // 3,
                      densify_interval=max(10, min(100, iters // 20)), sh_increase_interval=max(1, iters // 4),
                      opacity_reset_interval=max(3000, iters + 1), checkpoint_every=0,
                      background=background)
    t0 = time.perf_counter()
    trainer = Trainer.from_dataset(dataset, cfg, holdout_every=settings.holdout_every)
    initial_psnr = trainer.evaluate()
    model = trainer.train(eval_every=settings.eval_every, progress=False, time_budget_s=settings.train_seconds)
    wall = time.perf_counter() - t0
    hist = history_rows(trainer.state.history)
    info = {"settings": asdict(settings), "config": cfg.to_dict(), "initial_heldout_psnr_db": initial_psnr,
            "history": hist, "wall_s": wall, "train_frames": len(trainer.frames),
            "heldout_frames": len(trainer.test_frames), "gaussians": model.num_gaussians}
    log(f"{settings.scene}: GS trained, {model.num_gaussians} Gaussians, {hist[-1]['iteration']} iterations, "
        f"held-out PSNR {hist[-1]['heldout_psnr_db']:.2f} dB, {wall:.0f} s")
    return model, info


def build_scene_data(settings: DataSettings, cache: str | Path, log: Callable[[str], None] = print) -> SceneData:
    """Build (or load from ``cache``) the model, round-2 record, L_t and channel gains of one scene."""
    scene = with_resolution(load_scene(settings.scene), settings.width, settings.height)
    folder = Path(cache) / f"{settings.scene}-{settings.key()}"
    folder.mkdir(parents=True, exist_ok=True)
    model_path, train_path = folder / "model.ply", folder / "train.json"
    if model_path.exists() and train_path.exists():
        model, info = GaussianModel.load_ply(model_path), json.loads(train_path.read_text())
        log(f"{settings.scene}: cached GS model {model_path}")
    else:
        r1 = folder / "round1"
        if r1.exists():
            shutil.rmtree(r1)
        t0 = time.perf_counter()
        dataset = record_round1(scene, r1, frames=settings.frames, seed=settings.seed)
        log(f"{settings.scene}: round 1 recorded ({settings.frames} frames, {time.perf_counter() - t0:.1f} s)")
        model, info = _train(settings, dataset, tuple(scene.background), log)
        model.save_ply(folder / "model.tmp.ply")
        (folder / "model.tmp.ply").replace(model_path)
        train_path.write_text(json.dumps(info, indent=1))
    r2 = folder / "round2"
    if not (r2 / "index.json").exists():
        if r2.exists():
            shutil.rmtree(r2)
        t0 = time.perf_counter()
        record_round2(scene, folder / "round2.tmp", slots=settings.slots, seed=settings.seed)
        (folder / "round2.tmp").replace(r2)
        log(f"{settings.scene}: round 2 recorded ({settings.slots} slots, {time.perf_counter() - t0:.1f} s)")
    record = Round2Record(r2)
    loss_path = folder / "losses.npz"
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
        np.savez(folder / "losses.tmp.npz", gs_loss=loss, gs_psnr_db=psnr_db, gs_ssim=ssim)
        (folder / "losses.tmp.npz").replace(loss_path)
        log(f"{settings.scene}: L_t surveyed (mean {loss.mean():.4f}, {time.perf_counter() - t0:.1f} s)")
    dist = distances_m(record)
    gains = ChannelModel(seed=settings.channel_seed).gains(dist)
    return SceneData(settings, scene, folder, model, record, np.maximum(loss, 0.0), psnr_db, ssim, dist, gains, info)
