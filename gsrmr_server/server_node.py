"""The server node (``gsrmr-server``): one MR image per slot, whatever the uplink did.

For every slot k (processed as soon as its uploads are complete — its key, and its image when the
schedule expects one — and at the latest ``process_delay_s`` after the slot starts, see
:mod:`gsrmr_common.wire`) the node takes what arrived for k (:class:`~gsrmr_server.uplink.UplinkAssembler`) and composes
m̂_k (:class:`~gsrmr_server.compose.MRComposer`): the decoded image, or the Gaussian-splatting render at
the pose key, or — for a missing, late, duplicated or corrupt upload — the render at the best pose
estimate. It never skips a slot while it keeps up: after a stall (CPU starvation, a DDS peer killed
with -9 can block a publish for ~1 s) it composes the slots it missed, late and counted as such; only
when it is more than ``max_backlog_slots`` behind (suspended, clock jump) does it skip ahead to the
current slot and count ``skipped_slots``.

Subscribes: ``uplink/pose_key`` (geometry_msgs/Vector3Stamped), ``uplink/image_raw/compressed``
(sensor_msgs/CompressedImage), ``gsrmr/schedule`` (std_msgs/Float64MultiArray, transient local),
``gsrmr/ledger`` (std_msgs/Float64MultiArray, the robot's per-slot energy row), ``cmd_vel``
(geometry_msgs/Twist, u_t for the recording), and — only with ``evaluate_ground_truth`` in
simulation — ``camera/image_raw`` (the true r_t, to measure loss/PSNR/SSIM of m̂_t against m_t; with
``ground_truth_dir`` the frames are read from that folder instead, :mod:`gsrmr_common.truth_frames`).
``uplink/camera_info`` (sensor_msgs/CameraInfo, reliable, transient local, depth 1: the robot's latched
calibration) gives the intrinsics the node renders with: the slot clock starts with the first usable one
(until then ``/diagnostics`` says "waiting for camera_info"); a new calibration is adopted from the next
slot on and logged; an unusable one (distortion, skew, no K) is refused at WARN and the last usable one
kept. Every one received is recorded on ``/gsrmr/camera_info``. The camera's mount on the robot comes from
the ``camera_mount.*`` parameters (``config/camera_mount.yaml``, which the robot loads too), the virtual
agents from the MR content file (``mr_content``, :mod:`gsrmr_server.mr`).

Publishes: ``mr/image`` (sensor_msgs/Image rgb8, frame ``camera_optical_frame``, stamp = slot start),
``mr/image/compressed`` (JPEG), ``gsrmr/loss_sample`` (std_msgs/Float64MultiArray
``[slot, a_m, b_m, theta_rad, loss]``: the measured GS loss L_t of an image slot), ``/diagnostics``.
Records ``slots.csv`` and MCAP into ``record_dir`` when set.

Parameters: :class:`~gsrmr_server.server_params.ServerParameters` (``self.params``); a change is checked in
the on-set callback (read-only ones and values out of range or of the wrong type are refused with the reason)
and applied in the post-set callback.
"""

from __future__ import annotations

from collections import deque
from dataclasses import replace
import json
from pathlib import Path
import threading

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Twist, Vector3Stamped
import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Float64MultiArray

from gsrmr_common.camera import Intrinsics
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
    image_from_msg,
    image_to_msg,
    intrinsics_from_camera_info,
    ledger_from_msg,
    loss_sample_to_msg,
    pose_key_from_msg,
    schedule_from_msg,
    stamp_to_ns,
)
from gsrmr_common.slot_clock import ComposeCursor, SlotClock
from gsrmr_common.truth_frames import TruthFrameReader
from gsrmr_common.wire import (
    MAX_COMPRESSED_BYTES,
    LedgerRow,
    ScheduleMsg,
    UplinkFault,
)
from gsrmr_server.recording import TOPIC_CAMERA_INFO, RunRecorder
from gsrmr_server.server_params import ServerParameters
from gsrmr_server.slot_core import build_server_core, count_composition_faults, match_frame
from gsrmr_server.splatting.model import GaussianModel
from gsrmr_server.uplink import UplinkAssembler

# Intrinsics of the start-up warm-up render (compiles the kernels before any camera_info arrives).
WARM_UP_INTRINSICS = Intrinsics.from_fov(32, 24, 1.2)


def describe(k: Intrinsics) -> str:
    """``W×H fx=… fy=… cx=… cy=…`` (pixels; OpenCV pixel centres, see :mod:`gsrmr_common.camera`)."""
    return f"{k.width}×{k.height} fx={k.fx:.3f} fy={k.fy:.3f} cx={k.cx:.3f} cy={k.cy:.3f}"


