"""The server node (``gsrmr-server``): one MR image per slot, whatever the uplink did.

Slot k is composed once its uploads are complete (its key, and its image unless the robot's ledger row says none
follows: :class:`~gsrmr_server.ledger_book.LedgerBook`) and at the latest ``process_delay_s`` after it starts
(:class:`~gsrmr_common.slot_clock.ComposeCursor`: missed slots are composed late; more than ``max_backlog_slots``
behind, it skips ahead and counts ``skipped_slots``) by the pure slot core (:mod:`gsrmr_server.slot_core`): r̂_k
is the decoded image, the GS render at the pose key, or the render at the best pose estimate.

Subscribes: ``uplink/pose_key``, ``uplink/image_raw/compressed``, ``gsrmr/schedule``, ``gsrmr/ledger``, ``cmd_vel``
(recorded), ``uplink/camera_info`` (the render intrinsics: :class:`~gsrmr_server.render_intrinsics.RenderIntrinsics`;
the slot clock starts with the first usable one; each is recorded on ``/gsrmr/camera_info``).

Publishes: ``mr/image`` (rgb8, frame ``camera_optical_frame``, stamp = slot start), right after it
``mr/slot_info`` (:class:`~gsrmr_common.wire.MRSlotInfo`: source, pose and MR content time, what a monitor needs
to rebuild the slot's v and d), ``mr/image/compressed`` (JPEG), ``gsrmr/loss_sample`` (the GS loss L_t of an
image slot) and ``/diagnostics`` (:class:`~gsrmr_server.server_stats.ServerStats`, written to
``server_summary.json`` on shutdown). Records ``slots.csv`` and MCAP into ``record_dir`` when set. Parameters:
:class:`~gsrmr_server.server_params.ServerParameters` (checked on set, applied after set; live ones only with
``live_parameter_changes``). A new ``model_path`` (``ros2 param set /gsrmr_server model_path …``, a live change) is
loaded off the slot path and swapped in at a slot boundary (:class:`~gsrmr_server.model_swap.ModelSwap`): no slot
waits for it; ``/diagnostics`` says which model is in use (``model``, ``model_swaps``, ``model_loading``) and warns
when a load failed (the model in use stays).

Nothing on the graph is taken blindly (``docs/security.md``, "Application checks"): every input is admitted by its
writer (:class:`gsrmr_common.ros_admission.GatedInputs`: ``robot_writers`` for the uplink, the ledger and the
camera_info, ``schedule_writers``, ``cmd_vel_writers``; each writer endpoint rate-limited); pose keys must move
within ``max_speed_mps`` (:class:`gsrmr_common.plausibility.PoseTrack`), a ledger row must name a slot near now and
come once per slot, a schedule must be plausible and newer (``seq``) than the last of its writer endpoint. Refused
messages are counted by writer and by reason on ``/diagnostics`` and in ``server_summary.json``.
"""

from __future__ import annotations

from dataclasses import replace
import json
import math
from pathlib import Path
import threading

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Twist, Vector3Stamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Float64MultiArray

from gsrmr_common.interrupts import console_main
from gsrmr_common.plausibility import Implausible, PoseTrack, ScheduleLimits, ledger_problem, schedule_problem
from gsrmr_common.ros_admission import GatedInputs, ParameterAudit
from gsrmr_common.ros_node import (
    declare_camera_mount,
    declare_link_budget,
    declare_parameters,
    diagnostics_msg,
    run_node,
)
from gsrmr_common.ros_wire import (
    CAMERA_INFO_QOS,
    IMAGE_UPLOAD_QOS,
    SCHEDULE_QOS,
    UPLINK_QOS,
    compressed_to_msg,
    image_to_msg,
    intrinsics_from_camera_info,
    ledger_from_msg,
    loss_sample_to_msg,
    mr_slot_info_to_msg,
    pose_key_from_msg,
    pose_key_pose_msg,
    schedule_from_msg,
    stamp_to_ns,
)
from gsrmr_common.slot_clock import ComposeCursor, SlotClock
from gsrmr_common.tf_tree import CAMERA_OPTICAL_FRAME
from gsrmr_common.wire import MAX_COMPRESSED_BYTES, MR_SLOT_INFO_TOPIC, PoseKey, RealSource, UplinkFault
from gsrmr_common.writer_admission import SeqTracker
from gsrmr_server.compose import MRComposer
from gsrmr_server.ledger_book import LedgerBook
from gsrmr_server.model_swap import ModelSwap
from gsrmr_server.recording import TOPIC_CAMERA_INFO, TOPIC_RECEIVED_IMAGE, TOPIC_RECEIVED_POSE, RunRecorder
from gsrmr_server.render_intrinsics import RenderIntrinsics
from gsrmr_server.server_params import ServerParameters
from gsrmr_server.server_stats import ServerStats, diagnostic_report
from gsrmr_server.slot_core import WARM_UP_INTRINSICS, build_server_core, count_composition_faults
from gsrmr_server.splatting.model import GaussianModel
from gsrmr_server.uplink import SlotUploads, UplinkAssembler

