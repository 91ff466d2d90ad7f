"""The MR images a schedule actually produces, composed by the live slot core and scored by the deployment's
scoring library (:mod:`gsrmr_server.scoring`), and how far their loss is from the schedule's plan.

What each delivery composes, the split of the measured loss (``plan`` + ``jpeg`` + ``pose`` + ``fallback``) and the
metrics: docs/experiments.md, "What is measured" (Table 1, Metrics).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gsrmr_common.metrics import pooled_psnr_db
from gsrmr_scheduler.problem import IMAGE, KEY, NONE
from gsrmr_sim.offline_server import OfflineServer


@dataclass
class CompositeResult:
    """Per-slot metrics of the composited MR images (arrays of length T), their means and the split of the
    mean loss against the plan (see the module docstring)."""

    loss: np.ndarray
    psnr_db: np.ndarray
    ssim: np.ndarray
    delivered: list[str]
    plan_loss: float  # (1/T)·Σ_{key, none} L_t
    jpeg_loss: float  # (1/T)·Σ_image measured loss
    pose_loss: float  # (1/T)·Σ_key (measured − L_t)
    fallback_loss: float  # (1/T)·Σ_none (measured − L_t)

    @property
    def mean_loss(self) -> float:
        """(1/T)·Σ loss."""
        return float(np.mean(self.loss))

    @property
    def mean_psnr_db(self) -> float:
        """Mean per-slot PSNR (dB)."""
        return float(np.mean(self.psnr_db))

    @property
    def pooled_psnr_db(self) -> float:
        """PSNR of the mean MSE over slots (:func:`gsrmr_common.metrics.pooled_psnr_db`), dB."""
        return pooled_psnr_db(self.psnr_db)

    @property
    def mean_ssim(self) -> float:
        """Mean per-slot SSIM."""
        return float(np.mean(self.ssim))

    @property
    def parts_sum(self) -> float:
        """plan + jpeg + pose + fallback (equals :attr:`mean_loss` up to rounding)."""
        return self.plan_loss + self.jpeg_loss + self.pose_loss + self.fallback_loss


class Compositor:
    """Scores any delivery pattern of one recorded round: the live slot core's images (renders cached)."""

    def __init__(self, server: OfflineServer, gs_loss: np.ndarray) -> None:
        """``gs_loss``: the plan's L_t (key slot at the true pose, as the solvers were given it)."""
        self.server = server
        self.gs_loss = np.asarray(gs_loss, np.float64)

    def evaluate(self, delivered: list[str]) -> CompositeResult:
        """Per-slot loss/PSNR/SSIM of m̂_t against m_t and the split against the plan."""
        if len(delivered) != len(self.server):
            raise ValueError(f"delivered has {len(delivered)} slots, record has {len(self.server)}")
        q = self.server.evaluate(list(delivered))
        loss = np.array([s.loss for s in q])
        kind = np.array(delivered)
        n = float(len(delivered))
        lt = self.gs_loss
        img, key, none = kind == IMAGE, kind == KEY, kind == NONE
        return CompositeResult(loss, np.array([s.psnr_db for s in q]), np.array([s.ssim for s in q]), list(delivered),
                               plan_loss=float(lt[key | none].sum() / n), jpeg_loss=float(loss[img].sum() / n),
                               pose_loss=float((loss[key] - lt[key]).sum() / n),
                               fallback_loss=float((loss[none] - lt[none]).sum() / n))

    def images(self, delivered: list[str], t: int) -> tuple[np.ndarray, np.ndarray]:
        """(m_t, m̂_t) of slot t under ``delivered`` (float in [0, 1])."""
        return self.server.images(delivered, t)
