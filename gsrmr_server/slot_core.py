"""The server's slot core (pure: no ROS): one slot's uploads in, the slot's outcome out (:class:`ServerCore`).

The node (:mod:`gsrmr_server.server_node`) gathers the inputs, publishes and records; tests and benches call the
core directly. Units: stamps in seconds since the clock's epoch (``stamp_s``), poses in ``map`` (m, rad), powers in
W, energies in J, latency in ms.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math

import numpy as np

from gsrmr_common.camera import CameraMount, Intrinsics
from gsrmr_common.jpeg import encode_jpeg
from gsrmr_common.link_model import BANDWIDTH_HZ, NOISE_W, SLOT_S, required_power_w
from gsrmr_common.wire import POSE_KEY_BITS, LedgerRow, LossSample, MRSlotInfo, PoseKey
from gsrmr_server.compose import ComposedSlot, MRComposer, to_u8
from gsrmr_server.compose_levels import LevelChoice
from gsrmr_server.mr.content import AgentsView, load_mr_content
from gsrmr_server.server_params import ServerParameters
from gsrmr_server.slot_row import SlotRow
from gsrmr_server.uplink import SlotUploads, UplinkAssembler
from gsrmr_splat.model import GaussianModel

#: Intrinsics of the start-up warm-up render, before the robot's camera_info arrives (compiles the kernels).
WARM_UP_INTRINSICS = Intrinsics.from_fov(32, 24, 1.2)


@dataclass
class SlotOutcome:
    """Everything one slot produced."""

    composed: ComposedSlot
    mr_u8: np.ndarray  # H×W×3 uint8 RGB: what is published on mr/image
    row: SlotRow  # latency_ms is filled in by whoever publishes
    loss_sample: LossSample | None  # for the scheduler's loss map
    info: MRSlotInfo  # what m̂ was composed from (published on mr/slot_info)
    jpeg_quality: int = 85
    _jpeg: bytes | None = field(default=None, repr=False)

    @property
    def jpeg(self) -> bytes:
        """``mr_u8`` as JPEG (what ``mr/image/compressed`` carries and the recording stores), encoded once."""
        if self._jpeg is None:
            self._jpeg = encode_jpeg(self.mr_u8, self.jpeg_quality)
        return self._jpeg


class ServerCore:
    """Composes and encodes one slot at a time.

    :meth:`process` composes m̂_k (:class:`~gsrmr_server.compose.MRComposer`), converts it to 8 bit once and returns
    a :class:`SlotOutcome`: the image, its JPEG (encoded once, on first use), the typed ``slots.csv`` row
    (:class:`SlotRow`), the loss sample for the scheduler (image slots with a key) and the slot's
    :class:`~gsrmr_common.wire.MRSlotInfo` (what m̂_k was composed from: a monitor, such as the simulation's scorer,
    rebuilds v_k and d_k from it; scoring is :mod:`gsrmr_server.scoring`).
    """

    def __init__(self, composer: MRComposer, jpeg_quality: int = 85, measure_loss: bool = True, *,
                 slot_s: float = SLOT_S, bandwidth_hz: float = BANDWIDTH_HZ, noise_w: float = NOISE_W) -> None:
        self.composer = composer
        self.jpeg_quality = int(jpeg_quality)
        self.measure_loss = bool(measure_loss)
        self.slot_s, self.bandwidth_hz, self.noise_w = float(slot_s), float(bandwidth_hz), float(noise_w)

    def _energy_j(self, bits: float, gain: float) -> float | None:
        if not (gain > 0 and math.isfinite(gain)):
            return None
        e = self.slot_s * required_power_w(bits, gain, self.slot_s, self.bandwidth_hz, self.noise_w)
        return e if math.isfinite(e) else None

    def process(self, uploads: SlotUploads, best_pose: PoseKey | None, *, time_s: float, stamp_s: float,
                ledger: LedgerRow | None = None, scheduled_x: int | None = None,
                level: LevelChoice | None = None) -> SlotOutcome:
        """Slot ``uploads.slot``: ``best_pose`` is the fallback pose, ``time_s`` the MR content time (moving
        agents; seconds since the first composed slot), ``stamp_s`` the slot start, ``ledger`` the robot's row
        for the slot, ``scheduled_x`` what the schedule said (recorded when no ledger row came), ``level`` the
        composition level chosen for it (None: full size; a degraded level measures no loss sample)."""
        degraded = level is not None and level.degraded
        result = self.composer.compose(uploads, best_pose, time_s, measure_loss=self.measure_loss and not degraded,
                                       render_scale=level.render_scale if level is not None else 1.0)
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
            uplink_rate_bps=ledger.uplink_rate_bps if ledger and math.isfinite(ledger.uplink_rate_bps) else None,
            scene_change=ledger.scene_change if ledger else None,
            frame_stamp_s=ledger.frame_stamp_s if ledger and math.isfinite(ledger.frame_stamp_s) else None,
            correction_seq=ledger.correction_seq if ledger else None,
            level=level.level if level is not None else None,
            time_left_ms=level.time_left_ms if level is not None else None,
            predicted_ms=level.predicted_ms if level is not None else None)
        info = MRSlotInfo.of(result.slot, result.source, result.pose, time_s, level.level if level is not None else 0)
        return SlotOutcome(result, to_u8(result.mr), row, sample, info, self.jpeg_quality)


def build_composer(model: GaussianModel, intrinsics: Intrinsics, *, mr_content: str, mount: CameraMount,
                   background_rgb: tuple[float, ...], render_threads: int | None = None,
                   warm_up: bool = True) -> MRComposer:
    """The server's composer: ``model``, the MR content ``mr_content`` (a name in ``config/mr`` or a YAML path)
    as :class:`~gsrmr_server.mr.content.AgentsView`, the camera ``mount``, the GS ``background_rgb``, at the
    render ``intrinsics`` (``render_threads`` None = every core); ``warm_up`` composes one slot first
    (compiles the rasterizer and the ray caster, ~1.5 s cold)."""
    composer = MRComposer(model, AgentsView(load_mr_content(mr_content)), intrinsics, mount,
                          tuple(background_rgb), render_threads=render_threads)  # type: ignore[arg-type]
    if warm_up:
        composer.compose(SlotUploads(0), PoseKey(0, 0.0, 0.0, 0.0), 0.0, measure_loss=False)
    return composer


def build_server_core(params: ServerParameters, model: GaussianModel, intrinsics: Intrinsics, *,
                      warm_up: bool = True) -> ServerCore:
    """The slot core as :class:`~gsrmr_server.server_node.ServerNode` builds it from its parameters (MR content,
    background, camera mount, render threads, JPEG quality, link): :func:`build_composer` at ``intrinsics``."""
    composer = build_composer(model, intrinsics, mr_content=params.mr_content, mount=params.camera_mount,
                              background_rgb=params.background_rgb, render_threads=params.render_threads_or_all,
                              warm_up=warm_up)
    return ServerCore(composer, params.jpeg_quality, params.measure_loss, slot_s=params.slot_s,
                      bandwidth_hz=params.link.bandwidth_hz, noise_w=params.link.noise_w)


def count_composition_faults(uplink: UplinkAssembler, uploads: SlotUploads, outcome: SlotOutcome) -> None:
    """Count in ``uplink`` the faults found while composing (refused JPEGs) that the uploads did not carry."""
    for fault in outcome.composed.faults:
        if fault not in uploads.faults:
            uplink.count(fault)
