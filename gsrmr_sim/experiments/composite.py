"""The MR images a schedule actually produces, and their loss/PSNR/SSIM against the true m_t.

Per slot t with delivered content (``Schedule.delivered``):

* ``image`` — the server has r_t: m̂_t = d_t⊙r_t + (1−d_t)⊙v_t = m_t (the paper's lossless image
  upload; JPEG coding loss is measured separately in the JPEG trade-off);
* ``key``   — the server renders Φ(s_t): m̂_t = d_t⊙Φ(s_t) + (1−d_t)⊙v_t;
* ``none``  — nothing arrived (MaxRate/Fairness can starve a slot): the server renders Φ at the last
  pose it knows (the pose of the latest delivered slot, or the route start s_0 if none yet) and
  composites it with the current v_t through d_t. This matches the scheduling library's default
  ``undelivered_loss="gs"`` in spirit, but is measured, not assumed (a stale pose costs more than L_t).

Metrics use :func:`gsrmr_common.metrics.image_quality` (loss = 0.8·L1 + 0.2·(1 − SSIM), PSNR capped at
:data:`gsrmr_common.metrics.PSNR_CAP_DB` for identical images) and are averaged over the T slots.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gsrmr_common.metrics import image_quality, pooled_psnr_db
from gsrmr_server.mr.blend import mr_image
from gsrmr_server.scheduling.problem import IMAGE, KEY, NONE
from gsrmr_server.splatting.model import GaussianModel
from gsrmr_server.splatting.render import render
from gsrmr_sim.world import Round2Record


@dataclass
class CompositeResult:
    """Per-slot metrics of the composited MR images (arrays of length T) and their means."""

    loss: np.ndarray
    psnr_db: np.ndarray
    ssim: np.ndarray
    delivered: list[str]

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


class Compositor:
    """Builds m̂_t for any delivery pattern of one round-2 record; caches GS renders per pose slot."""

    def __init__(self, record: Round2Record, model: GaussianModel, background: tuple[float, float, float]) -> None:
        self.record = record
        self.model = model
        self.background = background
        self._gs: dict[int, np.ndarray] = {}
        self._q: dict[tuple[int, int | None], tuple[float, float, float]] = {}

    def gs_view(self, pose_slot: int) -> np.ndarray:
        """Φ(s_k) rendered at the camera of slot ``pose_slot`` (H×W×3 float in [0, 1]), cached."""
        if pose_slot not in self._gs:
            self._gs[pose_slot] = render(self.model, self.record.camera(pose_slot), self.background).rgb
        return self._gs[pose_slot]

    def pose_slots(self, delivered: list[str]) -> list[int | None]:
        """For each slot, which slot's pose the server renders at (None = it has the image)."""
        out: list[int | None] = []
        last = 0
        for t, d in enumerate(delivered):
            if d == IMAGE:
                out.append(None)
                last = t
            elif d == KEY:
                out.append(t)
                last = t
            elif d == NONE:
                out.append(last)
            else:
                raise ValueError(f"slot {t}: unknown delivery {d!r}")
        return out

    def mr_images(self, delivered: list[str], t: int, pose_slots: list[int | None] | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
        """(m_t, m̂_t) of slot t under ``delivered``."""
        ps = pose_slots if pose_slots is not None else self.pose_slots(delivered)
        rec = self.record[t]
        truth = mr_image(rec.image, rec.virtual, rec.mask)
        k = ps[t]
        got = truth if k is None else mr_image(self.gs_view(k), rec.virtual, rec.mask)
        return truth, got

    def evaluate(self, delivered: list[str]) -> CompositeResult:
        """Per-slot loss/PSNR/SSIM of m̂_t against m_t."""
        if len(delivered) != len(self.record):
            raise ValueError(f"delivered has {len(delivered)} slots, record has {len(self.record)}")
        ps = self.pose_slots(delivered)
        loss, psnr_db, ssim = (np.zeros(len(delivered)) for _ in range(3))
        for t in range(len(delivered)):
            if (t, ps[t]) not in self._q:  # the same (slot, pose) pair always gives the same image
                truth, got = self.mr_images(delivered, t, ps)
                q = image_quality(truth, got)
                self._q[(t, ps[t])] = (q["loss"], q["psnr_db"], q["ssim"])
            loss[t], psnr_db[t], ssim[t] = self._q[(t, ps[t])]
        return CompositeResult(loss, psnr_db, ssim, list(delivered))
