"""``gsrmr-sim-scorer``: the simulation's ground-truth scoring of every MR image the server publishes.

Each slot is rebuilt with the server's model, MR content, mount, background and intrinsics and scored with the
deployment library (:class:`gsrmr_server.scoring.SlotScorer`) into ``<record_dir>/scores.csv``
(:mod:`gsrmr_sim.scores`). Design: docs/world.md, "The simulation's scorer"; parameters:
:class:`~gsrmr_sim.world.scorer_core.ScorerParameters`.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
import threading
import time

from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Float64MultiArray

from gsrmr_common.camera import Intrinsics
from gsrmr_common.interrupts import console_main
from gsrmr_common.ros_admission import GatedInputs
from gsrmr_common.ros_node import declare_camera_mount, declare_parameters, run_node
from gsrmr_common.ros_wire import (
    CAMERA_INFO_QOS,
    UPLINK_QOS,
    image_from_msg,
    intrinsics_or_problem,
    ledger_from_msg,
    mr_slot_info_from_msg,
    stamp_to_ns,
)
from gsrmr_common.slot_clock import SlotClock
from gsrmr_common.wire import MR_SLOT_INFO_TOPIC
from gsrmr_server.render_intrinsics import RenderIntrinsics
from gsrmr_server.scoring import SlotScorer
from gsrmr_server.slot_core import WARM_UP_INTRINSICS, build_composer
from gsrmr_server.slot_row import SlotScore
from gsrmr_sim.scores import ScoresWriter
from gsrmr_sim.truth_frames import TruthFrameReader
from gsrmr_sim.world.scorer_core import INTERFACE, ScoreBacklog, ScoreJob, ScorerParameters
from gsrmr_splat.model import GaussianModel

#: camera/image_raw: best effort as the camera publishes, a deeper queue (the node takes frames between scores).
CAMERA_QOS = QoSProfile(depth=30, reliability=ReliabilityPolicy.BEST_EFFORT)
LOG_EVERY_SLOTS = 100


class ScorerNode(Node):
    """Scores the server's MR images against the simulator's truth (see the module docstring).

    ``worker=False`` starts no scoring thread: the caller scores with :meth:`score_ready` (tests, benches)."""

    def __init__(self, *, worker: bool = True, **node_kwargs) -> None:
        super().__init__("gsrmr_sim_scorer", **node_kwargs)
        self.params: ScorerParameters = replace(declare_parameters(self, ScorerParameters),
                                                camera_mount=declare_camera_mount(self))
        p = self.params
        self.camera = RenderIntrinsics()
        model = GaussianModel.load_ply(p.model_path)
        composer = build_composer(model, WARM_UP_INTRINSICS, mr_content=p.mr_content,
                                  mount=p.camera_mount, background_rgb=p.background_rgb,
                                  render_threads=p.render_threads or None)
        self.scorer = SlotScorer(composer, p.hindsight_jpeg_quality or None)
        self.backlog = ScoreBacklog(SlotClock(p.slot_s), p.queue_slots, idle_s=p.idle_before_scoring_s)
        self.truth_files = TruthFrameReader(p.truth_dir) if p.truth_dir else None
        self.writer = ScoresWriter(p.record_dir) if p.record_dir else None
        self.scored = self.no_truth = self.unusable = 0
        self._sums = {"loss": 0.0, "psnr_db": 0.0}
        self._pending_lock = threading.Lock()  # the pending model and intrinsics, set by callbacks
        self._pending_model: str | None = None
        self._pending_intrinsics: Intrinsics | None = None
        self._size_warned = False
        self._ready = False  # the first MR image has arrived (scorer.ready written)
        self._wake = threading.Event()
        self._stop = threading.Event()
        self.add_on_set_parameters_callback(self._validate)
        self.add_post_set_parameters_callback(self._after_set)
        # only from the stack's own nodes (the writer lists): a rogue's ledger or camera_info must not bend the scores
        self.inputs = GatedInputs(self)
        for kind, topic, callback, qos, writers in (
                (Image, "mr/image", self.on_mr_image, UPLINK_QOS, p.server_writers),
                (Float64MultiArray, MR_SLOT_INFO_TOPIC, self.on_slot_info, UPLINK_QOS, p.server_writers),
                (Float64MultiArray, "gsrmr/ledger", self.on_ledger, UPLINK_QOS, p.robot_writers),
                (CameraInfo, "uplink/camera_info", self.use_camera_info, CAMERA_INFO_QOS, p.robot_writers),
                *([(Image, "camera/image_raw", self.on_camera, CAMERA_QOS, p.camera_writers)]
                  if self.truth_files is None else [])):
            self.inputs.subscribe(kind, topic, lambda msg, _gid, cb=callback: cb(msg), qos, writers, rate_hz=0.0,
                                  burst=1.0)
        self._thread = threading.Thread(target=self._work, name="scorer", daemon=True) if worker else None
        if self._thread is not None:
            self._thread.start()
        truth = f"folder {p.truth_dir}" if self.truth_files else "camera/image_raw"
        self.get_logger().info(f"scorer: model {p.model_path} ({model.num_gaussians} Gaussians), MR content "
                               f"{p.mr_content}, truth from {truth}, scores to "
                               f"{self.writer.path if self.writer else '(log only)'}")

    # ---------------------------------------------------------------- parameters
    def _validate(self, params: list[Parameter]) -> SetParametersResult:
        """On-set: refuse what :class:`ScorerParameters` gives a reason for, and a model file that does not exist."""
        for param in params:
            reason = ScorerParameters.change_problem(param.name, param.value)
            if not reason and param.name == "model_path" and not Path(param.value).is_file():
                reason = f"model_path {param.value!r} is no file"
            if reason:
                return SetParametersResult(successful=False, reason=reason)
        return SetParametersResult(successful=True)

    def _after_set(self, params: list[Parameter]) -> None:
        """Post-set: a new ``model_path`` is loaded by the scoring thread before its next slot."""
        self.params = self.params.with_values({param.name: param.value for param in params})
        if any(param.name == "model_path" for param in params):
            with self._pending_lock:
                self._pending_model = self.params.model_path
            self._wake.set()

    # ---------------------------------------------------------------- inputs
    def on_mr_image(self, msg: Image) -> None:
        """``mr/image``: the published m̂ of the slot its stamp names."""
        try:
            stamp_ns, mr_u8 = stamp_to_ns(msg.header.stamp), image_from_msg(msg)
        except ValueError as err:
            self.get_logger().error(f"mr/image refused: {err}")
            return
        self.backlog.add_image(stamp_ns, mr_u8, time.monotonic())
        self._wake.set()
        if not self._ready and self.writer is not None:
            self._ready = True
            self.writer.mark_ready()

    def on_slot_info(self, msg: Float64MultiArray) -> None:
        """``mr/slot_info``: what the server composed the slot from."""
        try:
            info = mr_slot_info_from_msg(msg)
        except ValueError as err:
            self.get_logger().error(f"mr/slot_info refused: {err}")
            return
        self.backlog.add_info(info, time.monotonic())
        self._wake.set()

    def on_ledger(self, msg: Float64MultiArray) -> None:
        """``gsrmr/ledger``: the robot's row (the capture stamp of the frame its slot used)."""
        try:
            self.backlog.add_ledger(ledger_from_msg(msg))
        except ValueError:
            return  # the server counts malformed rows; a slot without its row is scored against the newest frame

    def on_camera(self, msg: Image) -> None:
        """``camera/image_raw``: a true frame (without ``truth_dir``)."""
        try:
            self.backlog.add_frame(stamp_to_ns(msg.header.stamp), image_from_msg(msg))
        except ValueError as err:
            self.get_logger().error(f"camera/image_raw frame refused: {err}")

    def use_camera_info(self, msg: CameraInfo) -> None:
        """``uplink/camera_info``: the intrinsics the server renders with, adopted or refused as the server does
        (:class:`~gsrmr_server.render_intrinsics.RenderIntrinsics`); applied before the next slot scored."""
        with self._pending_lock:
            line = self.camera.offer(*intrinsics_or_problem(msg))
            self._pending_intrinsics = self.camera.intrinsics
        self._wake.set()
        if line is not None:
            line.log_to(self.get_logger())

    # ---------------------------------------------------------------- scoring
    def _work(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(timeout=0.2)
            self._wake.clear()
            self.score_ready()

    def _apply_pending(self) -> None:
        with self._pending_lock:
            path, self._pending_model = self._pending_model, None
            intrinsics, self._pending_intrinsics = self._pending_intrinsics, None
        if path is not None:
            try:
                model = GaussianModel.load_ply(path)
            except (OSError, ValueError) as err:
                self.get_logger().error(f"model {path} not loaded, scoring with the previous one: {err}")
            else:
                self.scorer.composer.model = model
                self.get_logger().info(f"model {path} loaded ({model.num_gaussians} Gaussians)")
        if intrinsics is not None:
            self.scorer.composer.intrinsics = intrinsics

    def score_ready(self, *, flush: bool = False) -> int:
        """Score every slot that is ready (``flush``: without waiting for late ledger rows); the number scored.
        Nothing is scored before the robot's calibration has arrived."""
        n = 0
        while flush or not self._stop.is_set():
            self._apply_pending()
            if self.camera.intrinsics is None:
                return n
            job = self.backlog.take(time.monotonic(), flush=flush)
            if job is None:
                return n
            self._record(self._score(job))
            n += 1
        return n

    def _score(self, job: ScoreJob) -> SlotScore:
        if self.truth_files is not None:
            stamp_s = job.ledger.frame_stamp_s if job.ledger is not None else None
            truth = self.truth_files.frame(stamp_s, job.stamp_ns)
        else:
            truth = job.frame
        if truth is None:
            self.no_truth += 1
            return SlotScore(job.info.slot)
        try:
            return self.scorer.score(job.info, job.mr_u8, truth)
        except ValueError as err:  # the MR image does not fit the intrinsics (a calibration change in flight)
            self.unusable += 1
            if not self._size_warned:
                self._size_warned = True
                self.get_logger().warning(f"not scored: {err}")
            return SlotScore(job.info.slot)

    def _record(self, score: SlotScore) -> None:
        if self.writer is not None:
            self.writer.write(score)
        if score.scored:
            self.scored += 1
            self._sums["loss"] += score.loss or 0.0
            self._sums["psnr_db"] += score.psnr_db or 0.0
            if self.scored % LOG_EVERY_SLOTS == 0:
                self.get_logger().info(self.report())

    def report(self) -> str:
        """The running totals: slots scored, their mean loss and PSNR, slots without a true frame, backlog."""
        n = max(self.scored, 1)
        return (f"scored {self.scored} slots: mean loss {self._sums['loss'] / n:.4f}, mean PSNR "
                f"{self._sums['psnr_db'] / n:.2f} dB; {self.no_truth} without a true frame, {self.unusable} "
                f"not fitting the intrinsics, {self.backlog.dropped} dropped, {self.backlog.waiting()} waiting")

    def on_shutdown(self) -> None:
        """Stop the scoring thread (the slot in progress is finished) and close scores.csv (run_node on exit)."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=30)
        if self.writer is not None:
            self.writer.close()
        self.inputs.log_summary()
        print(f"gsrmr_sim_scorer: {self.report()}", flush=True)  # the context may be down: no rosout


@console_main
def main(args: list[str] | None = None) -> int:
    """Console script ``gsrmr-sim-scorer``."""
    return run_node(ScorerNode, args, interface=INTERFACE)


if __name__ == "__main__":
    raise SystemExit(main())
