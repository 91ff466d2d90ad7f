"""GS losses L_t of a recorded round (pure): what each slot would lose with Φ(s_t) instead of r_t.

``L_t = MR loss(d⊙r + (1−d)⊙v, d⊙Φ(s_t) + (1−d)⊙v)`` (paper Eq. for L_t), computed on a round-2 record
of the world simulator (true r_t, v_t, d_t at the true pose s_t). This is the L_t the paper's
optimisation assumes known; the experiments use it directly, and ``make demo`` uses it to seed the
scheduler's loss map (a rehearsal of the operating round), which the running system then corrects
online from the losses it measures in image slots.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gsrmr_common.metrics import image_quality
from gsrmr_server.loss_map import LossMap
from gsrmr_server.mr.blend import jpeg_mr_loss, mr_image
from gsrmr_server.splatting.model import GaussianModel
from gsrmr_server.splatting.render import render
from gsrmr_sim.world.recorder import Round2Record


@dataclass
class SlotLoss:
    """GS loss of one slot and the images it compares."""

    t: int
    pose: tuple[float, float, float]
    loss: float
    psnr_db: float
    ssim: float
    truth_mr: np.ndarray  # m_t
    gs_mr: np.ndarray  # m_t with Φ(s_t) in place of r_t
    image_loss: float = float("nan")  # MR loss of the frame's JPEG composite (with ``jpeg_quality``)


def gs_losses(record: Round2Record, model: GaussianModel, background=(0.0, 0.0, 0.0),
              keep_images: bool = False, jpeg_quality: int | None = None) -> list[SlotLoss]:
    """L_t, PSNR and SSIM of the GS view for every slot of ``record``; with ``jpeg_quality`` also the loss an
    image slot would leave (:func:`gsrmr_server.mr.blend.jpeg_mr_loss`)."""
    out = []
    for rec in record:
        gs = render(model, rec.camera, background)
        truth = mr_image(rec.image, rec.virtual, rec.mask)
        gs_mr = mr_image(gs.rgb, rec.virtual, rec.mask)
        q = image_quality(truth, gs_mr)
        image_loss = float("nan")
        if jpeg_quality is not None:
            frame_u8 = np.clip(np.rint(rec.image * 255.0), 0, 255).astype(np.uint8)
            image_loss = jpeg_mr_loss(frame_u8, rec.virtual, rec.mask, jpeg_quality)
        out.append(SlotLoss(rec.t, rec.pose, q["loss"], q["psnr_db"], q["ssim"],
                            truth if keep_images else np.empty(0), gs_mr if keep_images else np.empty(0),
                            image_loss))
    return out


def loss_map_from(losses: list[SlotLoss], **kwargs) -> LossMap:
    """A loss map holding every surveyed slot (and, where measured, the mean image-slot loss)."""
    lm = LossMap(**kwargs)
    for s in losses:
        lm.add(*s.pose, s.loss)
    measured = [s.image_loss for s in losses if np.isfinite(s.image_loss)]
    if measured:
        lm.image_loss = float(np.mean(measured))
    return lm
