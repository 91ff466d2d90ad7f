"""GS losses L_t of a recorded round: what each slot would lose with Φ(s_t) instead of r_t.

L_t (a key-only slot at the true pose) and, with ``jpeg_quality``, J_t (an image slot) are composed by
:class:`~gsrmr_sim.offline_server.OfflineServer` and scored by :func:`gsrmr_offline.frame_loss.frame_loss` (the
deployment survey's scoring) against the simulator's true frames: docs/experiments.md, "Data pipeline", item 3.
``make demo`` seeds the scheduler's loss map with them (docs/scheduling.md, "Seeding the loss map").
"""

from __future__ import annotations

from dataclasses import dataclass

from gsrmr_common.pose2d import Pose2D
from gsrmr_offline.deployment_survey import seed_loss_map
from gsrmr_offline.frame_loss import frame_loss
from gsrmr_scheduler.loss_map import LossMap
from gsrmr_sim.offline_server import REPORTED, TRUE, OfflineServer
from gsrmr_sim.world.recorder import Round2Record
from gsrmr_splat.model import GaussianModel

#: Bump when what :func:`gs_losses` measures changes (cached seed maps and loss files carry it).
SURVEY_VERSION = 3


@dataclass
class SlotLoss:
    """GS loss of one slot (the 3DGS image loss of the published 8-bit m̂ against m; PSNR in dB)."""

    t: int
    pose: Pose2D
    loss: float
    psnr_db: float
    ssim: float
    image_loss: float = float("nan")  # J_t: MR loss of the frame's JPEG composite (with ``jpeg_quality``)
    sample_bias: float = float("nan")  # the image slot's loss sample minus its loss against the true frame


def gs_losses(record: Round2Record, model: GaussianModel, background=(0.0, 0.0, 0.0), *, mr_content: str,
              jpeg_quality: int | None = None, server: OfflineServer | None = None) -> list[SlotLoss]:
    """L_t, PSNR and SSIM of a key slot at the true pose for every slot of ``record``; with ``jpeg_quality``
    also J_t, the loss an image slot leaves (the key the robot reports, at the server's JPEG quality). ``server``
    reuses an :class:`OfflineServer`: its composer, frames, reported poses and JPEG quality."""
    srv = server or OfflineServer(record, model, mr_content=mr_content, background_rgb=tuple(background),
                                  jpeg_quality=jpeg_quality or 80)
    quality = srv.jpeg_quality if jpeg_quality is not None else None  # image slots as the server's uplink sends them
    composer, times = srv.core.composer, record.times_s
    out = []
    for t, pose in enumerate(record.poses):
        q = frame_loss(composer, srv.frame_u8(t), srv.key(t, TRUE), content_time_s=float(times[t]),
                       jpeg_quality=quality, image_pose=srv.key(t, REPORTED))
        out.append(SlotLoss(t, (float(pose[0]), float(pose[1]), float(pose[2])), q.loss, q.psnr_db, q.ssim,
                            q.image_loss, q.sample_bias))
    return out


def loss_map_from(losses: list[SlotLoss], **kwargs) -> LossMap:
    """A loss map holding every surveyed slot (and, where measured, the mean image-slot loss): the deployment
    survey's :func:`~gsrmr_offline.deployment_survey.seed_loss_map`; ``kwargs`` are :class:`LossMap` settings."""
    return seed_loss_map([s.pose for s in losses], [s.loss for s in losses], [s.image_loss for s in losses],
                         [s.sample_bias for s in losses], **kwargs)
