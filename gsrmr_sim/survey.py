"""GS losses L_t of a recorded round: what each slot would lose with Φ(s_t) instead of r_t.

``L_t = MR loss(m_t, m̂_t)`` with m̂_t the live server's composite of a key-only slot at the true pose s_t,
and — with ``jpeg_quality`` — ``J_t``, the loss of an image slot (the robot's JPEG of r_t), both made by the
live slot core and scored by the deployment's scoring library (:mod:`gsrmr_server.scoring`) through
:class:`~gsrmr_sim.offline_server.OfflineServer` (the one composition pipeline). This is the L_t the paper's
optimisation assumes known; the experiments use it directly, and ``make demo`` uses it to seed the
scheduler's loss map (a rehearsal of the operating round), which the running system then corrects online
from the losses it measures in image slots.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gsrmr_server.loss_map import LossMap
from gsrmr_server.scheduling.problem import IMAGE, KEY
from gsrmr_server.splatting.model import GaussianModel
from gsrmr_sim.offline_server import TRUE, OfflineServer
from gsrmr_sim.world.recorder import Round2Record

#: Bump when what :func:`gs_losses` measures changes (cached seed maps and loss files carry it).
SURVEY_VERSION = 2


@dataclass
class SlotLoss:
    """GS loss of one slot (the 3DGS image loss of the published 8-bit m̂ against m; PSNR in dB)."""

    t: int
    pose: tuple[float, float, float]
    loss: float
    psnr_db: float
    ssim: float
    image_loss: float = float("nan")  # J_t: MR loss of the frame's JPEG composite (with ``jpeg_quality``)


def gs_losses(record: Round2Record, model: GaussianModel, background=(0.0, 0.0, 0.0), *, mr_content: str,
              jpeg_quality: int | None = None, server: OfflineServer | None = None) -> list[SlotLoss]:
    """L_t, PSNR and SSIM of a key slot at the true pose for every slot of ``record``; with ``jpeg_quality``
    also J_t, the loss an image slot leaves. ``server`` reuses an :class:`OfflineServer` (and its cache)."""
    srv = server or OfflineServer(record, model, mr_content=mr_content, background_rgb=tuple(background),
                                  jpeg_quality=jpeg_quality or 80)
    keys = srv.evaluate([KEY] * len(record), pose=TRUE)
    images = srv.evaluate([IMAGE] * len(record)) if jpeg_quality is not None else [None] * len(record)
    poses = record.poses
    return [SlotLoss(t, tuple(float(v) for v in poses[t]), k.loss, k.psnr_db, k.ssim,  # type: ignore[arg-type]
                     im.loss if im is not None else float("nan"))
            for t, (k, im) in enumerate(zip(keys, images, strict=True))]


def loss_map_from(losses: list[SlotLoss], **kwargs) -> LossMap:
    """A loss map holding every surveyed slot (and, where measured, the mean image-slot loss)."""
    lm = LossMap(**kwargs)
    for s in losses:
        lm.add(*s.pose, s.loss)
    measured = [s.image_loss for s in losses if np.isfinite(s.image_loss)]
    if measured:
        lm.image_loss = float(np.mean(measured))
    return lm
