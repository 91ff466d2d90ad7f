"""The simulation scorer's parameters and backlog (pure: no ROS); the node is :mod:`gsrmr_sim.world.scorer_node`.

:class:`ScoreBacklog` holds what the scorer receives until it scores a slot. Which frame is the truth, and why
the scorer waits for the round to end: docs/world.md, "The simulation's scorer".
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
import threading
from typing import Any

import numpy as np

from gsrmr_common.camera import CameraMount
from gsrmr_common.link_model import SLOT_S
from gsrmr_common.mount_params import MOUNT_PREFIX, CameraMountParameters
from gsrmr_common.node_help import Endpoint, NodeInterface, ParameterGroup
from gsrmr_common.node_params import NodeParameters, ros_parameter
from gsrmr_common.slot_clock import SlotClock
from gsrmr_common.wire import LedgerRow, MRSlotInfo
from gsrmr_common.writer_admission import writer_list_problem
from gsrmr_server.server_params import ServerParameters
from gsrmr_sim.truth_frames import match_frame

#: Seconds of true frames kept before the first MR image arrives (the server may start a few slots behind).
IDLE_FRAMES_S = 10.0


@dataclass(frozen=True)
class ScorerParameters(NodeParameters):
    """Every parameter of ``gsrmr-sim-scorer`` (ROS names; units in the names). ``model_path``, ``mr_content``,
    ``background_rgb`` and ``camera_mount.*`` must be the server's (``gsrmr_sim.sim_stack`` gives both the same)."""

    slot_s: float = ros_parameter(SLOT_S, "Slot length τ [s] (the server's): the slot an mr/image stamp names",
                                  min_value=0.01, max_value=10.0, read_only=True)
    model_path: str = ros_parameter("", "The server's Gaussian-splatting model (.ply); set it when the server's "
                                    "model changes: slots scored afterwards use the new one")
    mr_content: str = ros_parameter("sandbox", "The server's MR content (name in config/mr or a YAML path)",
                                    read_only=True)
    background_rgb: tuple[float, ...] = ros_parameter((0.5, 0.55, 0.6), "The server's GS background, linear RGB",
                                                      read_only=True)
    hindsight_jpeg_quality: int = ros_parameter(
        0, "Also score what the other choice would have given in each slot (the GS render, and the true frame as a "
        "JPEG of this quality = the robot's) for the hindsight optimum; 0 = off", min_value=0, max_value=100,
        read_only=True)
    truth_dir: str = ros_parameter(
        "", "Read the true frames from this folder (the mock camera's truth_dir, the simulation backplane) instead "
        "of subscribing to camera/image_raw; '' = subscribe", read_only=True)
    record_dir: str = ros_parameter("", "Append one row per slot to scores.csv here ('' = no file, the log only)",
                                    read_only=True)
    queue_slots: int = ros_parameter(400, "Slots that may wait to be scored (at least a round: the scorer waits for "
                                     "the round to end, see idle_before_scoring_s, and catches up then)", min_value=1,
                                     max_value=100_000, read_only=True)
    idle_before_scoring_s: float = ros_parameter(
        0.5, "Score only once no MR image has arrived for this long (the round is over or paused) or 3/4 of "
        "queue_slots wait, so that scoring does not compete with the system under test for the CPU; 0 = score as the "
        "images come", min_value=0.0, max_value=600.0, read_only=True)
    render_threads: int = ros_parameter(1, "CPU threads of the GS render (0 = every core)", min_value=0,
                                        max_value=256, read_only=True)
    # Who may write what the scorer reads (docs/security.md, "Application checks"): it is the simulation's measuring
    # instrument, so a rogue's lie must not reach it either (* = any writer; gsrmr_sim.sim_stack.SIM_WRITERS names
    # the stack's nodes)
    robot_writers: tuple[str, ...] = ros_parameter(
        ("*",), "Nodes whose gsrmr/ledger and uplink/camera_info are scored against (the robot)", read_only=True)
    server_writers: tuple[str, ...] = ros_parameter(
        ("*",), "Nodes whose mr/image and mr/slot_info are scored (the server)", read_only=True)
    camera_writers: tuple[str, ...] = ros_parameter(
        ("*",), "Nodes whose camera/image_raw is the truth (the simulated camera)", read_only=True)
    camera_mount: CameraMount = field(default_factory=CameraMount)  # gsrmr_common.ros_node.declare_camera_mount

    @classmethod
    def rule(cls, name: str, value: Any) -> str | None:
        """The server's rules for the parameters they share (``model_path`` required, the background in [0, 1]); a
        writer list names nodes."""
        if name in ("robot_writers", "server_writers", "camera_writers"):
            return writer_list_problem(name, value)
        return ServerParameters.rule(name, value)


@dataclass
class ScoreJob:
    """One published slot to score: its record, its MR image (slot start ``stamp_ns``), the robot's row and the
    true frame among those received (:func:`~gsrmr_sim.truth_frames.match_frame`; None: none matched)."""

    info: MRSlotInfo
    stamp_ns: int
    mr_u8: np.ndarray
    ledger: LedgerRow | None = None
    frame: np.ndarray | None = None


