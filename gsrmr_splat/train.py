"""The training loop (:class:`Trainer`): nerfstudio dataset → Gaussian model (.ply), the 3DGS recipe on the CPU. Its
pieces live beside it, split as gsplat splits its strategy from its ops: :mod:`~gsrmr_splat.losses`,
:mod:`~gsrmr_splat.initialise`, :mod:`~gsrmr_splat.optim`, :mod:`~gsrmr_splat.strategy`,
:mod:`~gsrmr_splat.contribution`, :mod:`~gsrmr_splat.camera_opt`, the step engines :mod:`~gsrmr_splat.fused` and
:mod:`~gsrmr_splat.diffrender`. Settings: :class:`~gsrmr_splat.train_config.TrainConfig`; the recipe: docs/splatting.md,
"Training".
"""

from __future__ import annotations

import math
from pathlib import Path
import time
from typing import NamedTuple

import numpy as np
import torch
from tqdm import tqdm

from gsrmr_common.camera import Camera
from gsrmr_common.metrics import psnr
from gsrmr_common.nerfstudio import DatasetFrame, dataset_point_cloud, holdout_split, read_dataset
from gsrmr_splat.camera_opt import (
    EXPOSURE_DIM,
    POSE_DIM,
    FrameCorrections,
    apply_exposure,
    corrected_world_to_camera,
    corrected_world_to_camera_np,
    exposure_summary,
    per_frame_rows,
    pose_summary,
    refine_pose,
    undo_exposure,
)
from gsrmr_splat.contribution import max_blend_weight
from gsrmr_splat.diffrender import render_torch
from gsrmr_splat.fused import FusedEngine
from gsrmr_splat.initialise import (
    INIT_METHODS,
    has_depth,
    initial_points,
    knn_scales,
    resize_frames,
    scene_extent,
)
from gsrmr_splat.losses import ssim_torch, train_loss
from gsrmr_splat.model import GaussianModel
from gsrmr_splat.optim import PARAM_NAMES, TrainState, adam_step, reset_opacity, select_rows
from gsrmr_splat.render import render
from gsrmr_splat.strategy import densify_and_prune
from gsrmr_splat.train_config import ENGINES, TrainConfig

__all__ = ["PARAM_NAMES", "HistoryRow", "TrainConfig", "TrainState", "Trainer", "max_blend_weight", "ssim_torch",
           "train_loss"]


def _plain(value):
    """A numpy scalar as the Python number it holds (checkpoints hold no numpy objects)."""
    return value.item() if isinstance(value, np.generic) else value


class HistoryRow(NamedTuple):
    """One progress record of :meth:`Trainer.train`."""

    iteration: int
    wall_s: float
    cpu_s: float
    loss: float
    test_psnr_db: float
    num_gaussians: int


