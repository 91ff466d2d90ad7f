"""The server node (``gsrmr-server``): one MR image per slot, whatever the uplink did.

Topics and parameters: ``gsrmr-server --help`` (:data:`~gsrmr_server.server_params.INTERFACE`); what it does each
slot, publishes and records: ``docs/nodes.md``, "The server"; what it takes from the graph: ``docs/security.md``,
"Application checks". Its logic is in pure objects: the slot core (:class:`~gsrmr_server.slot_core.ServerCore`),
:class:`~gsrmr_server.server_inputs.ServerInputs`, :class:`~gsrmr_server.render_intrinsics.RenderIntrinsics`,
:class:`~gsrmr_server.model_swap.ModelSwap` and :class:`~gsrmr_server.server_stats.ServerStats`.
"""

from __future__ import annotations

from dataclasses import replace
import json
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
    LOSS_SAMPLE_QOS,
    SCHEDULE_QOS,
    UPLINK_QOS,
    compressed_to_msg,
    image_to_msg,
    intrinsics_or_problem,
    loss_sample_to_msg,
    map_correction_to_msg,
    mr_slot_info_to_msg,
)
from gsrmr_common.slot_clock import ComposeCursor, SlotClock
from gsrmr_common.tf_tree import CAMERA_OPTICAL_FRAME
from gsrmr_common.wire import MAP_CORRECTION_TOPIC, MR_SLOT_INFO_TOPIC, RealSource, UplinkFault
from gsrmr_server.compose import to_u8
from gsrmr_server.compose_levels import DeadlineLevels
from gsrmr_server.localizer import LocalizerConfig, ServerLocalizer, correction_record
from gsrmr_server.map_correction import TRACKING
from gsrmr_server.model_swap import ModelSwap
from gsrmr_server.recording import TOPIC_CAMERA_INFO, RunRecorder
from gsrmr_server.render_intrinsics import RenderIntrinsics
from gsrmr_server.server_inputs import ServerInputs
from gsrmr_server.server_params import INTERFACE, ServerParameters
from gsrmr_server.server_stats import ServerStats, diagnostic_report
from gsrmr_server.slot_core import WARM_UP_INTRINSICS, build_server_core, count_composition_faults
from gsrmr_splat.model import GaussianModel

