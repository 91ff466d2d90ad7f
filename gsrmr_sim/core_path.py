"""The slot path without nodes or DDS for the soak and load benches (``bench/perf/soak.py``, ``bench/perf/load.py``
core mode): the robot's and the server's cores, wired as the nodes wire them. What it wires and what it leaves out:
docs/reliability.md, "Load and soak"."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
import math
from pathlib import Path
import time

import numpy as np

from gsrmr_common.camera import Intrinsics
from gsrmr_common.link_model import SLOT_S, LinkBudget
from gsrmr_common.pose2d import Pose2D
from gsrmr_common.slot_clock import SlotClock
from gsrmr_common.tf_tree import CAMERA_OPTICAL_FRAME
from gsrmr_common.wire import LedgerRow, PoseKey
from gsrmr_robot.uplink_core import PoseHistory, SlotDecision, SlotInputs, UplinkCore
from gsrmr_server.ledger_book import SlotPlan
from gsrmr_server.recording import RunRecorder
from gsrmr_server.scoring import score_slot
from gsrmr_server.server_params import ServerParameters
from gsrmr_server.slot_core import SlotOutcome, build_server_core, count_composition_faults
from gsrmr_server.slot_row import SlotScore
from gsrmr_server.uplink import UplinkAssembler
from gsrmr_sim.fault_relay import Upload
from gsrmr_splat.model import GaussianModel

CAMERA_FRAME = CAMERA_OPTICAL_FRAME
FOV_RAD = math.radians(70)  # the synthetic camera's horizontal field of view (what the benches relay)


def intrinsics(width: int, height: int) -> Intrinsics:
    """The synthetic camera's calibration (the robot's ``uplink/camera_info`` in the node benches)."""
    return Intrinsics.from_fov(width, height, FOV_RAD)


def point_model(folder: Path, n: int = 2000, seed: int = 0) -> Path:
    """An untrained model: ``n`` random coloured Gaussians over the sandbox (x, y in ±5 m, z in 0..2 m), saved as
    ``folder/points.ply`` (the tests' ``stack_harness.make_point_model``)."""
    rng = np.random.default_rng(seed)
    model = GaussianModel.from_points(rng.uniform([-5, -5, 0], [5, 5, 2], (n, 3)), rng.uniform(0, 1, (n, 3)),
                                      scales_m=0.08, opacities=0.6)
    return model.save_ply(Path(folder) / "points.ply")


def synthetic_frames(width: int, height: int, n: int, seed: int, noise: int = 30) -> list[np.ndarray]:
    """``n`` H×W×3 uint8 RGB frames: a colour ramp plus uniform noise (JPEGs of realistic size)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width]
    base = np.stack([xx * 255 // width, yy * 255 // height, (xx + yy) % 256], axis=2)
    return [np.clip(base + rng.integers(0, noise, base.shape), 0, 255).astype(np.uint8) for _ in range(n)]


class RobotSide:
    """One robot's uplink core (node defaults: JPEG q 80, image in unscheduled slots, ``LinkBudget()``)."""

    def __init__(self, slot_s: float = SLOT_S, link: LinkBudget | None = None, jpeg_quality: int = 80) -> None:
        self.clock = SlotClock(slot_s)
        self.core = UplinkCore(link or LinkBudget(), slot_s, jpeg_quality, default_upload_image=True)
        self.poses = PoseHistory()

    def run_slot(self, slot: int, frame: np.ndarray | None, frame_stamp_ns: int, pose: Pose2D,
                 entry: tuple[int, float] | None = None) -> SlotDecision:
        """Slot ``slot``: odometry ``pose`` at ``frame_stamp_ns``, the frame taken then, the schedule's entry."""
        self.poses.add(frame_stamp_ns, Pose2D(*pose))
        return self.core.run_slot(SlotInputs(slot, frame, frame_stamp_ns if frame is not None else None,
                                             self.poses.at(frame_stamp_ns), entry))

    def uploads(self, decision: SlotDecision) -> list[Upload]:
        """What the robot node publishes on the uplink (image first, then the key; the ledger row is not an
        upload: it travels on ``gsrmr/ledger``, which the fault relay does not touch)."""
        start = self.clock.start_ns(decision.slot)
        out = []
        if decision.jpeg is not None:
            out.append(Upload("image", start, decision.jpeg, CAMERA_FRAME))
        if decision.key is not None:
            k = decision.key
            out.append(Upload("key", start, (k.a_m, k.b_m, k.theta_rad), "map"))
        return out


def deliver(assembler, uploads: list[Upload], now_ns: int, clock: SlotClock) -> None:
    """Uploads into an :class:`~gsrmr_server.uplink.UplinkAssembler` arriving at ``now_ns``."""
    now_slot = clock.slot_at(now_ns)
    for up in uploads:
        slot = clock.slot_named(up.stamp_ns)
        if up.kind == "key":
            assembler.on_key(PoseKey(slot, *up.data), now_slot, now_ns)
        else:
            assembler.on_image(slot, up.data, now_slot, now_ns)


class ServerSide:
    """One robot's server core, assembler and recorder, built as ``ServerNode.__init__`` builds them."""

    def __init__(self, model_path: str | Path, camera: Intrinsics, **params) -> None:
        """``params``: :class:`~gsrmr_server.server_params.ServerParameters` fields other than the defaults
        (e.g. ``slot_s``, ``measure_loss``, ``record_dir``); ``camera`` is the robot's calibration."""
        p = self.params = ServerParameters(model_path=str(model_path), **params)
        self.slot_s, self.clock = p.slot_s, SlotClock(p.slot_s)
        self.core = build_server_core(p, GaussianModel.load_ply(p.model_path), camera)
        self.composer = self.core.composer
        self.uplink = UplinkAssembler()
        self.recorder = RunRecorder(p.record_dir) if p.record_dir else None
        self.slots_done = self.scored = 0
        self.sources: dict[str, int] = {}
        self.last_scores: SlotScore | None = None

    def process(self, slot: int, ledger: LedgerRow | None, *, t0_slot: int, truth: np.ndarray | None = None,
                clock_ns: Callable[[], int] | None = None) -> tuple[SlotOutcome, float]:
        """Compose, encode, score (with ``truth``, the true camera frame: ``last_scores``, counted in ``scored``)
        and record slot ``slot``; returns ``(SlotOutcome, ms)`` with ``ms`` the wall time of the work (take → JPEG,
        before scoring). The row's ``latency_ms`` is ``clock_ns() −`` slot start when a clock is given, else
        ``ms``."""
        t0 = time.perf_counter()
        start_ns = self.clock.start_ns(slot)
        uploads = self.uplink.take(slot, image_expected=SlotPlan(ledger).image_expected)
        best = self.uplink.best_pose(slot)
        out = self.core.process(uploads, best, time_s=(slot - t0_slot) * self.slot_s, stamp_s=start_ns / 1e9,
                                ledger=ledger)
        count_composition_faults(self.uplink, uploads, out)  # refusals found while composing
        jpeg = out.jpeg
        ms = 1e3 * (time.perf_counter() - t0)
        latency_ms = (clock_ns() - start_ns) / 1e6 if clock_ns is not None else ms
        self.slots_done += 1
        self.sources[out.composed.source] = self.sources.get(out.composed.source, 0) + 1
        if truth is not None:
            self.last_scores = score_slot(out.composed, out.mr_u8, truth)
            self.scored += int(self.last_scores.scored)
        if self.recorder is not None:
            self.recorder.write_slot(replace(out.row, latency_ms=latency_ms), jpeg, None, stamp_ns=start_ns)
        return out, ms

    def close(self) -> None:
        if self.recorder is not None:
            self.recorder.close()

