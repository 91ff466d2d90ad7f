"""Scoring an MR image against a reference real frame (pure, no ROS): a deployment library.

A reference frame r of the real camera is, in simulation, the true camera frame, in a deployment survey a frame
taken for the purpose. :func:`reference_quality` scores a slot's m̂ against m = d·r + (1 − d)·v with the slot's own
v and d, :func:`score_slot` adds the hindsight losses (:mod:`gsrmr_sim.hindsight`), and :class:`SlotScorer`
rebuilds a published slot from its :class:`~gsrmr_common.wire.MRSlotInfo`, so that another process can score the
server's images without adding to the server's work.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from gsrmr_common.metrics import image_quality
from gsrmr_common.wire import MRSlotInfo, RealSource
from gsrmr_server.compose import ComposedSlot, MRComposer, to_u8
from gsrmr_server.mr.blend import jpeg_mr_loss, mr_image
from gsrmr_server.slot_row import SlotScore
from gsrmr_server.uplink import SlotUploads


def reference_quality(mr_u8: np.ndarray, virtual: np.ndarray, mask: np.ndarray,
                      reference_u8: np.ndarray) -> dict[str, float] | None:
    """``{loss, psnr_db, ssim}`` of the published m̂ (H×W×3 uint8 RGB, as on ``mr/image``) against
    m = d·r + (1 − d)·v with r the reference frame (H×W×3 uint8 RGB) and v, d the slot's own virtual view; None when
    r has another size. ``loss`` is the 3DGS image loss 0.8·L1 + 0.2·(1 − SSIM), ``psnr_db`` in dB."""
    if reference_u8.shape[:2] != mr_u8.shape[:2]:
        return None
    truth = mr_image(reference_u8.astype(np.float32) / 255.0, virtual, mask)
    return image_quality(truth, np.asarray(mr_u8, np.float32) / 255.0)


def score_slot(composed: ComposedSlot, mr_u8: np.ndarray, reference_u8: np.ndarray | None,
               hindsight_jpeg_quality: int | None = None) -> SlotScore:
    """The scores of slot ``composed.slot`` — its v, d, GS composite and source from ``composed``, m̂ =
    ``mr_u8`` — against ``reference_u8`` (None, or a frame of another size: nothing measured); with
    ``hindsight_jpeg_quality`` and a GS composite, the hindsight losses too — what either choice would have left
    in the slot, the inputs of the hindsight optimum: ``gs_truth_loss``, the loss of the composite from the GS render
    at the slot's pose, and ``image_truth_loss``, that of the composite from the reference frame's JPEG at that
    quality (the robot's; in an image slot, the published m̂ itself)."""
    quality = reference_quality(mr_u8, composed.virtual, composed.mask, reference_u8) \
        if reference_u8 is not None else None
    if quality is None:
        return SlotScore(composed.slot)
    extra: dict[str, float] = {}
    if hindsight_jpeg_quality is not None and composed.gs_mr is not None:
        truth = mr_image(reference_u8.astype(np.float32) / 255.0, composed.virtual, composed.mask)
        image_slot = composed.source == RealSource.IMAGE
        gs_u8 = to_u8(composed.gs_mr) if image_slot else mr_u8  # render/fallback: m̂ is the GS composite
        extra["gs_truth_loss"] = image_quality(truth, gs_u8.astype(np.float32) / 255.0)["loss"]
        extra["image_truth_loss"] = quality["loss"] if image_slot else jpeg_mr_loss(
            reference_u8, composed.virtual, composed.mask, hindsight_jpeg_quality)
    return SlotScore(composed.slot, quality["loss"], quality["psnr_db"], quality["ssim"], **extra)


class SlotScorer:
    """Scores published slots from their :class:`~gsrmr_common.wire.MRSlotInfo`: rebuilds a slot's v, d and GS
    composite from the pose it was composed at, its MR content time and its source.

    ``composer`` must hold what the server composes with (model, MR content, mount, background, and the
    intrinsics of the robot's ``camera_info``); ``hindsight_jpeg_quality`` as :func:`score_slot`."""

    def __init__(self, composer: MRComposer, hindsight_jpeg_quality: int | None = None) -> None:
        self.composer = composer
        self.hindsight_jpeg_quality = hindsight_jpeg_quality

    def rebuild(self, info: MRSlotInfo) -> ComposedSlot:
        """The slot's composition at its pose and MR content time: v, d and the GS composite (its ``source``
        is the published one). Without a pose, v = 0 and d = 1, as the server had."""
        composed = self.composer.compose(SlotUploads(info.slot, key=info.pose), None, info.content_time_s,
                                         measure_loss=False)
        return replace(composed, source=info.source)

    def size_problem(self, mr_u8: np.ndarray) -> str | None:
        """Why an MR image cannot be rebuilt with the composer's intrinsics (another size), or None."""
        k = self.composer.intrinsics
        if mr_u8.shape[:2] != (k.height, k.width):
            return f"MR image is {mr_u8.shape[1]}×{mr_u8.shape[0]}, the intrinsics {k.width}×{k.height}"
        return None

    def score(self, info: MRSlotInfo, mr_u8: np.ndarray, reference_u8: np.ndarray | None) -> SlotScore:
        """The scores of the published ``mr_u8`` of slot ``info.slot`` against ``reference_u8`` (nothing is
        rendered without a usable reference). ValueError when the MR image does not fit the intrinsics."""
        problem = self.size_problem(mr_u8)
        if problem:
            raise ValueError(f"slot {info.slot}: {problem}")
        if reference_u8 is None or reference_u8.shape[:2] != mr_u8.shape[:2]:
            return SlotScore(info.slot)
        return score_slot(self.rebuild(info), mr_u8, reference_u8, self.hindsight_jpeg_quality)