#: A slot composed later than this fraction of τ after its start skips its registration (the localizer is shed first).
LATE_FRACTION = 0.5


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
        # a new model_path is loaded off the slot path and swapped in at a slot boundary
        self.model_swap: ModelSwap[GaussianModel] = ModelSwap(self._load_model)
        self.model_swap.in_use = p.model_path
        self.camera = RenderIntrinsics()  # none until the robot's camera_info arrives
        self.clock = SlotClock(p.slot_s)
        self.cursor = ComposeCursor(self.clock)
        self.stats = ServerStats(p.slot_s)
        self.levels = DeadlineLevels(max_level=p.max_compose_level)  # each slot's level from its time left
        self._lock = threading.Lock()
        self.checked = ServerInputs(self.clock, p.max_speed_mps, self._lock)  # plausibility checks, per-slot books
        self.uplink = self.checked.uplink
        self.audit = ParameterAudit(self, p.live_parameter_changes)
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
        self._pub_loss = self.create_publisher(Float64MultiArray, "gsrmr/loss_sample", LOSS_SAMPLE_QOS)
        self._pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._pub_correction = self.create_publisher(Float64MultiArray, MAP_CORRECTION_TOPIC, CAMERA_INFO_QOS)
        self.localizer = (ServerLocalizer(p.model_path, p.camera_mount, p.background_rgb,
                                          LocalizerConfig(min_interval_s=p.localization_interval_s))
                          if p.localization else None)
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
        """On-set: refuse a change :class:`ServerParameters` gives a reason for (type, range, read-only, no file)."""
        reason = self.audit.problem(ServerParameters, params)
        return SetParametersResult(successful=reason is None, reason=reason or "")

    def _after_set(self, params: list[Parameter]) -> None:
        """Post-set: the accepted values into ``self.params`` and the slot core (the cursor's from the next tick)."""
        with self._lock:
            self.params = self.audit.applied(self.params, params)
            self.core.jpeg_quality, self.core.measure_loss = self.params.jpeg_quality, self.params.measure_loss
        if any(param.name == "model_path" for param in params):  # a swap is privileged: audit.record logged it
            self.get_logger().info(f"loading model {self.params.model_path} off the slot path; it is used from the "
                                   "first slot after it is ready")
            self.model_swap.request(self.params.model_path)

    def _load_model(self, path: str) -> GaussianModel:
        """The model_swap loader (its own thread): read the .ply and render it once (:meth:`MRComposer.warm_up`)."""
        return self.composer.warm_up(GaussianModel.load_ply(path))

    # ---------------------------------------------------------------- inputs
    def _on_key(self, msg: Vector3Stamped, _gid: bytes = b"") -> None:
        if (line := self.checked.on_key(msg, self.get_clock().now().nanoseconds)) is not None:
            self.get_logger().warning(line, throttle_duration_sec=1.0)

    def _on_image(self, msg: CompressedImage, _gid: bytes = b"") -> None:
        self.checked.on_image(msg, self.get_clock().now().nanoseconds)

    def _on_schedule(self, msg: Float64MultiArray, gid: bytes = b"") -> None:
        if (line := self.checked.on_schedule(msg, gid, self.get_clock().now().nanoseconds)) is not None:
            self.get_logger().error(line, throttle_duration_sec=5.0)

    def _on_ledger(self, msg: Float64MultiArray, _gid: bytes = b"") -> None:
        self.checked.on_ledger(msg, self.get_clock().now().nanoseconds)

    def _on_cmd(self, msg: Twist, _gid: bytes = b"") -> None:
        self._cmd = (float(msg.linear.x), float(msg.angular.z))

    def use_camera_info(self, msg: CameraInfo, _gid: bytes = b"") -> None:
        """The ``uplink/camera_info`` callback: render with the robot's calibration from the next slot on, or
        refuse an unusable one (:class:`~gsrmr_server.render_intrinsics.RenderIntrinsics`)."""
        if self.recorder is not None:
            self.recorder.write_message(TOPIC_CAMERA_INFO, msg, self.get_clock().now().nanoseconds)
        with self._lock:
            line = self.camera.offer(*intrinsics_or_problem(msg))
            if self.camera.intrinsics is not None:
                self.composer.intrinsics = self.camera.intrinsics
        if line is not None:
            line.log_to(self.get_logger())

    # ---------------------------------------------------------------- slots
    def _tick(self) -> None:
        if self.camera.intrinsics is None:  # the slot clock starts with the robot's calibration
            return
        skips = self.cursor.skips
        slot = self.cursor.next_slot(self.get_clock().now().nanoseconds, delay_s=self.params.process_delay_s,
                                     max_backlog_slots=self.params.max_backlog_slots, complete=self.checked.complete)
        if self.cursor.skips > skips:  # far behind (suspended, clock jump): skipped ahead
            self.uplink.count(UplinkFault.SKIPPED_SLOTS)
        if slot is not None:
            self.process_slot(slot)

    def process_slot(self, slot: int) -> None:
        """Compose, publish and record slot ``slot`` (the work is the slot core's; this publishes)."""
        start_ns = self.clock.start_ns(slot)
        swapped = self.model_swap.take()  # at the slot boundary: this slot is the first with a new model
        with self._lock:
            if swapped is not None:
                self.composer.model = swapped.model
            plan, uploads, best = self.checked.take(slot)
        chosen_ns = self.get_clock().now().nanoseconds
        self.levels.max_level = self.params.max_compose_level
        level = self.levels.choose((start_ns + self.params.slot_s * 1e9 - chosen_ns) / 1e6)
        out = self.core.process(uploads, best, time_s=self.cursor.round_time_s(slot), stamp_s=start_ns / 1e9,
                                ledger=plan.ledger, scheduled_x=plan.scheduled_x, level=level)
        count_composition_faults(self.uplink, uploads, out)
        if swapped is not None:
            self.get_logger().info(f"model swapped in at slot {slot}: {swapped.path} "
                                   f"({swapped.model.num_gaussians} Gaussians, loaded in {swapped.load_s:.2f} s)")
        if out.loss_sample is not None:  # first: the scheduler replans on it, for the robot's next slot
            self._pub_loss.publish(loss_sample_to_msg(out.loss_sample))
        self._pub_mr.publish(image_to_msg(out.mr_u8, start_ns, CAMERA_OPTICAL_FRAME))
        published_ns = self.get_clock().now().nanoseconds
        latency_ms, compose_ms = (published_ns - start_ns) / 1e6, (published_ns - chosen_ns) / 1e6
        self.levels.observe(level.level, compose_ms)
        self._pub_info.publish(mr_slot_info_to_msg(out.info))
        compressed = compressed_to_msg(out.jpeg, start_ns, CAMERA_OPTICAL_FRAME)
        self._pub_mr_c.publish(compressed)
        self.stats.record(latency_ms, out.composed.source, out.composed.timings_ms)
        if self.localizer is not None:  # shed first: in a degraded or late slot it registers nothing
            late = level.degraded or latency_ms > LATE_FRACTION * 1e3 * self.params.slot_s
            self._localize(out, uploads, plan.ledger, start_ns, late, swapped)
        if self.recorder is not None:
            if out.composed.source == RealSource.IMAGE and uploads.key is not None and uploads.jpeg is not None:
                self.recorder.write_received(uploads.jpeg, uploads.key, start_ns)  # training data for an update
            self.recorder.write_slot(replace(out.row, latency_ms=latency_ms, compose_ms=compose_ms), compressed,
                                     self._cmd, stamp_ns=start_ns)

    def _localize(self, out, uploads, ledger, start_ns: int, late: bool, swapped) -> None:
        """Hand an image slot's decoded image and key to the localizer (off the slot path; shed when this slot ran
        late or was degraded) and publish the correction a fix gives."""
        now_s = self.get_clock().now().nanoseconds / 1e9
        if swapped is not None:
            self.localizer.swap_model(swapped.path)
        if uploads.key is not None:
            self.localizer.note_key(uploads.key)
        if out.composed.source == RealSource.IMAGE and uploads.key is not None and ledger is not None:
            self.localizer.offer(to_u8(out.composed.real_estimate), uploads.key, ledger.correction_seq,
                                 self.camera.intrinsics, start_ns / 1e9, now_s,
                                 late=late)
        correction = self.localizer.poll(now_s)
        if correction is not None:
            self._pub_correction.publish(map_correction_to_msg(correction_record(correction)))
            x, sd = correction.x, [v ** 0.5 for v in correction.variance]
            self.get_logger().info(f"map correction {correction.seq}: ({x.x_m:+.4f} m, {x.y_m:+.4f} m, "
                                   f"{x.theta_rad:+.5f} rad) ± ({sd[0]:.4f}, {sd[1]:.4f}, {sd[2]:.5f})")

    def security_summary(self) -> dict:
        """What the known-writer and plausibility checks refused, and the live parameter changes (JSON-able)."""
        return {**self.inputs.diagnostic_values(), **self.checked.diagnostic_values(), **self.audit.diagnostic_values()}

    def _publish_diagnostics(self) -> None:
        with self._lock:
            values, problems = diagnostic_report(self.stats.summary(self.uplink.faults), self.camera)
            values.update({k: json.dumps(v) if isinstance(v, dict) else v for k, v in self.security_summary().items()})
            values.update(self.model_swap.diagnostic_values(), model_gaussians=self.composer.model.num_gaussians)
            problems += self.inputs.problems() + self.checked.problems() + self.model_swap.problems()
            if self.localizer is not None:
                now_s = self.get_clock().now().nanoseconds / 1e9
                values.update({k: json.dumps(v) if isinstance(v, dict) else v
                               for k, v in self.localizer.diagnostic_values(now_s).items()})
                if values["localization"] != TRACKING:
                    problems.append(f"localization {values['localization']}")
        self._pub_diag.publish(diagnostics_msg(self, name=f"{self.get_name()}: MR composition",
                                               hardware_id="gsrmr_server", values=values, problems=problems))

    def on_shutdown(self) -> None:
        """Close the recording and write ``server_summary.json`` beside it (called by run_node on exit); log what the
        input checks refused."""
        self.inputs.log_summary(self.checked.implausible, relocalisations=self.checked.poses.relocalisations)
        if self.localizer is not None:
            self.localizer.close()
        if self.recorder is not None:
            self.recorder.close()
            summary = {**self.stats.summary(self.uplink.faults), **self.security_summary()}
            Path(self.recorder.out_dir, "server_summary.json").write_text(json.dumps(summary, indent=1))


@console_main
def main(args: list[str] | None = None) -> int:
    """Console script ``gsrmr-server``."""
    return run_node(ServerNode, args, interface=INTERFACE)


