"""The MR loss of one real frame as the live server would compose and score it (pure, no ROS): :func:`frame_loss`, the
scoring of the deployment survey (:mod:`gsrmr_offline.deployment_survey`) and of the simulator's survey
(``gsrmr_sim.survey``). Why an image slot's sample bias matters: docs/scheduling.md, "The live loop", item 7.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gsrmr_common.jpeg import encode_jpeg
from gsrmr_common.wire import PoseKey, RealSource
from gsrmr_server.compose import ComposedSlot, MRComposer, to_u8
from gsrmr_server.scoring import score_slot
from gsrmr_server.slot_row import SlotScore
from gsrmr_server.uplink import SlotUploads


@dataclass(frozen=True)
class FrameLoss:
    """One frame's scores: the key slot's GS loss L, PSNR [dB] and SSIM, and the image slot's loss J (NaN when
    no JPEG quality was given)."""

    loss: float
    psnr_db: float
    ssim: float
    image_loss: float = float("nan")
    sample_bias: float = float("nan")  # the image slot's loss sample minus its GS composite's loss vs the frame


def _composed_score(composer: MRComposer, uploads: SlotUploads, frame_u8: np.ndarray, content_time_s: float,
                    measure_loss: bool = False,
                    hindsight_jpeg_quality: int | None = None) -> tuple[ComposedSlot, SlotScore]:
    """One slot composed by ``composer`` (with the server's loss sample when ``measure_loss``) and scored against
    ``frame_u8``; ValueError when the frame has another size than the composer renders or the server refuses the
    slot's JPEG."""
    composed = composer.compose(uploads, None, content_time_s, measure_loss=measure_loss)
    if uploads.jpeg is not None and composed.source != RealSource.IMAGE:
        raise ValueError(f"frame {uploads.slot}: the server refused the frame's JPEG "
                         f"({', '.join(str(f) for f in composed.faults)})")
    score = score_slot(composed, to_u8(composed.mr), frame_u8, hindsight_jpeg_quality)
    if not score.scored:
        k = composer.intrinsics
        raise ValueError(f"frame {uploads.slot}: the frame is {frame_u8.shape[1]}×{frame_u8.shape[0]}, the composer "
                         f"renders {k.width}×{k.height}")
    return composed, score




def frame_loss(composer: MRComposer, frame_u8: np.ndarray, pose: PoseKey, *, content_time_s: float,
               jpeg_quality: int | None, image_pose: PoseKey | None = None) -> FrameLoss:
    """L, PSNR, SSIM of the key slot at ``pose`` and, with ``jpeg_quality``, J and the sample bias of the image slot.

    Both slots are composed with the server's composer (``composer``: an
    :class:`~gsrmr_server.compose.MRComposer`, the pipeline of :meth:`gsrmr_server.slot_core.ServerCore.process`)
    at the MR content time ``content_time_s``, its camera the pose key ∘ the composer's ``mount`` at its
    ``intrinsics``, and each is scored as the server scores a slot (:func:`gsrmr_server.scoring.score_slot`)
    against the composite m = d·r + (1 − d)·v of the frame r with the slot's own virtual view v and mask d:

    * the key slot (pose key only): m̂ = d·Φ(s) + (1 − d)·v, published in 8 bit; its loss is the GS loss L a loss
      map holds;
    * the image slot (the pose key and the robot's JPEG of r at ``jpeg_quality``): m̂ from the decoded JPEG; its
      loss is J, what an image slot leaves (a loss map's ``image_loss``); its sample bias is the live server's loss
      sample (its GS composite against the composite of the decoded JPEG, all it has) minus the loss of the same GS
      composite against the frame's composite (what the loss budget counts): a loss map's ``sample_offset``.

    Losses are the MR loss 0.8·L1 + 0.2·(1 − SSIM) (:func:`gsrmr_common.metrics.mr_loss`); PSNR in dB.

    ``frame_u8``: the real frame, H×W×3 uint8 RGB at the composer's intrinsics; ``pose``: the pose key (``map``:
    a_m, b_m, theta_rad; its ``slot`` names the frame in messages); ``content_time_s``: the MR content's time
    [s since the round start]; ``image_pose``: the key the image slot carries (default ``pose``). Raises
    ValueError for a frame of another size or a JPEG the server refuses."""
    _, key = _composed_score(composer, SlotUploads(pose.slot, key=pose), frame_u8, content_time_s)
    image_loss = sample_bias = float("nan")
    if jpeg_quality is not None:
        jpeg = encode_jpeg(np.ascontiguousarray(frame_u8), int(jpeg_quality))
        composed, image = _composed_score(composer, SlotUploads(pose.slot, key=image_pose or pose, jpeg=jpeg),
                                          frame_u8, content_time_s, measure_loss=True,
                                          hindsight_jpeg_quality=int(jpeg_quality))
        image_loss = float(image.loss)  # type: ignore[arg-type]
        if composed.gs_loss is not None and image.gs_truth_loss is not None:
            sample_bias = float(composed.gs_loss) - float(image.gs_truth_loss)
    return FrameLoss(float(key.loss), float(key.psnr_db), float(key.ssim), image_loss,  # type: ignore[arg-type]
                     sample_bias)
