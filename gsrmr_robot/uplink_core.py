"""The robot's slot core (pure: no ROS): what to upload in one slot, and what it cost.

:meth:`UplinkCore.run_slot` takes what the robot knows at the start of slot k (:class:`SlotInputs`) and returns a
:class:`SlotDecision`: the pose key, the JPEG when ``x_k = 1`` and the energy-ledger row (``docs/nodes.md``, "The
robot"). Poses are ``base_link`` in ``map``, ``(a_m, b_m, theta_rad)`` (REP-103: x forward, y left, θ
counter-clockwise); stamps are ROS time in integer nanoseconds; powers in W, energies in J.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
import math

import numpy as np

from gsrmr_common.jpeg import encode_jpeg
from gsrmr_common.link_model import LinkBudget
from gsrmr_common.pose2d import Pose2D
from gsrmr_common.wire import LedgerRow, PoseKey, ScheduleMsg
from gsrmr_robot.ledger import EnergyLedger
from gsrmr_robot.scene_change import ChangeProbe, SceneChangeDetector

#: A stamp within this of the node's clock is taken to be on it (a driver stamping on another clock — device time, a
#: bag's — is judged by arrival only).
SAME_CLOCK_NS = 60 * 1_000_000_000


def stale(stamp_ns: int, arrival_ns: int, now_ns: int, max_age_ns: int) -> bool:
    """Whether a sample stamped ``stamp_ns`` that arrived at ``arrival_ns`` is older than ``max_age_ns`` at ``now_ns``
    (all on the node's clock): it arrived longer ago, or — its stamp on the node's clock (:data:`SAME_CLOCK_NS`) —
    was taken longer ago. After a stall the oldest samples queued meanwhile (in the socket, on the executor) are
    taken first, with a fresh arrival and a stamp from the stall's start."""
    if now_ns - arrival_ns > max_age_ns:
        return True
    return abs(now_ns - stamp_ns) <= SAME_CLOCK_NS and now_ns - stamp_ns > max_age_ns


class PoseHistory:
    """Recent odometry poses in ``map`` by stamp: the key of a slot is the pose when its frame was taken.

    Each pose also keeps when it arrived (the node's clock, ns): :meth:`at` with ``max_age_ns`` names no pose when
    the newest one is older than that (:func:`stale`: by arrival, and by stamp when the stamp is on the node's clock).
    A node that stalled (a starved process, a blocked executor) would otherwise key the slots after the stall with the
    pose from before it — up to the stall's length of driving behind the robot, which the server's pose-continuity
    rule then sees jump ahead at the next fresh key. Both ways occur under load: the slot timer runs before the
    queued odometry, or the oldest queued odometry runs first, arriving fresh with a stamp 2 s old."""

    def __init__(self, maxlen: int = 100) -> None:
        self._poses: deque[tuple[int, Pose2D]] = deque(maxlen=maxlen)
        self.latest: Pose2D | None = None
        self.latest_arrival_ns: int | None = None
        self.latest_stamp_ns: int | None = None

    def add(self, stamp_ns: int, pose: Pose2D, arrival_ns: int | None = None) -> bool:
        """Keep a pose (``arrival_ns``: when it arrived, default its stamp); a non-finite one is refused (returns
        False)."""
        if not all(math.isfinite(v) for v in pose):
            return False
        self.latest = pose
        self.latest_arrival_ns = int(stamp_ns if arrival_ns is None else arrival_ns)
        self.latest_stamp_ns = int(stamp_ns)
        self._poses.append((int(stamp_ns), pose))
        return True

    def at(self, stamp_ns: int | None, now_ns: int | None = None, max_age_ns: int | None = None) -> Pose2D | None:
        """The pose nearest in time to ``stamp_ns`` (the latest one when ``stamp_ns`` is None); None when there is none
        or — given ``now_ns`` and ``max_age_ns`` — the newest pose arrived more than ``max_age_ns`` before ``now_ns``
        (the odometry, or this node, stalled: no pose is known for now; :func:`stale`)."""
        sample = self.sample_at(stamp_ns, now_ns, max_age_ns)
        return None if sample is None else sample[1]

    def sample_at(self, stamp_ns: int | None, now_ns: int | None = None,
                  max_age_ns: int | None = None) -> tuple[int, Pose2D] | None:
        """As :meth:`at`, with the pose's stamp: ``(stamp_ns, pose)``."""
        if self.latest is None:
            return None
        if now_ns is not None and max_age_ns is not None and stale(self.latest_stamp_ns, self.latest_arrival_ns,
                                                                   now_ns, max_age_ns):
            return None
        if stamp_ns is None or not self._poses:
            return self.latest_stamp_ns, self.latest
        return min(self._poses, key=lambda item: abs(item[0] - stamp_ns))


@dataclass(frozen=True)
class SlotInputs:
    """What the robot knows at the start of ``slot``."""

    slot: int
    frame: np.ndarray | None  # H×W×3 uint8 RGB, None when no frame is fresh enough
    frame_stamp_ns: int | None  # its capture stamp
    pose: Pose2D | None  # at the frame's capture time (the latest pose when there is no frame)
    entry: tuple[int, float] | None  # (x, power_w) of the schedule, None when no schedule covers the slot
    measured_gain: float | None = None  # the radio's channel gain g = |h|² for this slot (None: not measured)
    gain_threshold: float | None = None  # the schedule's in-slot rule: image iff measured_gain ≥ this
    round_slot: int = -1  # the radio's index of this slot in the round (−1: unknown)
    uplink_queued: bool = False  # the last image is still unacknowledged (gsrmr_robot.uplink_backlog): hold back
    uplink_rate_bps: float = float("nan")  # the robot's estimate of the uplink throughput (for the ledger)
    correction_seq: int = 0  # the map → odom correction the pose was made with (for the ledger)


@dataclass(frozen=True)
class SlotDecision:
    """What the robot sends in one slot."""

    slot: int
    x: int  # 1 = image slot, 0 = key only
    key: PoseKey | None  # None without a pose
    jpeg: bytes | None  # the upload of an image slot (None in key slots or without a frame)
    row: LedgerRow  # the energy ledger's row for this slot
    scheduled: bool  # a schedule covered the slot
    publish_row: bool  # False when nothing at all was sent (no pose and no image)
    scene_changed: bool = False  # the slot's frame differed suddenly from the previous slot's (scene_change.py)


def covering_schedule(slot: int, newest: ScheduleMsg | None, before: ScheduleMsg | None) -> ScheduleMsg | None:
    """The schedule that decides ``slot``: the newest one, unless it does not cover the slot and the one before it
    does (a newer schedule that starts after a slot leaves that slot to the last plan made for it, not to the
    default upload). None when neither is there."""
    if newest is not None and newest.lookup(slot) is None and before is not None and before.lookup(slot) is not None:
        return before
    return newest


class UplinkCore:
    """Decides each slot's upload and books its energy; the node and ``bench/perf/soak.py``-style drivers call it alike.

    The slot's channel gain is the radio's measurement (``radio/channel_gain``; the simulator's
    ``gsrmr-sim-channel`` in simulation); without one the ledger books the expected gain ρ0·d^−α at the odometry
    position. Scene changes (``scene_change``, optional): when a slot's frame differs suddenly from the previous
    slot's and the rule sent only the key, an image goes in the first of the next ``change_wait_slots`` slots (that
    one included) whose measured gain is fair (:class:`~gsrmr_robot.scene_change.ChangeProbe`), so the server
    measures the change then instead of at the schedule's next image. An image sent for any reason ends the wait.
    """

    def __init__(self, link: LinkBudget, slot_s: float, jpeg_quality: int = 80,
                 default_upload_image: bool = True, scene_change: SceneChangeDetector | None = None,
                 change_wait_slots: int = 5) -> None:
        self.link = link
        self.jpeg_quality = int(jpeg_quality)
        self.default_upload_image = bool(default_upload_image)
        self.ledger = EnergyLedger(link.required_power_w, slot_s, link.bandwidth_hz, link.noise_w)
        self.scene_change = scene_change
        self.change_probe = ChangeProbe(link.rician_k, change_wait_slots)
        self.change_images = 0  # images sent for a scene change the rule would not have sent

    def run_slot(self, inputs: SlotInputs) -> SlotDecision:
        """The upload of one slot; every slot is booked in the ledger, whatever was sent."""
        if inputs.entry is None:
            x, power_w = int(self.default_upload_image), float("nan")
        else:
            x, power_w = inputs.entry
        pose = inputs.pose
        # the radio's measurement of this slot; without one, the expected gain at the odometry position
        gain = inputs.measured_gain
        if gain is None or not (math.isfinite(gain) and gain > 0):
            gain = self.link.mean_gain(pose[:2] if pose is not None else None)
        if inputs.entry is not None and inputs.gain_threshold is not None:
            # decided in the slot at the gain just measured (the expected one when the radio said nothing:
            # the rule, with its probing, keeps working; the plan's own x assumed the rule would run)
            x = int(gain >= inputs.gain_threshold)
        changed = self.scene_change is not None and self.scene_change.update(inputs.frame, inputs.frame_stamp_ns)
        if changed:
            self.change_probe.changed(inputs.slot)
        if (x == 0 and inputs.entry is not None and inputs.frame is not None and self.change_probe.wants_image(
                inputs.slot, gain, self.link.mean_gain(pose[:2] if pose is not None else None))):
            x = 1  # the view changed: let the server measure it now (UplinkCore's docstring, "Scene changes")
            for_change = True
        else:
            for_change = False
        # no fresh frame (before the camera's first, or a late one): nothing but the key can go, and the ledger
        # says so — a row claiming an image here would tell the scheduler an image left that the server never
        # composes: its link cap would read the link as too slow to deliver, and its probe clock would restart
        # without a measurement (docs/scheduling.md, "The live loop", item 10)
        if x == 1 and inputs.frame is None:
            x = 0
        # an image asked for while the last one is still queued on the link is held back (key only): on a link
        # slower than one image per slot, images then leave as fast as it delivers them instead of piling up
        held_back = int(x == 1 and inputs.uplink_queued)
        if held_back:
            x = 0
        elif x == 1:
            self.change_probe.image_sent()
            self.change_images += int(for_change)
        frame = inputs.frame
        # Encoded in key slots too: the ledger books what an image would have cost (upload-all baseline).
        jpeg = encode_jpeg(frame, self.jpeg_quality) if frame is not None else None
        upload = jpeg if x == 1 else None
        key = PoseKey(inputs.slot, *pose) if pose is not None else None
        stamp_s = inputs.frame_stamp_ns / 1e9 if inputs.frame_stamp_ns is not None and frame is not None \
            else float("nan")
        row = self.ledger.record(inputs.slot, x, power_w, len(upload) if upload is not None else None, gain,
                                 len(jpeg) if jpeg is not None else None, stamp_s, inputs.round_slot, held_back,
                                 inputs.uplink_rate_bps, int(changed), inputs.correction_seq)
        return SlotDecision(inputs.slot, x, key, upload, row, inputs.entry is not None,
                            publish_row=key is not None or upload is not None, scene_changed=changed)
