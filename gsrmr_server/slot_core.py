"""The server's slot core (pure: no ROS): one slot's uploads in, the slot's outcome out.

:meth:`ServerCore.process` composes m̂_k (:class:`~gsrmr_server.compose.MRComposer`), converts it to
8 bit once and returns a :class:`SlotOutcome`: the image, its JPEG (encoded once, on first use), the
typed ``slots.csv`` row (:class:`SlotRow`) and the loss sample for the scheduler (image slots with a
key). :meth:`ServerCore.score` adds — in simulation, given the true camera frame — the quality of m̂_k
against the true m_k; it is separate so that a node can publish m̂_k first. The node
(:mod:`gsrmr_server.server_node`) gathers the inputs, publishes and records; tests and benches call the
core directly.

Units: stamps in seconds since the clock's epoch (``stamp_s``), poses in ``map`` (m, rad), powers in W,
energies in J, latency in ms.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
import math

import numpy as np

from gsrmr_common.camera import Intrinsics
from gsrmr_common.jpeg import encode_jpeg
from gsrmr_common.link_model import BANDWIDTH_HZ, NOISE_W, SLOT_S, required_power_w
from gsrmr_common.metrics import image_quality
from gsrmr_common.wire import POSE_KEY_BITS, LedgerRow, LossSample, PoseKey
from gsrmr_server.compose import ComposedSlot, MRComposer, to_u8
from gsrmr_server.mr.blend import jpeg_mr_loss, mr_image
from gsrmr_server.mr.content import AgentsView, load_mr_content
from gsrmr_server.server_params import ServerParameters
from gsrmr_server.slot_row import SlotRow
from gsrmr_server.splatting.model import GaussianModel
from gsrmr_server.uplink import SlotUploads, UplinkAssembler


@dataclass
class SlotOutcome:
    """Everything one slot produced."""

    composed: ComposedSlot
    mr_u8: np.ndarray  # H×W×3 uint8 RGB: what is published on mr/image
    row: SlotRow  # latency_ms is filled in by whoever publishes
    loss_sample: LossSample | None  # for the scheduler's loss map
    jpeg_quality: int = 85
    quality: dict[str, float] | None = None  # {loss, psnr_db, ssim} against the truth (ServerCore.score)
    _jpeg: bytes | None = field(default=None, repr=False)

    @property
    def jpeg(self) -> bytes:
        """``mr_u8`` as JPEG (what ``mr/image/compressed`` carries and the recording stores), encoded once."""
        if self._jpeg is None:
            self._jpeg = encode_jpeg(self.mr_u8, self.jpeg_quality)
        return self._jpeg


class ServerCore:
    """Composes, encodes and scores one slot at a time (see the module docstring)."""

    def __init__(self, composer: MRComposer, jpeg_quality: int = 85, measure_loss: bool = True, *,
                 slot_s: float = SLOT_S, bandwidth_hz: float = BANDWIDTH_HZ, noise_w: float = NOISE_W,
                 hindsight_jpeg_quality: int | None = None) -> None:
        """``hindsight_jpeg_quality``: when set (simulation), :meth:`score` also measures what the other
        choice would have given in each slot (the robot's JPEG quality of the true frame, and the GS render)."""
        self.composer = composer
        self.jpeg_quality = int(jpeg_quality)
        self.measure_loss = bool(measure_loss)
        self.slot_s, self.bandwidth_hz, self.noise_w = float(slot_s), float(bandwidth_hz), float(noise_w)
        self.hindsight_jpeg_quality = hindsight_jpeg_quality

    def _energy_j(self, bits: float, gain: float) -> float | None:
        if not (gain > 0 and math.isfinite(gain)):
            return None
        e = self.slot_s * required_power_w(bits, gain, self.slot_s, self.bandwidth_hz, self.noise_w)
        return e if math.isfinite(e) else None

    def process(self, uploads: SlotUploads, best_pose: PoseKey | None, *, time_s: float, stamp_s: float,
                ledger: LedgerRow | None = None, scheduled_x: int | None = None) -> SlotOutcome:
        """Slot ``uploads.slot``: ``best_pose`` is the fallback pose, ``time_s`` the round time (moving
        agents), ``stamp_s`` the slot start, ``ledger`` the robot's row for the slot, ``scheduled_x`` what
        the schedule said (recorded when no ledger row came)."""
        result = self.composer.compose(uploads, best_pose, time_s, measure_loss=self.measure_loss)
        sample = None
        if result.gs_loss is not None and result.pose is not None:
            p = result.pose
            sample = LossSample(result.slot, p.a_m, p.b_m, p.theta_rad, result.gs_loss)
        pose = result.pose
        row = SlotRow(
            slot=result.slot, stamp_s=stamp_s,
            x=ledger.x if ledger else scheduled_x,
            power_w=ledger.power_w if ledger else None,
            bytes_sent=ledger.bits_sent // 8 if ledger else None,
            energy_j=ledger.energy_j if ledger else None,
            source=result.source,
            pose_a_m=pose.a_m if pose else None, pose_b_m=pose.b_m if pose else None,
            pose_theta_rad=pose.theta_rad if pose else None,
            faults=tuple(result.faults), gs_loss=result.gs_loss,
            energy_upload_all_j=ledger.upload_all_energy_j if ledger else None,
            channel_gain=ledger.gain if ledger else None,
            energy_image_j=(self._energy_j(ledger.upload_all_bits + POSE_KEY_BITS, ledger.gain)
                            if ledger and ledger.upload_all_bits > 0 else None),
            energy_key_j=self._energy_j(POSE_KEY_BITS, ledger.gain) if ledger else None,
            round_slot=ledger.round_slot if ledger else None,
            held_back=ledger.held_back if ledger else None,
            uplink_rate_bps=ledger.uplink_rate_bps if ledger and math.isfinite(ledger.uplink_rate_bps) else None)
        return SlotOutcome(result, to_u8(result.mr), row, sample, self.jpeg_quality)

    def score(self, outcome: SlotOutcome, truth_frame: np.ndarray | None) -> SlotOutcome:
        """Add the quality of the published m̂ against the truth built from ``truth_frame`` (the true camera
        image r_k, H×W×3 uint8; simulation only) to the outcome and its row; None leaves them empty.

        With ``hindsight_jpeg_quality`` set, also the loss either choice would have had in this slot:
        ``gs_truth_loss`` (the composite from the GS render at the slot's pose) and ``image_truth_loss``
        (from the true frame's JPEG at that quality; in an image slot, the published m̂ itself)."""
        quality = truth_quality(outcome.composed, outcome.mr_u8, truth_frame) if truth_frame is not None else None
        outcome.quality = quality
        if quality is None:
            return outcome
        extra: dict[str, float] = {}
        c = outcome.composed
        if self.hindsight_jpeg_quality is not None and c.gs_mr is not None:
            truth = mr_image(truth_frame.astype(np.float32) / 255.0, c.virtual, c.mask)
            gs_u8 = outcome.mr_u8 if c.source != "image" else to_u8(c.gs_mr)
            extra["gs_truth_loss"] = image_quality(truth, gs_u8.astype(np.float32) / 255.0)["loss"]
            if c.source == "image":
                extra["image_truth_loss"] = quality["loss"]
            else:
                extra["image_truth_loss"] = jpeg_mr_loss(truth_frame, c.virtual, c.mask, self.hindsight_jpeg_quality)
        outcome.row = replace(outcome.row, loss=quality["loss"], psnr_db=quality["psnr_db"], ssim=quality["ssim"],
                              **extra)
        return outcome


def build_server_core(params: ServerParameters, model: GaussianModel, intrinsics: Intrinsics, *,
                      warm_up: bool = True) -> ServerCore:
    """The slot core as :class:`~gsrmr_server.server_node.ServerNode` builds it from its parameters (MR content,
    background, camera mount, render threads, JPEG quality, link), at the render ``intrinsics``; ``warm_up``
    composes one slot first (compiles the rasterizer and the ray caster, ~1.5 s cold)."""
    composer = MRComposer(model, AgentsView(load_mr_content(params.mr_content)), intrinsics, params.camera_mount,
                          tuple(params.background_rgb), render_threads=params.render_threads_or_all)  # type: ignore[arg-type]
    if warm_up:
        composer.compose(SlotUploads(0), PoseKey(0, 0.0, 0.0, 0.0), 0.0, measure_loss=False)
    return ServerCore(composer, params.jpeg_quality, params.measure_loss, slot_s=params.slot_s,
                      bandwidth_hz=params.link.bandwidth_hz, noise_w=params.link.noise_w,
                      hindsight_jpeg_quality=params.hindsight_jpeg_quality_or_off)


def count_composition_faults(uplink: UplinkAssembler, uploads: SlotUploads, outcome: SlotOutcome) -> None:
    """Count in ``uplink`` the faults found while composing (refused JPEGs) that the uploads did not carry."""
    for fault in outcome.composed.faults:
        if fault not in uploads.faults:
            uplink.count(fault)


def truth_quality(result: ComposedSlot, mr_u8: np.ndarray, frame: np.ndarray) -> dict[str, float] | None:
    """Loss, PSNR and SSIM of the published m̂ (8 bit) against the true m = d·r + (1 − d)·v, with r the
    true camera frame and v, d the slot's own virtual view (None when the frame has another size)."""
    if frame.shape[:2] != result.mr.shape[:2]:
        return None
    truth = mr_image(frame.astype(np.float32) / 255.0, result.virtual, result.mask)
    return image_quality(truth, np.asarray(mr_u8, np.float32) / 255.0)


def match_frame(frames: list[tuple[int, np.ndarray]], ledger: LedgerRow | None,
                slot_start_ns: int) -> np.ndarray | None:
    """The true camera frame of a slot among ``(stamp_ns, frame)``: the one whose stamp the robot's ledger row
    names (within 1 ms: the row carries it in float seconds), else the newest one at the slot start."""
    used = ledger.frame_stamp_s if ledger else None
    if used is not None and math.isfinite(used):
        match = [f for s, f in frames if abs(s / 1e9 - used) < 1e-3]
    else:
        match = [f for s, f in frames if s <= slot_start_ns + 5_000_000][-1:]
    return match[0] if match else None