# what a plausible schedule looks like to the server (the transmit power is the robot's radio's to bound)
_SCHEDULE_LIMITS = ScheduleLimits(max_power_w=float("inf"))


class ServerNode(Node):
    """Composes and publishes m̂_t every slot; measures L_t in image slots."""

    def __init__(self, **node_kwargs) -> None:
        super().__init__("gsrmr_server", **node_kwargs)
        self.params: ServerParameters = replace(declare_parameters(self, ServerParameters),
                                                camera_mount=declare_camera_mount(self), link=declare_link_budget(self))
        p = self.params
        # Warm-up: the first render compiles the kernels (~1.5 s) before the slot clock starts, not in a slot.
        self.core = build_server_core(p, GaussianModel.load_ply(p.model_path), WARM_UP_INTRINSICS)
        self.composer = self.core.composer
        # a new model_path is loaded off the slot path and swapped in at a slot boundary (issue 27, item 3)
        self.model_swap: ModelSwap[GaussianModel] = ModelSwap(self._load_model)
        self.model_swap.in_use = p.model_path
        self.camera = RenderIntrinsics()  # none until the robot's camera_info arrives
        self.clock = SlotClock(p.slot_s)
        self.cursor = ComposeCursor(self.clock)
        self.uplink = UplinkAssembler()
        self.ledgers = LedgerBook()
        self.stats = ServerStats(p.slot_s)
        self._lock = threading.Lock()
        self.audit = ParameterAudit(self, p.live_parameter_changes)
        self.implausible = Implausible()
        self.poses = PoseTrack(p.max_speed_mps, p.slot_s)
        self._schedule_seq = SeqTracker()
        self._composed_slot: int | None = None  # the newest slot composed
        self.add_on_set_parameters_callback(self._validate)
        self.add_post_set_parameters_callback(self._after_set)
        self._cmd: tuple[float, float] | None = None
        self.recorder = RunRecorder(p.record_dir) if p.record_dir else None

        # One thread: uploads arriving while a slot is composed wait in DDS. A second executor thread made composition
        # several times slower: the GIL passes between numpy/numba calls and the executor's loop (convoy effect).
        io = MutuallyExclusiveCallbackGroup()
        self._pub_mr = self.create_publisher(Image, "mr/image", 5)
        self._pub_info = self.create_publisher(Float64MultiArray, MR_SLOT_INFO_TOPIC, UPLINK_QOS)
        self._pub_mr_c = self.create_publisher(CompressedImage, "mr/image/compressed", 5)
        self._pub_loss = self.create_publisher(Float64MultiArray, "gsrmr/loss_sample", UPLINK_QOS)
        self._pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        # what is taken from the graph, and from whom (docs/security.md, "Application checks"); per writer endpoint:
        # a few messages per slot sustained (relay duplicates and reorderings come in bursts)
        self.inputs = GatedInputs(self, callback_group=io)
        for topic, kind, callback, qos, writers, rate_hz, burst in (
                ("uplink/pose_key", Vector3Stamped, self._on_key, UPLINK_QOS, p.robot_writers, 40.0, 60.0),
                ("uplink/image_raw/compressed", CompressedImage, self._on_image, IMAGE_UPLOAD_QOS, p.robot_writers,
                 40.0, 30.0),
                ("gsrmr/schedule", Float64MultiArray, self._on_schedule, SCHEDULE_QOS, p.schedule_writers, 20.0, 20.0),
                ("gsrmr/ledger", Float64MultiArray, self._on_ledger, UPLINK_QOS, p.robot_writers, 40.0, 60.0),
                ("cmd_vel", Twist, self._on_cmd, 10, p.cmd_vel_writers, 200.0, 100.0),
                ("uplink/camera_info", CameraInfo, self.use_camera_info, CAMERA_INFO_QOS, p.robot_writers, 5.0,
                 10.0)):
            self.inputs.subscribe(kind, topic, callback, qos, writers, rate_hz=rate_hz, burst=burst)
        self.create_timer(0.01, self._tick)  # 10 ms: a slot is composed ≤ 10 ms after it is complete or due
        self.create_timer(1.0, self._publish_diagnostics)
        content = self.composer.virtual.content
        self.get_logger().info(f"server: model {p.model_path} ({self.composer.model.num_gaussians} Gaussians), MR "
                               f"content {content.name} ({len(content.agents)} agents); waiting for uplink/camera_info")

    def _validate(self, params: list[Parameter]) -> SetParametersResult:
        """On-set: refuse a change :class:`ServerParameters` gives a reason for (type, range, read-only), or a
        ``model_path`` that is no file."""
        for param in params:
            reason = ServerParameters.change_problem(param.name, param.value)
            if not reason and param.name == "model_path" and not Path(str(param.value)).is_file():
                reason = f"model_path {param.value!r} is no file (a 3DGS .ply)"
            if reason:
                return SetParametersResult(successful=False, reason=reason)
        reason = self.audit.refusal(param.name for param in params)
        return SetParametersResult(successful=reason is None, reason=reason or "")

    def _after_set(self, params: list[Parameter]) -> None:
        """Post-set: the accepted values into ``self.params`` and the slot core (the cursor's from the next tick)."""
        with self._lock:
            old = self.params
            self.params = self.params.with_values({param.name: param.value for param in params})
            self.audit.record({param.name: (getattr(old, param.name, None), getattr(self.params, param.name, None))
                               for param in params})
            self.core.jpeg_quality, self.core.measure_loss = self.params.jpeg_quality, self.params.measure_loss
        if any(param.name == "model_path" for param in params):  # a swap is privileged: audit.record logged it
            self.get_logger().info(f"loading model {self.params.model_path} off the slot path; it is used from the "
                                   "first slot after it is ready")
            self.model_swap.request(self.params.model_path)

    def _load_model(self, path: str) -> GaussianModel:
        """The model_swap loader (its own thread): read the .ply and render it once at the current intrinsics, so
        the first slot with it pays no first-touch cost."""
        model = GaussianModel.load_ply(path)
        with self._lock:
            probe = MRComposer(model, self.composer.virtual, self.composer.intrinsics, self.composer.mount,
                               tuple(float(c) for c in self.composer.background_rgb),  # type: ignore[arg-type]
                               render_threads=1)
        probe.compose(SlotUploads(0), PoseKey(0, 0.0, 0.0, 0.0), 0.0, measure_loss=False)
        return model

    # ---------------------------------------------------------------- inputs
    def _on_key(self, msg: Vector3Stamped, _gid: bytes = b"") -> None:
        now_ns = self.get_clock().now().nanoseconds
        with self._lock:
            try:
                key = pose_key_from_msg(msg, self.clock)
            except ValueError:  # wrong frame or an invalid stamp: refuse, never raise out of the callback
                self.uplink.count(UplinkFault.MALFORMED_KEY)
                return
            last = self.poses.last
            if key.is_valid() and not self.poses.offer(key.slot, key.a_m, key.b_m):
                self.implausible["pose_jump"] += 1  # faster than the robot drives: no relocalisation (yet)
                if last is not None:  # what jumped, for a false alarm's diagnosis
                    self.get_logger().warning(
                        f"pose key refused (pose_jump): slot {key.slot} at ({key.a_m:.3f}, {key.b_m:.3f}) m, "
                        f"{math.hypot(key.a_m - last[1], key.b_m - last[2]):.3f} m from the track's slot {last[0]} "
                        f"({key.slot - last[0]} slots; reach {self.poses.reach_m(key.slot - last[0]):.3f} m)",
                        throttle_duration_sec=1.0)
                return
            self.uplink.on_key(key, self.clock.slot_at(now_ns), now_ns)

    def _on_image(self, msg: CompressedImage, _gid: bytes = b"") -> None:
        now_ns = self.get_clock().now().nanoseconds
        data = bytes(msg.data)
        with self._lock:
            if len(data) > MAX_COMPRESSED_BYTES:
                self.uplink.count(UplinkFault.OVERSIZED_IMAGE)
                return
            try:
                image_slot = self.clock.slot_named(stamp_to_ns(msg.header.stamp))
            except ValueError:
                self.uplink.count(UplinkFault.MALFORMED_IMAGE)
                return
            self.uplink.on_image(image_slot, data, self.clock.slot_at(now_ns), now_ns)

    def _on_schedule(self, msg: Float64MultiArray, gid: bytes = b"") -> None:
        """A schedule from an admitted writer: taken when it parses, is plausible (T, slots near now; the power is
        the robot's to check) and is newer (seq) than the last one of its writer endpoint; else counted."""
        try:
            sched = schedule_from_msg(msg)
        except ValueError as err:
            self.implausible["schedule_malformed"] += 1
            self.get_logger().error(f"schedule refused: {err}", throttle_duration_sec=5.0)
            return
        reason = schedule_problem(sched, self.clock.slot_at(self.get_clock().now().nanoseconds), _SCHEDULE_LIMITS)
        if reason is None:
            seq = self._schedule_seq.check(gid, sched.seq)
            if seq == "repeat":  # the same schedule delivered again (latched): nothing new
                return
            reason = "schedule_seq" if seq == "older" else None
        with self._lock:
            if reason:
                self.implausible[reason] += 1
                return
            self.ledgers.schedule = sched

    def _on_ledger(self, msg: Float64MultiArray, _gid: bytes = b"") -> None:
        with self._lock:
            try:
                row = ledger_from_msg(msg)
            except ValueError:  # wrong length, or a NaN/inf slot, x or bit count
                self.uplink.count(UplinkFault.MALFORMED_LEDGER)
                return
            # near the slot being composed (the clock's before the first): a replay driving the node faster than
            # real time (bench/soak.py --node) stays near it too
            near = self._composed_slot if self._composed_slot is not None else \
                self.clock.slot_at(self.get_clock().now().nanoseconds)
            reason = ledger_problem(row, near)
            if reason is None and self.ledgers.image_sent(row.slot) is not None:
                reason = "ledger_repeat"  # one row per slot: the first stands
            if reason:
                self.implausible[reason] += 1
                return
            self.ledgers.add(row)

    def _on_cmd(self, msg: Twist, _gid: bytes = b"") -> None:
        self._cmd = (float(msg.linear.x), float(msg.angular.z))

    def use_camera_info(self, msg: CameraInfo, _gid: bytes = b"") -> None:
        """The ``uplink/camera_info`` callback: render with the robot's calibration from the next slot on, or
        refuse an unusable one (:class:`~gsrmr_server.render_intrinsics.RenderIntrinsics`)."""
        if self.recorder is not None:
            self.recorder.write_message(TOPIC_CAMERA_INFO, msg, self.get_clock().now().nanoseconds)
        try:
            got, problem = intrinsics_from_camera_info(msg), None
        except ValueError as err:
            got, problem = None, str(err)
        with self._lock:
            line = self.camera.offer(got, problem)
            if self.camera.intrinsics is not None:
                self.composer.intrinsics = self.camera.intrinsics
        if line is not None and line.level == "warning":  # rclpy: one severity per call site
            self.get_logger().warning(line.text)
        elif line is not None:
            self.get_logger().info(line.text)

    # ---------------------------------------------------------------- slots
    def _tick(self) -> None:
        if self.camera.intrinsics is None:  # the slot clock starts with the robot's calibration
            return
        skips = self.cursor.skips
        slot = self.cursor.next_slot(self.get_clock().now().nanoseconds, delay_s=self.params.process_delay_s,
                                     max_backlog_slots=self.params.max_backlog_slots, complete=self._uploads_complete)
        if self.cursor.skips > skips:  # far behind (suspended, clock jump): skipped ahead
            self.uplink.count(UplinkFault.SKIPPED_SLOTS)
        if slot is not None:
            self.process_slot(slot)

    def _uploads_complete(self, slot: int) -> bool:
        """Its key and its image arrived, or its key and the robot's ledger row saying no image follows."""
        with self._lock:
            return self.uplink.complete(slot, self.ledgers.image_sent(slot))

    def process_slot(self, slot: int) -> None:
        """Compose, publish and record slot ``slot`` (the work is the slot core's; this publishes)."""
        start_ns = self.clock.start_ns(slot)
        swapped = self.model_swap.take()  # at the slot boundary: this slot is the first with a new model
        with self._lock:
            if swapped is not None:
                self.composer.model = swapped.model
            self._composed_slot = slot if self._composed_slot is None else max(slot, self._composed_slot)
            plan = self.ledgers.take(slot)
            uploads = self.uplink.take(slot, image_expected=plan.image_expected)
            best = self.uplink.best_pose(slot)
        out = self.core.process(uploads, best, time_s=self.cursor.round_time_s(slot), stamp_s=start_ns / 1e9,
                                ledger=plan.ledger, scheduled_x=plan.scheduled_x)
        count_composition_faults(self.uplink, uploads, out)
        if swapped is not None:
            self.get_logger().info(f"model swapped in at slot {slot}: {swapped.path} "
                                   f"({swapped.model.num_gaussians} Gaussians, loaded in {swapped.load_s:.2f} s)")
        self._pub_mr.publish(image_to_msg(out.mr_u8, start_ns, CAMERA_OPTICAL_FRAME))
        latency_ms = (self.get_clock().now().nanoseconds - start_ns) / 1e6
        self._pub_info.publish(mr_slot_info_to_msg(out.info))
        compressed = compressed_to_msg(out.jpeg, start_ns, CAMERA_OPTICAL_FRAME)
        self._pub_mr_c.publish(compressed)
        self.stats.record(latency_ms, out.composed.source, out.composed.timings_ms)
        if out.loss_sample is not None:
            self._pub_loss.publish(loss_sample_to_msg(out.loss_sample))
        if self.recorder is not None:
            if out.composed.source == RealSource.IMAGE and uploads.key is not None and uploads.jpeg is not None:
                # what the robot paid to send: training data for a model update (issue 27)
                self.recorder.write_message(TOPIC_RECEIVED_IMAGE,
                                            compressed_to_msg(uploads.jpeg, start_ns, CAMERA_OPTICAL_FRAME), start_ns)
                self.recorder.write_message(TOPIC_RECEIVED_POSE, pose_key_pose_msg(uploads.key, start_ns), start_ns)
            self.recorder.write_slot(replace(out.row, latency_ms=latency_ms), compressed, self._cmd,
                                     stamp_ns=start_ns)

    def security_summary(self) -> dict:
        """What the known-writer and plausibility checks refused, and the live parameter changes (JSON-able)."""
        return {**self.inputs.diagnostic_values(), "implausible": self.implausible.values_for_diagnostics(),
                "relocalisations": self.poses.relocalisations, **self.audit.diagnostic_values()}

    def _publish_diagnostics(self) -> None:
        with self._lock:
            values, problems = diagnostic_report(self.stats.summary(self.uplink.faults), self.camera)
            values.update({k: json.dumps(v) if isinstance(v, dict) else v for k, v in self.security_summary().items()})
            values.update({"model": self.model_swap.in_use, "model_gaussians": self.composer.model.num_gaussians,
                           "model_swaps": self.model_swap.swaps, "model_loading": self.model_swap.loading})
            problems += self.inputs.problems()
            if self.model_swap.error:
                problems.append(f"model swap failed, the model in use stays: {self.model_swap.error}")
            if self.implausible:
                problems.append("implausible inputs refused: " + ", ".join(
                    f"{k} {n}" for k, n in sorted(self.implausible.items())))
        self._pub_diag.publish(diagnostics_msg(self, name=f"{self.get_name()}: MR composition",
                                               hardware_id="gsrmr_server", values=values, problems=problems))

    def on_shutdown(self) -> None:
        """Close the recording and write ``server_summary.json`` beside it (called by run_node on exit); log what the
        input checks refused."""
        self.inputs.log_summary(self.implausible, relocalisations=self.poses.relocalisations)
        if self.recorder is not None:
            self.recorder.close()
            summary = {**self.stats.summary(self.uplink.faults), **self.security_summary()}
            Path(self.recorder.out_dir, "server_summary.json").write_text(json.dumps(summary, indent=1))


@console_main
def main(args: list[str] | None = None) -> int:
    """Console script ``gsrmr-server``."""
    return run_node(ServerNode, args)