class Trainer:
    """Optimises a Gaussian model on a list of training frames: the 3DGS recipe on the CPU.

    Loss 0.8·L1 + 0.2·(1 − SSIM); Adam with the 3DGS learning rates (:meth:`lr`); adaptive density control under
    a Gaussian budget (:func:`~gsrmr_splat.strategy.densify_and_prune`), opacity resets and an SH degree ramp (one
    degree more every ``sh_increase_interval`` steps); optional per-frame pose and exposure corrections
    (:mod:`~gsrmr_splat.camera_opt`); each step computed by the fused numba engine or by torch autograd
    (``TrainConfig.engine``). Settings: :class:`TrainConfig`; the recipe and its measurements: docs/splatting.md,
    "Training" and "Training on what a robot records".

    A frame (:class:`gsrmr_common.nerfstudio.DatasetFrame`) is a camera — OpenCV axes (x right, y down,
    z forward), world→camera 4×4 in metres, intrinsics in pixels — and an H×W×3 float32 image, RGB in [0, 1].

    Args:
        frames: The training frames (at least one), images loaded at their cameras' size.
        config: The settings (None: the defaults).
        test_frames: Held-out frames for :meth:`evaluate` (None: none).
        initial_model: A trained model to fine-tune: it replaces the point initialisation, and its SH degree
            (capped by ``config.sh_degree``) is active from the start.
        point_cloud: The dataset's sparse cloud, (N×3 points in metres in the frames' world, N×3 colours in
            [0, 1]), for ``config.init`` ``points`` or ``auto``.

    Raises:
        ValueError: No training frames, an image that does not match its camera, an unknown ``init`` or
            ``engine``, or an explicit ``init`` source the frames do not have.

    Example:
        ::

            trainer = Trainer.from_dataset("data/round1", TrainConfig(iterations=2000), holdout_every=8)
            model = trainer.train(cpu_budget_s=120.0, progress=False)
            print(trainer.evaluate())  # held-out PSNR in dB, at the recorded poses
            model.save_ply("round1.ply")
    """

    def __init__(self, frames: list[DatasetFrame], config: TrainConfig | None = None,
                 test_frames: list[DatasetFrame] | None = None, initial_model: GaussianModel | None = None,
                 point_cloud: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        self.config = config or TrainConfig()
        cfg = self.config
        if cfg.torch_threads:
            # The torch ops here are small; a second OpenMP pool next to numba's costs up to 5× per step.
            torch.set_num_threads(cfg.torch_threads)
        if not frames:
            raise ValueError("Trainer: no training frames")
        for i, f in enumerate([*frames, *(test_frames or [])]):
            k = f.camera.intrinsics
            if f.image.shape != (k.height, k.width, 3):  # e.g. read_dataset(load_images=False): 0×0 placeholders
                raise ValueError(f"Trainer: frame {i} ({f.file_path or 'unnamed'}) has a {f.image.shape} image for a "
                                 f"{k.width}×{k.height} camera (were the images loaded?)")
        if cfg.init not in INIT_METHODS:
            raise ValueError(f"Trainer: init must be one of {', '.join(INIT_METHODS)}, got {cfg.init!r}")
        self.frames = resize_frames(frames, cfg.resolution)
        self.test_frames = resize_frames(test_frames or [], cfg.resolution)
        self.targets = [torch.from_numpy(np.ascontiguousarray(f.image, np.float32)) for f in self.frames]
        self.extent = scene_extent([f.camera for f in self.frames])
        self.rng = np.random.default_rng(cfg.seed)
        self.torch_gen = torch.Generator().manual_seed(cfg.seed)
        self.point_cloud = point_cloud
        self.init_source = "model"  # where the initial Gaussians came from: depth, points, random or model
        if initial_model is None:
            self.state = self._initial_state()
        else:
            self.state = self._state_from_model(initial_model.with_degree(min(initial_model.sh_degree,
                                                                               cfg.sh_degree)))
            self.state.sh_active = min(initial_model.sh_degree, cfg.sh_degree)
        if cfg.pose_opt:
            self.state.pose = FrameCorrections.zeros(len(self.frames), POSE_DIM)
        if cfg.exposure_opt:
            self.state.exposure = FrameCorrections.zeros(len(self.frames), EXPOSURE_DIM)
        # the recorded world→camera of each training frame, float64, for the pose refinement
        self._recorded_w2c = [torch.as_tensor(f.camera.world_to_camera, dtype=torch.float64)
                              for f in self.frames] if cfg.pose_opt else []
        self._perm: list[int] = []
        if cfg.engine not in ENGINES:
            raise ValueError(f"Trainer: engine must be one of {', '.join(ENGINES)}, got {cfg.engine!r}")
        self._fused = FusedEngine(adaptive_threads=cfg.adaptive_threads)
        self._target_arrays = [t.numpy() for t in self.targets]

    @classmethod
    def from_dataset(cls, path: str | Path, config: TrainConfig | None = None,
                     holdout_every: int = 0) -> Trainer:
        """A trainer on a nerfstudio dataset (:func:`gsrmr_common.nerfstudio.read_dataset`).

        Args:
            path: The dataset folder or its ``transforms.json``.
            config: The settings (None: the defaults).
            holdout_every: Every ``holdout_every``-th frame becomes a held-out test view (0: none).

        Returns:
            Trainer: Initialised, not yet trained. The point cloud the dataset names (``ply_file_path``) is read
            when the initialisation would use it.

        Raises:
            FileNotFoundError: No ``transforms.json`` (or no point cloud where the dataset names one).
            ValueError: A malformed dataset or point cloud, or as the constructor.

        Example:
            ::

                trainer = Trainer.from_dataset("data/round1", holdout_every=8)
        """
        cfg = config or TrainConfig()
        train, test = holdout_split(read_dataset(path), holdout_every)
        wants_cloud = cfg.init == "points" or (cfg.init == "auto" and not has_depth(train))
        cloud = dataset_point_cloud(path) if wants_cloud else None
        return cls(train, config, test, point_cloud=cloud)

    # ------------------------------------------------------------------ state
    def _initial_state(self) -> TrainState:
        cfg = self.config
        pts, cols, self.init_source = initial_points(cfg.init, self.frames, cfg.init_points, self.extent, self.rng,
                                                     self.point_cloud)
        scales = np.clip(knn_scales(pts), 1e-4, 0.1 * self.extent)
        model = GaussianModel.from_points(pts, np.clip(cols, 0, 1), scales_m=scales, opacities=0.1,
                                          degree=cfg.sh_degree)
        return self._state_from_model(model)

    def _state_from_model(self, model: GaussianModel) -> TrainState:
        n = model.num_gaussians
        params = {"means": torch.from_numpy(model.means.copy()), "quats": torch.from_numpy(model.quats.copy()),
                  "log_scales": torch.from_numpy(model.log_scales.copy()),
                  "opacity_logits": torch.from_numpy(model.opacity_logits.copy()),
                  "sh_dc": torch.from_numpy(model.sh[:, :1].copy()),
                  "sh_rest": torch.from_numpy(model.sh[:, 1:].copy())}
        return TrainState(params, {k: torch.zeros_like(v) for k, v in params.items()},
                          {k: torch.zeros_like(v) for k, v in params.items()}, 0, torch.zeros(n), torch.zeros(n),
                          torch.zeros(n), torch.zeros(n, dtype=torch.long), 0, [])

    @property
    def num_gaussians(self) -> int:
        """Current Gaussian count."""
        return int(self.state.params["means"].shape[0])

    def model(self) -> GaussianModel:
        """The current model as a :class:`GaussianModel` (SH of the configured degree)."""
        p = self.state.params
        sh = torch.cat([p["sh_dc"], p["sh_rest"]], dim=1)
        return GaussianModel(p["means"].numpy(), p["quats"].numpy(), p["log_scales"].numpy(),
                             p["opacity_logits"].numpy(), sh.numpy())

    def lr(self, name: str, step: int) -> float:
        """Learning rate of a parameter group at ``step`` (position: exponential decay × extent; the per-frame
        ``pose`` and ``exposure`` corrections: exponential decay from their initial to their final rate)."""
        cfg = self.config
        t = min(max(step / max(cfg.iterations, 1), 0.0), 1.0)
        if name == "means":
            return math.exp((1 - t) * math.log(cfg.lr_means) + t * math.log(cfg.lr_means_final)) * self.extent
        if name == "pose":
            return math.exp((1 - t) * math.log(cfg.lr_pose) + t * math.log(cfg.lr_pose_final))
        if name == "exposure":
            return math.exp((1 - t) * math.log(cfg.lr_exposure) + t * math.log(cfg.lr_exposure_final))
        return {"quats": cfg.lr_quats, "log_scales": cfg.lr_scales, "opacity_logits": cfg.lr_opacity,
                "sh_dc": cfg.lr_sh_dc, "sh_rest": cfg.lr_sh_rest}[name]

    # ------------------------------------------------------------------ one step
    def _next_view(self) -> int:
        if not self._perm:
            self._perm = list(self.rng.permutation(len(self.frames)))
        return int(self._perm.pop())

    def step(self) -> tuple[float, float]:
        """One optimisation step on the next training view (a shuffled pass over the views).

        With ``pose_opt`` the view is rendered at its recorded pose corrected by its learned δ, with
        ``exposure_opt`` its render passes through its learned gain and bias before the loss.
        ``TrainConfig.engine`` picks the fused numba step (:mod:`~gsrmr_splat.fused`) or the torch autograd one;
        density control, the SH schedule and the opacity reset follow either.

        Returns:
            tuple[float, float]: The photometric loss (without the corrections' L2 penalties) and the PSNR (dB) of
            that view's render.
        """
        cfg, st = self.config, self.state
        it = st.step + 1
        view = self._next_view()
        if cfg.engine == "fused":
            loss, mse = self._step_fused(it, view)
        else:
            loss, mse = self._step_torch(it, view)
        st.step = it
        if it % cfg.sh_increase_interval == 0 and st.sh_active < cfg.sh_degree:
            st.sh_active += 1
        if cfg.densify_from <= it <= cfg.densify_until and it % cfg.densify_interval == 0:
            self.densify_and_prune(it)
        if it % cfg.opacity_reset_interval == 0 and it <= cfg.densify_until:
            self.reset_opacity()
        return loss, -10.0 * math.log10(max(mse, 1e-10))

    def _step_fused(self, it: int, view: int) -> tuple[float, float]:
        """The fused engine's step (:class:`~gsrmr_splat.fused.FusedEngine`); (loss, MSE)."""
        cfg, st = self.config, self.state
        frame = self.frames[view]
        res = self._fused.step(st, frame.camera, self._target_arrays[view], it, self.lr,
                               background=cfg.background, near_m=cfg.near_m, sh_degree=st.sh_active,
                               pose=None if st.pose is None else st.pose.values[view].numpy(), pose_reg=cfg.pose_reg,
                               exposure=None if st.exposure is None else st.exposure.values[view].numpy(),
                               exposure_reg=cfg.exposure_reg)
        self._update_corrections(it, view, None if res.pose_grad is None else torch.from_numpy(res.pose_grad),
                                 None if res.exposure_grad is None else torch.from_numpy(res.exposure_grad))
        return res.loss, res.mse

    def _step_torch(self, it: int, view: int) -> tuple[float, float]:
        """The torch engine's step (autograd through :func:`~gsrmr_splat.diffrender.render_torch`);
        (loss, MSE)."""
        cfg, st = self.config, self.state
        frame, target = self.frames[view], self.targets[view]
        p = st.params
        for v in p.values():
            v.requires_grad_(True)
            v.grad = None
        pose_row = None if st.pose is None else st.pose.row(view)
        exposure_row = None if st.exposure is None else st.exposure.row(view)
        w2c = None if pose_row is None else corrected_world_to_camera(self._recorded_w2c[view], pose_row)
        sh = torch.cat([p["sh_dc"], p["sh_rest"]], dim=1)
        out = render_torch(p["means"], p["quats"], p["log_scales"], p["opacity_logits"], sh, frame.camera,
                           cfg.background, sh_degree=st.sh_active, near_m=cfg.near_m, world_to_camera=w2c)
        rgb = out.rgb if exposure_row is None else apply_exposure(out.rgb, exposure_row)
        loss = train_loss(rgb, target)
        objective = loss
        if pose_row is not None:
            objective = objective + cfg.pose_reg * (pose_row * pose_row).sum()
        if exposure_row is not None:
            objective = objective + cfg.exposure_reg * (exposure_row * exposure_row).sum()
        objective.backward()
        with torch.no_grad():
            idx = torch.from_numpy(out.index)
            if out.means2d.grad is not None and len(idx):
                k = frame.camera.intrinsics
                g = out.means2d.grad * torch.tensor([0.5 * k.width, 0.5 * k.height])
                st.grad_accum.index_add_(0, idx, g.norm(dim=1))
                st.grad_count.index_add_(0, idx, torch.ones(len(idx)))
                st.max_radius[idx] = torch.maximum(st.max_radius[idx],
                                                   torch.from_numpy(out.radius_px.astype(np.float32)))
            st.last_seen[idx] = it
            self._adam(it)
            self._update_corrections(it, view, None if pose_row is None else pose_row.grad,
                                     None if exposure_row is None else exposure_row.grad)
            mse = float(((rgb.clamp(0, 1) - target) ** 2).mean())
        return float(loss.detach()), mse

    def _adam(self, it: int) -> None:
        adam_step(self.state, self.lr, it)

    def _update_corrections(self, it: int, view: int, pose_grad: torch.Tensor | None,
                            exposure_grad: torch.Tensor | None) -> None:
        """Adam step of the view's pose and exposure rows from their gradients, then the gauge rule (the rows' mean
        is zero)."""
        st = self.state
        for name, table, grad in (("pose", st.pose, pose_grad), ("exposure", st.exposure, exposure_grad)):
            if table is None or grad is None:
                continue
            table.adam_update(view, grad, self.lr(name, it))
            table.remove_mean()

    # ------------------------------------------------------------------ per-frame corrections
    def training_cameras(self) -> list[Camera]:
        """The training views' cameras as the model was fitted to them: the recorded ones, corrected by the
        learned pose δ when ``pose_opt`` is on."""
        if self.state.pose is None:
            return [f.camera for f in self.frames]
        deltas = self.state.pose.values.numpy()
        return [Camera(f.camera.intrinsics, corrected_world_to_camera_np(f.camera.world_to_camera, d))
                for f, d in zip(self.frames, deltas, strict=True)]

    def refined_frames(self) -> list[DatasetFrame]:
        """The training frames as the model sees them: refined cameras (:meth:`training_cameras`) and, with
        ``exposure_opt``, images mapped back to the model's exposure ((image − b)/gain, clipped). The recorded
        frames when both options are off (e.g. for the compaction's fine-tuning)."""
        st = self.state
        if st.pose is None and st.exposure is None:
            return list(self.frames)
        out = []
        for i, (f, cam) in enumerate(zip(self.frames, self.training_cameras(), strict=True)):
            image = f.image if st.exposure is None else undo_exposure(f.image, st.exposure.values[i].numpy())
            out.append(DatasetFrame(cam, image, f.depth_m, f.pose, f.file_path))
        return out

    def corrections_summary(self) -> dict[str, float]:
        """Size of the learned corrections: mean and max ‖τ‖ (cm) and ‖ω‖ (degrees) over the training frames, and
        the range of the exposure gains and biases (only the keys of the options that are on)."""
        st = self.state
        out: dict[str, float] = {}
        if st.pose is not None:
            out.update(pose_summary(st.pose))
        if st.exposure is not None:
            out.update(exposure_summary(st.exposure))
        return out

    def corrections_per_frame(self) -> list[dict]:
        """Per training frame: its file, the pose correction (δ: ω rad, τ m, world axes; ‖τ‖ cm, ‖ω‖ degrees)
        and the exposure (gains r, g, b and biases r, g, b), for the options that are on."""
        return per_frame_rows([f.file_path for f in self.frames], self.state.pose, self.state.exposure)

    # ------------------------------------------------------------------ density control
    def _apply(self, keep: torch.Tensor, new: dict[str, torch.Tensor] | None = None) -> None:
        select_rows(self.state, keep, new)

    def densify_and_prune(self, it: int) -> None:
        """Clone, split and prune (:func:`gsrmr_splat.strategy.densify_and_prune`)."""
        densify_and_prune(self.state, self.config, self.extent, len(self.frames), it, self.torch_gen)

    def reset_opacity(self) -> None:
        """3DGS opacity reset (:func:`gsrmr_splat.optim.reset_opacity`)."""
        reset_opacity(self.state)

    def prune_unused(self) -> int:
        """Remove Gaussians that change no training pixel (max blending weight < 1/255); returns count."""
        weights = max_blend_weight(self.model(), self.training_cameras(), self.config.near_m)
        keep = torch.from_numpy(weights >= 1.0 / 255.0)
        removed = int((~keep).sum())
        self._apply(keep)
        return removed

    # ------------------------------------------------------------------ evaluation, IO, loop
    def evaluate(self, frames: list[DatasetFrame] | None = None) -> float:
        """Mean PSNR of :func:`~gsrmr_splat.render.render` on ``frames``, each at its recorded pose, without any
        exposure model (what the live server does at the robot's pose keys), at the training resolution.

        Args:
            frames: The frames to score (None: the held-out test frames).

        Returns:
            float: The mean PSNR in dB; NaN when there are no frames.

        Example:
            ::

                psnr_db = trainer.evaluate()
        """
        frames = self.test_frames if frames is None else frames
        if not frames:
            return float("nan")
        model = self.model()
        vals = [psnr(render(model, f.camera, self.config.background, sh_degree=self.state.sh_active,
                            near_m=self.config.near_m).rgb, f.image) for f in frames]
        return float(np.mean(vals))

    def evaluate_pose_refined(self, steps: int = 20, lr_pose: float | None = None,
                              frames: list[DatasetFrame] | None = None) -> tuple[float, list[np.ndarray]]:
        """Test-time pose refinement: the mean PSNR of ``frames`` after ``steps`` Adam steps of a pose correction
        per frame with the model frozen (:func:`~gsrmr_splat.camera_opt.refine_pose`). Not the fair held-out
        figure (:meth:`evaluate`, at the recorded poses): it tells how much of the error is the frame's pose.

        Args:
            steps: Adam steps per frame.
            lr_pose: Adam step size (rad and m per update; None: ``config.lr_pose``).
            frames: The frames to refine and score (None: the held-out test frames).

        Returns:
            tuple[float, list[numpy.ndarray]]: The mean PSNR in dB (NaN without frames) and each frame's
            correction δ = (ω rad, τ m), world axes.

        Example:
            ::

                refined_db, deltas = trainer.evaluate_pose_refined(steps=30)
        """
        frames = self.test_frames if frames is None else frames
        if not frames:
            return float("nan"), []
        cfg, st = self.config, self.state
        lr = cfg.lr_pose if lr_pose is None else lr_pose
        model = self.model()
        vals, deltas = [], []
        for f in frames:
            d = refine_pose(st.params, f, steps, lr, background=cfg.background, sh_degree=st.sh_active,
                            near_m=cfg.near_m)
            cam = Camera(f.camera.intrinsics, corrected_world_to_camera_np(f.camera.world_to_camera, d))
            vals.append(psnr(render(model, cam, cfg.background, sh_degree=st.sh_active, near_m=cfg.near_m).rgb,
                             f.image))
            deltas.append(d)
        return float(np.mean(vals)), deltas

    def save_checkpoint(self, path: str | Path) -> Path:
        """Save everything needed to resume bit-exactly (``torch.save``): the config, parameters, Adam moments,
        density statistics, step, history, RNG states and, when on, the per-frame corrections with their Adam
        state. Tensors and plain Python types only, so that :meth:`load_checkpoint` reads it with
        ``torch.load(weights_only=True)`` (no arbitrary unpickling).

        Args:
            path: The checkpoint file; its folder is created.

        Returns:
            Path: ``path``.

        Example:
            ::

                trainer.save_checkpoint("round1.ply.ckpt")
        """
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        st = self.state
        ck = {"config": self.config.to_dict(), "params": st.params, "exp_avg": st.exp_avg,
              "exp_avg_sq": st.exp_avg_sq, "step": st.step, "grad_accum": st.grad_accum,
              "grad_count": st.grad_count, "max_radius": st.max_radius, "last_seen": st.last_seen,
              "sh_active": int(st.sh_active), "history": [tuple(_plain(v) for v in h) for h in st.history],
              "rng": self.rng.bit_generator.state,
              "torch_rng": self.torch_gen.get_state(), "extent": float(self.extent),
              "perm": [int(i) for i in self._perm]}
        if st.pose is not None:
            ck["pose_corrections"] = st.pose.to_dict()
        if st.exposure is not None:
            ck["exposure_corrections"] = st.exposure.to_dict()
        if st.pose is not None or st.exposure is not None:
            ck["correction_history"] = [dict(r) for r in st.correction_history]
        torch.save(ck, path)
        return path

    def load_checkpoint(self, path: str | Path) -> None:
        """Resume from :meth:`save_checkpoint` output; the next :meth:`train` continues bit-exactly.

        Args:
            path: The checkpoint file. The trainer must hold the same frames and the same ``pose_opt`` and
                ``exposure_opt`` options as the run that wrote it.

        Raises:
            FileNotFoundError: ``path`` does not exist.
            ValueError: The checkpoint's pose or exposure corrections do not match this run's options.

        Example:
            ::

                trainer = Trainer.from_dataset("data/round1", cfg, holdout_every=8)
                trainer.load_checkpoint("round1.ply.ckpt")
                model = trainer.train()
        """
        ck = torch.load(Path(path), weights_only=True)  # tensors and plain types only: no arbitrary unpickling
        st = self.state
        st.params, st.exp_avg, st.exp_avg_sq = ck["params"], ck["exp_avg"], ck["exp_avg_sq"]
        st.step, st.grad_accum, st.grad_count = ck["step"], ck["grad_accum"], ck["grad_count"]
        st.max_radius, st.last_seen, st.sh_active = ck["max_radius"], ck["last_seen"], ck["sh_active"]
        st.history = [HistoryRow(*h) for h in ck["history"]]
        self.rng.bit_generator.state = ck["rng"]
        self.torch_gen.set_state(ck["torch_rng"])
        self.extent = ck["extent"]
        self._perm = [int(i) for i in ck["perm"]]
        for key, name, on in (("pose_corrections", "pose", self.config.pose_opt),
                              ("exposure_corrections", "exposure", self.config.exposure_opt)):
            if on != (key in ck):
                raise ValueError(f"checkpoint {path}: {name} corrections {'missing' if on else 'present'}, but this "
                                 f"run has {name} optimisation {'on' if on else 'off'}: resume with the same options")
            if on:
                setattr(st, name, FrameCorrections.from_dict(ck[key]))
        st.correction_history = [dict(r) for r in ck.get("correction_history", [])]

    def train(self, iterations: int | None = None, *, checkpoint: str | Path | None = None,
              eval_every: int = 0, progress: bool = True, time_budget_s: float | None = None,
              cpu_budget_s: float | None = None) -> GaussianModel:
        """Train until the iteration count or a time budget is reached, then (with ``config.final_prune``) remove
        the Gaussians that change no training pixel.

        Appends a :class:`HistoryRow` (iteration, wall s, CPU s, train loss, held-out PSNR or NaN, Gaussian count)
        to ``state.history`` every ``eval_every`` iterations and at the end.

        Args:
            iterations: The step count to reach, counted from the start of the run (None: ``config.iterations``).
            checkpoint: Save a checkpoint here every ``config.checkpoint_every`` steps and at the end (None: none).
            eval_every: Score the held-out frames every this many steps (0: only at the end).
            progress: Show a tqdm progress bar.
            time_budget_s: Stop after this much wall time (seconds; None: no limit).
            cpu_budget_s: Stop after this much process CPU time, all threads, held-out evaluation excluded
                (seconds; None: no limit).

        Returns:
            GaussianModel: The trained model.

        Example:
            ::

                model = trainer.train(checkpoint="round1.ply.ckpt", eval_every=500, progress=False)
                last = trainer.state.history[-1]  # HistoryRow
        """
        total = self.config.iterations if iterations is None else iterations
        st = self.state
        wall0 = time.perf_counter() - (st.history[-1].wall_s if st.history else 0.0)
        cpu_used = st.history[-1].cpu_s if st.history else 0.0
        bar = tqdm(total=total, initial=st.step, disable=not progress, unit="it", dynamic_ncols=True)
        loss = float("nan")
        while st.step < total:
            c0 = time.process_time()
            loss, view_psnr = self.step()
            cpu_used += time.process_time() - c0
            bar.update(1)
            if st.step % 10 == 0:
                bar.set_postfix(loss=f"{loss:.4f}", psnr=f"{view_psnr:.2f}", n=self.num_gaussians)
            if eval_every and st.step % eval_every == 0:
                self._record(HistoryRow(st.step, time.perf_counter() - wall0, cpu_used, loss, self.evaluate(),
                                        self.num_gaussians))
            if checkpoint and self.config.checkpoint_every and st.step % self.config.checkpoint_every == 0:
                self.save_checkpoint(checkpoint)
            if time_budget_s is not None and time.perf_counter() - wall0 >= time_budget_s:
                break
            if cpu_budget_s is not None and cpu_used >= cpu_budget_s:
                break
        bar.close()
        if self.config.final_prune:
            c0 = time.process_time()
            self.prune_unused()
            cpu_used += time.process_time() - c0
        self._record(HistoryRow(st.step, time.perf_counter() - wall0, cpu_used, loss, self.evaluate(),
                                self.num_gaussians))
        if checkpoint:
            self.save_checkpoint(checkpoint)
        return self.model()

    def _record(self, row: HistoryRow) -> None:
        """Append a history row (and, with pose or exposure optimisation, the corrections' summary beside it)."""
        st = self.state
        st.history.append(row)
        if st.pose is not None or st.exposure is not None:
            st.correction_history.append({"iteration": int(row.iteration), **self.corrections_summary()})
