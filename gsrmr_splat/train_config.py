"""The trainer's settings (:class:`TrainConfig`), apart from the loop so that the density control
(:mod:`~gsrmr_splat.strategy`), which the loop calls, can read them without importing the loop."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from gsrmr_splat.project import NEAR_M

#: Training engines (``TrainConfig.engine``): ``fused`` = the numba step without autograd
#: (:mod:`~gsrmr_splat.fused`), ``torch`` = torch autograd through the numba rasterizer.
ENGINES = ("fused", "torch")


@dataclass
class TrainConfig:
    """Trainer settings (3DGS defaults where they exist; iteration counts shortened for the CPU)."""

    iterations: int = 6000
    budget: int = 200_000
    resolution: int | None = None  # train at this image width (keeps aspect); None = as stored
    sh_degree: int = 1
    sh_increase_interval: int = 1000
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    lr_means: float = 1.6e-4
    lr_means_final: float = 1.6e-6
    lr_sh_dc: float = 2.5e-3
    lr_sh_rest: float = 2.5e-3 / 20
    lr_opacity: float = 0.05
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    densify_from: int = 300
    densify_until: int = 4000
    densify_interval: int = 100
    grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    prune_opacity: float = 0.005
    opacity_reset_interval: int = 3000
    max_screen_px: float = 20.0
    init_points: int = 30_000
    seed: int = 0
    checkpoint_every: int = 1000
    near_m: float = NEAR_M
    final_prune: bool = True  # at the end, remove the Gaussians that change no training pixel
    # Density control also prunes the Gaussians no training view has drawn for two passes over the views. Both that
    # and final_prune assume the training views see the whole scene; a fine-tune on part of it (the model update,
    # gsrmr_offline.model_update) turns both off: unseen there means unknown, not useless.
    prune_unseen: bool = True
    torch_threads: int | None = 1  # torch.set_num_threads for the process (None = leave as is)
    # Where the initial Gaussians come from (initialise.choose_init): "auto" = depth when a training frame has
    # depth, else the point cloud the dataset names (ply_file_path), else random; or "depth", "points", "random".
    init: str = "auto"
    # Per-frame camera pose refinement (camera_opt): δ = (ω rad, τ m) in world axes per training frame, Adam step
    # size per update of a frame's row (rad and m) decaying exponentially from lr_pose to lr_pose_final over
    # `iterations` (as the position rate), L2 penalty pose_reg·(|ω|² + |τ|²) on the loss, the corrections' mean
    # held at zero (the gauge: the model stays in map).
    pose_opt: bool = False
    lr_pose: float = 2e-3
    lr_pose_final: float = 5e-4
    pose_reg: float = 1e-2
    # Per-frame exposure compensation (camera_opt): exp(g)·rgb + b per channel before the loss, training only;
    # Adam step size lr_exposure → lr_exposure_final (log-gain and bias units), L2 penalty
    # exposure_reg·(|g|² + |b|²), mean zero.
    exposure_opt: bool = False
    lr_exposure: float = 2e-2
    lr_exposure_final: float = 5e-3
    exposure_reg: float = 1e-3
    # The step's engine (ENGINES): "fused" (numba kernels, no autograd; same maths, several times faster on the
    # CPU) or "torch" (autograd through the numba rasterizer: the reference the fused engine's tests compare to).
    engine: str = "fused"
    # The fused engine runs each step on one numba thread or on numba's count, whichever its timing probes found
    # faster (fused.ThreadChooser; on a busy machine one thread is several times faster); False: numba's count.
    # Never changes a result.
    adaptive_threads: bool = True

    def to_dict(self) -> dict:
        """JSON-friendly dict."""
        return asdict(self)
