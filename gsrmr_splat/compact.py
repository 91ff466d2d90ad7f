"""Compaction: the smallest model of a scene within a held-out PSNR tolerance (:class:`Compactor`, settings
:class:`CompactConfig`): Gaussians ranked by their accumulated blending weight, pruned in rounds with brief fine-tuning,
then lower SH degrees while the tolerance holds. Design and measurements: docs/splatting.md, "Compaction".
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
import math
import time

import numpy as np

from gsrmr_common.camera import Camera
from gsrmr_common.nerfstudio import DatasetFrame
from gsrmr_splat.contribution import blend_weights
from gsrmr_splat.model import GaussianModel
from gsrmr_splat.train import TrainConfig, Trainer


@dataclass(frozen=True)
class CompactConfig:
    """How hard to compact (fractions of the current model; PSNR in dB)."""

    max_psnr_drop_db: float = 0.3  # tolerance below the uncompacted model's held-out PSNR
    prune_fraction: float = 0.25  # share of the remaining Gaussians pruned per round
    min_prune_fraction: float = 0.06  # a round over the tolerance is retried with half the share, down to this
    finetune_iterations: int = 300  # fine-tuning steps after each pruning round and SH step
    max_rounds: int = 12
    min_gaussians: int = 500
    lower_sh: bool = True  # also try lower SH degrees

    def __post_init__(self) -> None:
        if not (math.isfinite(self.max_psnr_drop_db) and self.max_psnr_drop_db >= 0):
            raise ValueError("max_psnr_drop_db must be a finite number ≥ 0")
        if not 0.0 < self.min_prune_fraction <= self.prune_fraction < 1.0:
            raise ValueError("need 0 < min_prune_fraction ≤ prune_fraction < 1")
        if self.finetune_iterations < 0 or self.max_rounds < 0 or self.min_gaussians < 1:
            raise ValueError("finetune_iterations, max_rounds ≥ 0 and min_gaussians ≥ 1")


@dataclass
class CompactStep:
    """One attempted round: what was tried and what it measured."""

    kind: str  # "prune" | "sh"
    gaussians: int
    sh_degree: int
    heldout_psnr_db: float
    accepted: bool
    wall_s: float


@dataclass
class CompactResult:
    """The compacted model and the trade it made."""

    model: GaussianModel
    gaussians_before: int
    gaussians_after: int
    sh_degree_before: int
    sh_degree_after: int
    heldout_psnr_before_db: float
    heldout_psnr_after_db: float
    wall_s: float
    cpu_s: float
    steps: list[CompactStep] = field(default_factory=list)

    def summary(self) -> dict:
        """The figures ``gsrmr-compact`` prints as its last line (JSON)."""
        return {"gaussians_before": self.gaussians_before, "gaussians_after": self.gaussians_after,
                "sh_degree_before": self.sh_degree_before, "sh_degree_after": self.sh_degree_after,
                "heldout_psnr_before_db": self.heldout_psnr_before_db,
                "heldout_psnr_after_db": self.heldout_psnr_after_db, "wall_s": self.wall_s, "cpu_s": self.cpu_s,
                "rounds": len(self.steps)}


def finetune_config(base: TrainConfig, iterations: int, sh_degree: int) -> TrainConfig:
    """Fine-tuning settings: the base run's rates and background, no densification, no opacity reset, the
    position rate held at its final (smallest) value, the SH degree fixed."""
    return replace(base, iterations=max(1, iterations), densify_from=iterations + 1, densify_until=0,
                   opacity_reset_interval=10 ** 9, lr_means=base.lr_means_final, sh_degree=sh_degree,
                   sh_increase_interval=10 ** 9, checkpoint_every=0)


class Compactor:
    """Runs the compaction of one model on one dataset split.

    Every Gaussian is ranked by its accumulated blending weight Σ α·T over every pixel of the coverage views
    (LightGaussian's global significance, Mini-Splatting's importance). Rounds prune the least contributing
    ``prune_fraction`` of what is left and fine-tune briefly (:func:`finetune_config`), measuring the held-out
    PSNR as ``gsrmr-train`` does (:meth:`Trainer.evaluate`); a round more than ``max_psnr_drop_db`` below the
    uncompacted model is discarded and retried with half the share, until the share falls below
    ``min_prune_fraction``. Then the SH degree is lowered one step at a time (fine-tuned the same way) while the
    tolerance holds.
    """

    def __init__(self, train_frames: list[DatasetFrame], test_frames: list[DatasetFrame],
                 train_config: TrainConfig | None = None, config: CompactConfig | None = None,
                 coverage_cameras: list[Camera] | None = None) -> None:
        """``coverage_cameras``: the views a Gaussian's contribution is summed over to rank it (default: the
        training frames' cameras). A fine-tune on part of a scene (the model update) passes every view the model
        must serve, so that what its training views do not see is not pruned first."""
        if not test_frames:
            raise ValueError("compaction needs held-out frames to measure the PSNR it may lose")
        self.train_frames, self.test_frames = train_frames, test_frames
        self.coverage_cameras = list(coverage_cameras) if coverage_cameras is not None else None
        self.train_config = train_config or TrainConfig()
        self.config = config or CompactConfig()

    def _trainer(self, model: GaussianModel, iterations: int) -> Trainer:
        cfg = finetune_config(self.train_config, iterations, model.sh_degree)
        return Trainer(self.train_frames, cfg, self.test_frames, initial_model=model)

    def evaluate(self, model: GaussianModel) -> float:
        """Held-out PSNR (dB) of ``model``, as ``gsrmr-train`` measures it."""
        return self._trainer(model, 1).evaluate()

    def finetune(self, model: GaussianModel) -> tuple[GaussianModel, float]:
        """``finetune_iterations`` steps on the training views; returns (model, held-out PSNR dB)."""
        tr = self._trainer(model, self.config.finetune_iterations)
        if self.config.finetune_iterations:
            tr.train(progress=False)
        return tr.model(), tr.evaluate()

    def run(self, model: GaussianModel) -> CompactResult:
        """Compact ``model``; the result is never below the tolerance (else it is the input itself)."""
        cfg = self.config
        wall0, cpu0 = time.perf_counter(), time.process_time()
        before = self.evaluate(model)
        floor = before - cfg.max_psnr_drop_db
        best, best_psnr = model, before
        steps: list[CompactStep] = []
        cameras = self.coverage_cameras if self.coverage_cameras is not None else [f.camera for f in self.train_frames]
        fraction = cfg.prune_fraction
        for _ in range(cfg.max_rounds):
            n = best.num_gaussians
            n_keep = max(cfg.min_gaussians, int(round(n * (1.0 - fraction))))
            if n_keep >= n:
                break
            t0 = time.perf_counter()
            score, _ = blend_weights(best, cameras, self.train_config.near_m)
            keep = np.sort(np.argsort(score, kind="stable")[n - n_keep:])
            cand, psnr_db = self.finetune(best.subset(keep))
            ok = psnr_db >= floor
            steps.append(CompactStep("prune", cand.num_gaussians, cand.sh_degree, psnr_db, ok,
                                     time.perf_counter() - t0))
            if not ok:
                fraction /= 2.0
                if fraction < cfg.min_prune_fraction:
                    break
                continue
            best, best_psnr = cand, psnr_db
        while cfg.lower_sh and best.sh_degree > 0:
            t0 = time.perf_counter()
            cand, psnr_db = self.finetune(best.with_degree(best.sh_degree - 1))
            ok = psnr_db >= floor
            steps.append(CompactStep("sh", cand.num_gaussians, cand.sh_degree, psnr_db, ok,
                                     time.perf_counter() - t0))
            if not ok:
                break
            best, best_psnr = cand, psnr_db
        return CompactResult(best, model.num_gaussians, best.num_gaussians, model.sh_degree, best.sh_degree,
                             before, best_psnr, time.perf_counter() - wall0, time.process_time() - cpu0, steps)
