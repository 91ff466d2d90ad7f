"""One slot of the server's record (pure, light): the typed row behind ``slots.csv``.

The CSV columns are this dataclass's fields in order (:data:`SLOT_ROW_COLUMNS`); the codec is
:mod:`gsrmr_server.recording`. :class:`SlotScore` is a slot's quality against a reference frame
(:mod:`gsrmr_server.scoring`): in simulation the scorer's ``scores.csv``, which the demo's report joins in.
Units are in the names: seconds, watts, joules, metres, radians, ms.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

from gsrmr_common.wire import RealSource, UplinkFault


@dataclass(frozen=True)
class SlotRow:
    """One row of ``slots.csv`` (column order = field order); None = empty cell."""

    slot: int
    stamp_s: float  # slot start [s, ROS time]
    x: int | None = None  # what the robot did (its ledger row), else what the schedule said
    power_w: float | None = None  # transmit power the robot needed for what it sent
    bytes_sent: int | None = None
    energy_j: float | None = None
    loss: float | None = None  # MR loss of m̂ against the true m (simulation: the scorer's, joined by the report)
    psnr_db: float | None = None
    ssim: float | None = None
    source: RealSource | None = None  # where r̂ came from
    pose_a_m: float | None = None  # the pose m̂ was rendered at (map)
    pose_b_m: float | None = None
    pose_theta_rad: float | None = None
    latency_ms: float | None = None  # slot start → m̂ published
    faults: tuple[UplinkFault, ...] = ()
    gs_loss: float | None = None  # measured L_t (image slots with a key)
    energy_upload_all_j: float | None = None  # the same frame uploaded as an image (the RoboMR reference)
    channel_gain: float | None = None  # g = |h|² the robot's ledger booked the slot at (the radio's measurement)
    # hindsight (what either choice would have given in this slot): energies from the robot's ledger row, losses
    # from the simulation's scorer (joined by the report; the server leaves them empty):
    energy_image_j: float | None = None  # this slot's JPEG + key at channel_gain
    energy_key_j: float | None = None  # the key alone at channel_gain
    gs_truth_loss: float | None = None  # MR loss vs the truth of the composite from the GS render
    image_truth_loss: float | None = None  # … and of the composite from the decoded JPEG of the true frame
    scored: int | None = None  # 1 = a slot of the scored round (set by the demo's report), 0 = outside it
    round_slot: int | None = None  # the radio's index of the slot in the round (its ledger; −1 before it)
    held_back: int | None = None  # 1: an image was asked for, the robot sent the key (its last image still queued)
    uplink_rate_bps: float | None = None  # the robot's estimate of the uplink throughput from image acks
    scene_change: int | None = None  # 1: the robot's scene-change test fired on this slot's frame (its ledger)
    frame_stamp_s: float | None = None  # capture stamp of the frame the key stands for [s, ROS time] (its ledger)
    correction_seq: int | None = None  # the map → odom correction the key was made with (its ledger; 0: none)
    level: int | None = None  # composition level (gsrmr_server.compose_levels: 0 full, 1 half, 2 quarter size)
    time_left_ms: float | None = None  # time before τ when the level was chosen (negative: already late)
    predicted_ms: float | None = None  # the level's predicted time, choice → m̂ published
    compose_ms: float | None = None  # the time it took, choice → m̂ published


SLOT_ROW_COLUMNS = tuple(f.name for f in fields(SlotRow))


@dataclass(frozen=True)
class SlotScore:
    """One slot's scores against a reference frame (:mod:`gsrmr_server.scoring`; None = not measured: no
    reference, or hindsight off): the columns of ``slots.csv`` the simulation's scorer fills."""

    slot: int
    loss: float | None = None  # 3DGS image loss of m̂ against m
    psnr_db: float | None = None
    ssim: float | None = None
    gs_truth_loss: float | None = None  # hindsight: the composite from the GS render at the slot's pose
    image_truth_loss: float | None = None  # hindsight: the composite from the reference frame's JPEG

    @property
    def scored(self) -> bool:
        """Whether m̂ was measured against a reference."""
        return self.loss is not None

    def columns(self) -> dict[str, float | None]:
        """The scores by column name (:data:`SCORE_COLUMNS` but ``slot``)."""
        return {name: getattr(self, name) for name in SCORE_COLUMNS[1:]}


#: The columns of a slot's scores (``slot`` first): a subset of :data:`SLOT_ROW_COLUMNS`.
SCORE_COLUMNS = tuple(f.name for f in fields(SlotScore))