class ScoreBacklog:
    """What waits to be scored (see the module docstring); every method is thread-safe."""

    def __init__(self, clock: SlotClock, depth_slots: int, *, frame_margin_s: float = 2.0,
                 ledger_grace_s: float = 0.5, idle_s: float = 0.0) -> None:
        self.clock = clock
        self.depth_slots = int(depth_slots)
        self.idle_s = float(idle_s)
        self._last_arrival_s = float("-inf")  # monotonic time of the last MR image or slot record
        self.frame_margin_ns = round(frame_margin_s * 1e9)
        self.ledger_grace_s = float(ledger_grace_s)
        self.dropped = 0  # slots dropped unscored (over depth_slots)
        self._lock = threading.Lock()
        self._images: dict[int, tuple[int, np.ndarray]] = {}
        self._infos: dict[int, MRSlotInfo] = {}
        self._ready: dict[int, tuple[float, ScoreJob]] = {}  # slot → (paired at [s], job), in slot order
        self._ledger: dict[int, LedgerRow] = {}
        self._frames: deque[tuple[int, np.ndarray]] = deque()
        self._next_slot: int | None = None  # every slot before it was handed out or dropped

    def add_image(self, stamp_ns: int, mr_u8: np.ndarray, now_s: float) -> None:
        """An ``mr/image`` (stamped with its slot's start) arrived at monotonic time ``now_s``."""
        with self._lock:
            slot = self.clock.slot_named(stamp_ns)
            self._last_arrival_s = max(self._last_arrival_s, now_s)
            self._images[slot] = (int(stamp_ns), mr_u8)
            self._pair(slot, now_s)

    def add_info(self, info: MRSlotInfo, now_s: float) -> None:
        """An ``mr/slot_info`` arrived at monotonic time ``now_s``."""
        with self._lock:
            self._last_arrival_s = max(self._last_arrival_s, now_s)
            self._infos[info.slot] = info
            self._pair(info.slot, now_s)

    def add_ledger(self, row: LedgerRow) -> None:
        """A robot ledger row arrived."""
        with self._lock:
            self._ledger[row.slot] = row
            while len(self._ledger) > 4 * self.depth_slots:
                del self._ledger[min(self._ledger)]

    def add_frame(self, stamp_ns: int, frame_u8: np.ndarray) -> None:
        """A true camera frame captured at ``stamp_ns`` arrived (frames come in capture order)."""
        with self._lock:
            self._frames.append((int(stamp_ns), frame_u8))
            self._prune_frames()

    def _pair(self, slot: int, now_s: float) -> None:
        if slot in self._images and slot in self._infos:
            stamp_ns, mr_u8 = self._images.pop(slot)
            self._ready[slot] = (now_s, ScoreJob(self._infos.pop(slot), stamp_ns, mr_u8))
        for waiting in (self._images, self._infos, self._ready):  # over the depth: drop the oldest
            while len(waiting) > self.depth_slots:
                del waiting[min(waiting)]
                self.dropped += 1

    def _oldest_waiting(self) -> int | None:
        slots = [min(d) for d in (self._images, self._infos, self._ready) if d]
        return min(slots) if slots else self._next_slot

    def _prune_frames(self) -> None:
        """Keep the frames from ``frame_margin_s`` before the oldest slot still to come (before any MR image:
        the last :data:`IDLE_FRAMES_S`), at most ``2·depth_slots`` of them."""
        if not self._frames:
            return
        oldest = self._oldest_waiting()
        keep_from = (self.clock.start_ns(oldest) - self.frame_margin_ns if oldest is not None
                     else self._frames[-1][0] - round(IDLE_FRAMES_S * 1e9))
        while self._frames and (self._frames[0][0] < keep_from or len(self._frames) > 2 * self.depth_slots):
            self._frames.popleft()

    def streaming(self, now_s: float) -> bool:
        """Whether the server still streams: an MR image or slot record came less than ``idle_s`` ago and fewer than
        three quarters of ``depth_slots`` are ready (then :meth:`take` holds the slots back)."""
        with self._lock:
            return self._streaming(now_s)

    def _streaming(self, now_s: float) -> bool:
        return now_s - self._last_arrival_s < self.idle_s and len(self._ready) < 0.75 * self.depth_slots

    def take(self, now_s: float, *, flush: bool = False) -> ScoreJob | None:
        """The oldest paired slot once its ledger row is there or it waited ``ledger_grace_s`` and the server no
        longer streams (``flush``: at once), with its ledger row and its true frame; None when none is ready."""
        with self._lock:
            if not self._ready or (not flush and self._streaming(now_s)):
                return None
            slot = min(self._ready)
            paired_s, job = self._ready[slot]
            row = self._ledger.get(slot)
            if row is None and not flush and now_s - paired_s < self.ledger_grace_s:
                return None
            del self._ready[slot]
            job.ledger = self._ledger.pop(slot, None)
            job.frame = match_frame(list(self._frames), job.ledger, job.stamp_ns)
            self._next_slot = slot + 1 if self._next_slot is None else max(self._next_slot, slot + 1)
            for old in [s for s in self._ledger if s < slot]:
                del self._ledger[old]
            self._prune_frames()
            return job

    def waiting(self) -> int:
        """Slots received and not yet handed out (paired or not)."""
        with self._lock:
            return len(self._ready) + len(self._images.keys() | self._infos.keys())


#: What ``gsrmr-sim-scorer --help`` prints.
INTERFACE = NodeInterface(
    executable="gsrmr-sim-scorer", node="gsrmr_sim_scorer",
    summary="The simulation's ground-truth scoring of every MR image the server publishes (loss, PSNR, SSIM per "
            "slot to <record_dir>/scores.csv).",
    subscribes=(Endpoint("mr/image", "sensor_msgs/msg/Image"),
                Endpoint("mr/slot_info", "std_msgs/msg/Float64MultiArray"),
                Endpoint("gsrmr/ledger", "std_msgs/msg/Float64MultiArray"),
                Endpoint("uplink/camera_info", "sensor_msgs/msg/CameraInfo"),
                Endpoint("camera/image_raw", "sensor_msgs/msg/Image", "the truth, unless truth_dir")),
    parameters=(ParameterGroup(ScorerParameters), ParameterGroup(CameraMountParameters, MOUNT_PREFIX)))