def intrinsics_mismatch(got: Intrinsics, want: Intrinsics, tol_px: float = 1e-3) -> str | None:
    """How ``got`` differs from ``want`` (image size exactly, fx, fy, cx, cy within ``tol_px`` pixels), or None."""
    if (got.width, got.height) != (want.width, want.height):
        return f"size {got.width}×{got.height} != {want.width}×{want.height}"
    diffs = [f"{name} {getattr(got, name):.3f} != {getattr(want, name):.3f}" for name in ("fx", "fy", "cx", "cy")
             if abs(getattr(got, name) - getattr(want, name)) > tol_px]
    return ", ".join(diffs) or None


class ServerNode(Node):
    """Composes and publishes m̂_t every slot; measures L_t in image slots."""

    def __init__(self, **node_kwargs) -> None:
        super().__init__("gsrmr_server", **node_kwargs)
        self.params: ServerParameters = replace(declare_parameters(self, ServerParameters),
                                                camera_mount=declare_camera_mount(self), link=declare_link_budget(self))
        p = self.params
        # Render intrinsics: none until the robot's camera_info arrives (use_camera_info).
        self.intrinsics: Intrinsics | None = None
        # Warm-up: the first render compiles/loads the rasterizer and the ray caster (~1.5 s); doing it
        # before the slot clock starts keeps the first slots on time instead of skipping the ones that
        # elapsed meanwhile.
        self.core = build_server_core(p, GaussianModel.load_ply(p.model_path), WARM_UP_INTRINSICS)
        self.composer = self.core.composer
        self.clock = SlotClock(p.slot_s)
        self.cursor = ComposeCursor(self.clock)
        self.uplink = UplinkAssembler()
        self._lock = threading.Lock()
        self.add_on_set_parameters_callback(self._validate)
        self.add_post_set_parameters_callback(self._after_set)
        self._schedule: ScheduleMsg | None = None
        self._ledger: dict[int, LedgerRow] = {}
        self._cmd: tuple[float, float] | None = None
        self._frames: deque[tuple[int, np.ndarray]] = deque(maxlen=30)
        self.slots_done = self.slots_on_time = 0
        self.sources: dict[str, int] = {}
        self.latencies_ms: deque[float] = deque(maxlen=1000)
        self.stage_ms: dict[str, deque[float]] = {}
        self.recorder = RunRecorder(p.record_dir) if p.record_dir else None
        self.eval_rows: list[dict] = []
        self.camera_info: CameraInfo | None = None  # last one received
        self.camera_info_status = "waiting for camera_info"
        self._camera_info_warned: str | None = None

        # One thread: uploads that arrive while a slot is composed are taken right after it (DDS queues
        # them). A second executor thread made composition several times slower: the GIL passes between
        # the compose thread's numpy/numba calls and the executor's Python loop (convoy effect).
        io = MutuallyExclusiveCallbackGroup()
        self._pub_mr = self.create_publisher(Image, "mr/image", 5)
        self._pub_mr_c = self.create_publisher(CompressedImage, "mr/image/compressed", 5)
        self._pub_loss = self.create_publisher(Float64MultiArray, "gsrmr/loss_sample", UPLINK_QOS)
        self._pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_subscription(Vector3Stamped, "uplink/pose_key", self._on_key, UPLINK_QOS, callback_group=io)
        self.create_subscription(CompressedImage, "uplink/image_raw/compressed", self._on_image, IMAGE_UPLOAD_QOS,
                                 callback_group=io)
        self.create_subscription(Float64MultiArray, "gsrmr/schedule", self._on_schedule, SCHEDULE_QOS,
                                 callback_group=io)
        self.create_subscription(Float64MultiArray, "gsrmr/ledger", self._on_ledger, UPLINK_QOS, callback_group=io)
        self.create_subscription(Twist, "cmd_vel", self._on_cmd, 10, callback_group=io)
        self.create_subscription(CameraInfo, "uplink/camera_info", self.use_camera_info, CAMERA_INFO_QOS,
                                 callback_group=io)
        self._truth_files = TruthFrameReader(p.ground_truth_dir) if p.ground_truth_dir else None
        if p.evaluate_ground_truth and self._truth_files is None:
            self.create_subscription(Image, "camera/image_raw", self._on_camera, qos_profile_sensor_data,
                                     callback_group=io)
        self.create_timer(0.01, self._tick)  # 10 ms: a slot is composed ≤ 10 ms after it is complete or due
        self.create_timer(1.0, self._publish_diagnostics)
        content = self.composer.virtual.content
        self.get_logger().info(f"server: model {p.model_path} ({self.composer.model.num_gaussians} Gaussians), MR "
                               f"content {content.name} ({len(content.agents)} agents); waiting for uplink/camera_info")

    def _validate(self, params: list[Parameter]) -> SetParametersResult:
        """On-set: refuse a change :class:`ServerParameters` gives a reason for (type, range, read-only);
        change nothing."""
        for param in params:
            reason = ServerParameters.change_problem(param.name, param.value)
            if reason:
                return SetParametersResult(successful=False, reason=reason)
        return SetParametersResult(successful=True)

    def _after_set(self, params: list[Parameter]) -> None:
        """Post-set: take the accepted values (:data:`~gsrmr_server.server_params.LIVE_PARAMETERS`) into
        ``self.params`` and the slot core; ``process_delay_s`` and ``max_backlog_slots`` act from the next tick."""
        with self._lock:
            self.params = self.params.with_values({param.name: param.value for param in params})
            self.core.jpeg_quality, self.core.measure_loss = self.params.jpeg_quality, self.params.measure_loss

    # ---------------------------------------------------------------- inputs
    def _now_slot(self) -> tuple[int, int]:
        now_ns = self.get_clock().now().nanoseconds
        return self.clock.slot_at(now_ns), now_ns

    def _on_key(self, msg: Vector3Stamped) -> None:
        slot, now_ns = self._now_slot()
        try:
            key = pose_key_from_msg(msg, self.clock)
        except ValueError:  # wrong frame or an invalid stamp: refuse, never raise out of the callback
            with self._lock:
                self.uplink.count(UplinkFault.MALFORMED_KEY)
            return
        with self._lock:
            self.uplink.on_key(key, slot, now_ns)

    def _on_image(self, msg: CompressedImage) -> None:
        slot, now_ns = self._now_slot()
        data = bytes(msg.data)
        with self._lock:
            if len(data) > MAX_COMPRESSED_BYTES:
                self.uplink.count(UplinkFault.OVERSIZED_IMAGE)
                return
            try:
                stamp_ns = stamp_to_ns(msg.header.stamp)
            except ValueError:
                self.uplink.count(UplinkFault.MALFORMED_IMAGE)
                return
            self.uplink.on_image(self.clock.slot_named(stamp_ns), data, slot, now_ns)

    def _on_schedule(self, msg: Float64MultiArray) -> None:
        try:
            sched = schedule_from_msg(msg)
        except ValueError as err:
            self.get_logger().error(f"schedule refused: {err}")
            return
        with self._lock:
            self._schedule = sched

    def _on_ledger(self, msg: Float64MultiArray) -> None:
        try:
            row = ledger_from_msg(msg)
        except ValueError:  # wrong length, or a NaN/inf slot, x or bit count
            with self._lock:
                self.uplink.count(UplinkFault.MALFORMED_LEDGER)
            return
        with self._lock:
            self._ledger[row.slot] = row
            if len(self._ledger) > 200:
                del self._ledger[min(self._ledger)]

    def _on_cmd(self, msg: Twist) -> None:
        self._cmd = (float(msg.linear.x), float(msg.angular.z))

    def use_camera_info(self, msg: CameraInfo) -> None:
        """Render with the robot's calibration from now on (the ``uplink/camera_info`` callback).

        An unusable one (distortion, skew, no K: the pinhole renderer cannot match it) is refused with one
        WARN per distinct problem and the last usable one is kept."""
        if self.recorder is not None:
            self.recorder.write_message(TOPIC_CAMERA_INFO, msg, self.get_clock().now().nanoseconds)
        try:
            got = intrinsics_from_camera_info(msg)
        except ValueError as err:
            with self._lock:
                self.camera_info = msg
                self.camera_info_status = f"unusable: {err}"
            if str(err) != self._camera_info_warned:
                self._camera_info_warned = str(err)
                kept = "no intrinsics yet" if self.intrinsics is None else "keeping " + describe(self.intrinsics)
                self.get_logger().warning(f"camera_info from the robot refused ({kept}): {err}")
            return
        with self._lock:
            previous, self.camera_info = self.intrinsics, msg
            self.camera_info_status = describe(got)
            if got == previous:
                return
            self.intrinsics = self.composer.intrinsics = got
        change = "" if previous is None else f" (was {describe(previous)}: {intrinsics_mismatch(got, previous)})"
        self.get_logger().info(f"render intrinsics from camera_info: {describe(got)}{change}")

    def _on_camera(self, msg: Image) -> None:
        try:
            frame = image_from_msg(msg)
            stamp_ns = stamp_to_ns(msg.header.stamp)
        except ValueError:
            return
        with self._lock:
            self._frames.append((stamp_ns, frame))

    # ---------------------------------------------------------------- slots
    def _tick(self) -> None:
        if self.intrinsics is None:  # the slot clock starts with the robot's calibration
            return
        skips = self.cursor.skips
        slot = self.cursor.next_slot(self.get_clock().now().nanoseconds, delay_s=self.params.process_delay_s,
                                     max_backlog_slots=self.params.max_backlog_slots, complete=self._uploads_complete)
        if self.cursor.skips > skips:  # far behind (suspended, clock jump): skipped ahead
            self.uplink.count(UplinkFault.SKIPPED_SLOTS)
        if slot is not None:
            self.process_slot(slot)

    def _uploads_complete(self, slot: int) -> bool:
        """Everything for ``slot`` arrived: its key and its image, or its key and the robot's ledger row
        saying no image was sent (the robot decides in the slot, so the schedule alone cannot say; the robot
        publishes the row first). Until then the slot waits, at most ``process_delay_s``."""
        with self._lock:
            ledger = self._ledger.get(slot)
            return self.uplink.complete(slot, None if ledger is None else bool(ledger.x))

    def process_slot(self, slot: int) -> None:
        """Compose, publish and record slot ``slot`` (the work is the slot core's; this publishes)."""
        start_ns = self.clock.start_ns(slot)
        with self._lock:
            entry = self._schedule.lookup(slot) if self._schedule is not None else None
            ledger = self._ledger.pop(slot, None)
            expected = bool(ledger.x) if ledger is not None else (None if entry is None else bool(entry[0]))
            uploads = self.uplink.take(slot, image_expected=expected)
            best = self.uplink.best_pose(slot)
            frames = list(self._frames) if self.params.evaluate_ground_truth else []
        time_s = self.cursor.round_time_s(slot)
        out = self.core.process(uploads, best, time_s=time_s, stamp_s=start_ns / 1e9, ledger=ledger,
                                scheduled_x=entry[0] if entry else None)
        result = out.composed
        for stage, ms in result.timings_ms.items():
            self.stage_ms.setdefault(stage, deque(maxlen=1000)).append(ms)
        count_composition_faults(self.uplink, uploads, out)
        self._pub_mr.publish(image_to_msg(out.mr_u8, start_ns, "camera_optical_frame"))
        latency_ms = (self.get_clock().now().nanoseconds - start_ns) / 1e6
        self.latencies_ms.append(latency_ms)
        compressed = compressed_to_msg(out.jpeg, start_ns, "camera_optical_frame")
        self._pub_mr_c.publish(compressed)
        self.slots_done += 1
        self.slots_on_time += int(latency_ms <= 1e3 * self.params.slot_s)
        self.sources[result.source] = self.sources.get(result.source, 0) + 1
        if out.loss_sample is not None:
            self._pub_loss.publish(loss_sample_to_msg(out.loss_sample))
        if self.params.evaluate_ground_truth:
            if self._truth_files is not None:
                truth = self._truth_files.frame(ledger.frame_stamp_s if ledger else None, start_ns)
            else:
                truth = match_frame(frames, ledger, start_ns)
            self.core.score(out, truth)
        if self.recorder is not None:
            self.recorder.write_slot(replace(out.row, latency_ms=latency_ms), compressed, self._cmd,
                                     stamp_ns=start_ns)

    def _publish_diagnostics(self) -> None:
        lat = np.asarray(self.latencies_ms) if self.latencies_ms else np.zeros(1)
        values = {"slots": self.slots_done, "slots_on_time": self.slots_on_time,
                  "latency_ms_p50": round(float(np.percentile(lat, 50)), 2),
                  "latency_ms_p99": round(float(np.percentile(lat, 99)), 2),
                  "sources": json.dumps(self.sources), "faults": json.dumps(dict(self.uplink.faults)),
                  "compose_ms_p50": json.dumps(self._stage_medians())}
        with self._lock:
            info_status = self.camera_info_status
        values["camera_info"] = info_status
        problems = ["uplink faults counted"] if self.uplink.faults else []
        if self.intrinsics is None:
            problems.append("waiting for camera_info")
        if info_status.startswith("unusable"):
            problems.append("camera_info refused")
        self._pub_diag.publish(diagnostics_msg(self, name=f"{self.get_name()}: MR composition",
                                               hardware_id="gsrmr_server", values=values, problems=problems))

    def _stage_medians(self) -> dict[str, float]:
        return {k: round(float(np.median(v)), 2) for k, v in self.stage_ms.items() if v}

    def on_shutdown(self) -> None:
        """Close the recording (called by run_node on exit)."""
        if self.recorder is not None:
            self.recorder.close()
            lat = np.asarray(self.latencies_ms) if self.latencies_ms else np.zeros(1)
            summary = {"slots": self.slots_done, "slots_on_time": self.slots_on_time, "sources": self.sources,
                       "faults": dict(self.uplink.faults), "compose_ms_p50": self._stage_medians(),
                       "latency_ms_p50": float(np.percentile(lat, 50)),
                       "latency_ms_p99": float(np.percentile(lat, 99))}
            Path(self.recorder.out_dir, "server_summary.json").write_text(json.dumps(summary, indent=1))


def main(args: list[str] | None = None) -> int:
    """Console script ``gsrmr-server``."""
    return run_node(ServerNode, args)


