"""The robot node (``gsrmr-robot``): each slot, upload the camera image or only the pose key.

Every τ seconds, aligned to the slot clock of :mod:`gsrmr_common.wire`, the node takes the newest
camera frame and the current pose, looks up (x_t, p_t) for this slot in the active schedule, and
publishes:

* ``uplink/pose_key`` (``geometry_msgs/Vector3Stamped``, reliable, depth 50): (a, b, θ) in ``map``
  — every slot (in image slots too, so the server can measure the GS loss at this pose);
* ``uplink/image_raw/compressed`` (``sensor_msgs/CompressedImage``, JPEG, ``format`` =
  ``"rgb8; jpeg compressed bgr8"``, reliable, depth 10; the frame rectified and sized to ``uplink_width_px``,
  the camera of ``uplink/camera_info``, below): only when x_t = 1 — and, with
  ``hold_images_while_queued``, only when the previous image has been acknowledged by the server's reader
  (else the slot sends the key only and its ledger row says ``held_back``; :mod:`gsrmr_robot.uplink_backlog`:
  on a link slower than one image per slot images leave as fast as it delivers them, not into a queue).

Inputs: ``camera/image_raw`` (``sensor_msgs/Image``, sensor-data QoS), ``odom`` (``nav_msgs/Odometry``,
odom → base_link; composed with the ``map_from_odom`` parameter to get the pose in ``map``),
``gsrmr/schedule`` (``std_msgs/Float64MultiArray``, layout in :mod:`gsrmr_common.wire`, transient
local). Without a schedule for the slot (neither the newest nor the one before it covers it: a newer one that starts
after the slot keeps the last plan for it) the node uploads the image (``default_upload_image``).

Camera calibration: ``camera/camera_info`` (``sensor_msgs/CameraInfo``, sensor-data QoS; remap it to
the driver's topic; plumb_bob, rational_polynomial or equidistant) decides what the robot uploads: every
frame is rectified to a pinhole camera and scaled down to ``uplink_width_px`` (aspect kept, never enlarged)
before it is JPEG-encoded (:class:`gsrmr_robot.camera_rectify.UplinkCamera` over
:mod:`gsrmr_common.calibration`: the maps are computed once per calibration, then one ``cv2.remap`` and one
``cv2.resize`` per frame a slot takes, in that slot — frames no slot takes cost nothing —; an undistorted camera
at or below that width passes through untouched). That
pinhole camera is published on ``uplink/camera_info`` (reliable, transient local, depth 1: latched, a
server started later still gets it): ``plumb_bob`` with zero D, R = I, P = [K | 0], K with pixel centres at
integers (ROS), the uplink image size, ``frame_id`` = ``camera_frame_id`` (the uploaded images' frame) —
re-published only when it changes (a new calibration, ``uplink_width_px`` or ``camera_frame_id``; the stamp
alone is no change). A calibration that describes no camera (an all-zero K, an unknown distortion model …)
is refused with one WARN per distinct problem and the last usable one kept.

Before the first usable ``camera_info`` the robot uploads no image (the server cannot compose one without
intrinsics, and a distorted frame of unknown geometry is no use to it): its slots send the pose key and the
ledger row only (the row says key, x = 0), as slots without a fresh frame do, and ``/diagnostics`` counts them
in ``frames_uncalibrated`` and says ``waiting for camera_info``. A frame whose size is not the calibration's is
withheld and counted the same way (WARN, throttled).

TF (REP-105, frames of :mod:`gsrmr_common.tf_tree`): where ``tf2_ros`` imports (a ROS install,
:func:`gsrmr_common.tf_ros.load_tf2_ros`) the node publishes on ``/tf_static`` ``map → odom`` from
``map_from_odom`` (re-sent when the parameter changes) and ``base_link → camera_frame_id`` from the
``camera_mount.*`` parameters; ``odom → base_link`` comes from the base driver (``gsrmr-limo-base`` with
``publish_tf``). Without ``tf2_ros`` it logs once, at INFO, that no TF is published.

What to send in a slot and its energy are decided by the pure slot core
(:class:`gsrmr_robot.uplink_core.UplinkCore`: the energy ledger under the link model of
:mod:`gsrmr_common.link_model`); the node publishes each slot's ledger row on ``gsrmr/ledger``
(``std_msgs/Float64MultiArray``, fields :data:`gsrmr_common.wire.LEDGER_FIELDS`) and totals on
``/diagnostics`` once a second. Its parameters (:class:`gsrmr_robot.robot_params.RobotParameters`: ``slot_s``,
``jpeg_quality``, ``uplink_width_px``, ``default_upload_image``, ``max_frame_age_s``, ``max_pose_age_s``,
``map_from_odom``,
``camera_frame_id``, ``hold_images_while_queued``, ``uplink_ack_stale_s``, ``odom_frame_id``,
``base_frame_id``; ``camera_mount.*`` and the link budget of ``config/link.yaml``) are checked in the on-set
callback and applied in the post-set callback (a new ``uplink_width_px`` rebuilds the maps and re-publishes
``uplink/camera_info``).

Nothing on the graph is taken blindly (``docs/security.md``, "Application checks"): every input is admitted by its
writer (:class:`gsrmr_common.ros_admission.GatedInputs`: ``schedule_writers``, ``channel_writers``,
``camera_writers``, ``odom_writers``, each writer endpoint rate-limited); a schedule must be plausible
(:func:`gsrmr_common.plausibility.schedule_problem`: bounded T, slots near now, powers ≤ ``max_tx_power_w``) and
its ``seq`` must grow per writer endpoint; a channel gain must lie in the Rician band around the path-loss
prediction at the robot's position (:class:`gsrmr_common.channel_band.GainBand`; refused: the slot counts as
unmeasured). The hold-back trusts DDS acknowledgements only while every matched reader of the image topic is one
of ``image_readers``. Refusals are counted and named on ``/diagnostics``; live parameters change only with
``live_parameter_changes``.
"""

from __future__ import annotations

from dataclasses import replace
import json
import math
import threading

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Vector3Stamped
from nav_msgs.msg import Odometry
import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Float64MultiArray

from gsrmr_common.calibration import CalibrationError, CameraCalibration
from gsrmr_common.camera import Intrinsics
from gsrmr_common.channel_band import GainBand
from gsrmr_common.interrupts import console_main
from gsrmr_common.plausibility import Implausible, ScheduleLimits, schedule_problem
from gsrmr_common.ros_admission import GatedInputs, ParameterAudit
from gsrmr_common.ros_node import (
    aligned_timer,
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
    camera_info_from_intrinsics,
    channel_sample_from_msg,
    compressed_to_msg,
    image_from_msg,
    ledger_to_msg,
    pose_key_to_msg,
    schedule_from_msg,
    stamp_to_ns,
)
from gsrmr_common.slot_clock import SlotClock, SlotTicker
from gsrmr_common.tf_ros import load_tf2_ros, transform_to_msg
from gsrmr_common.tf_tree import MAP_FRAME, base_from_camera_optical_transform, map_from_odom_transform
from gsrmr_common.wire import CHANNEL_TOPIC, ScheduleMsg
from gsrmr_common.writer_admission import SeqTracker, join_node_name, resolve_writer_name
from gsrmr_robot.camera_rectify import UplinkCamera
from gsrmr_robot.dds_profile import use_uplink_profile
from gsrmr_robot.robot_params import RobotParameters
from gsrmr_robot.scene_change import SceneChangeDetector
from gsrmr_robot.uplink_backlog import UplinkBacklog
from gsrmr_robot.uplink_core import PoseHistory, SlotInputs, UplinkCore, covering_schedule, odom_to_map, stale


def yaw_of(q) -> float:
    """Yaw (rad, about +z) of a geometry_msgs/Quaternion."""
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


class RobotNode(Node):
    """Slot-clocked uplink: image or pose key, with an energy ledger."""

    def __init__(self, **node_kwargs) -> None:
        super().__init__("gsrmr_robot", **node_kwargs)
        self.params: RobotParameters = replace(declare_parameters(self, RobotParameters),
                                               camera_mount=declare_camera_mount(self), link=declare_link_budget(self))
        p = self.params
        self.slot_s, self.odom_frame, self.base_frame = p.slot_s, p.odom_frame_id, p.base_frame_id
        self.mount, self.link = p.camera_mount, p.link
        self.audit = ParameterAudit(self, p.live_parameter_changes)
        self.add_on_set_parameters_callback(self._validate)
        self.add_post_set_parameters_callback(self._after_set)
        self.clock = SlotClock(self.slot_s)
        self._ticker = SlotTicker(self.clock)
        self._lock = threading.Lock()
        self._frame: np.ndarray | None = None
        self._frame_ns = 0
        self._frame_stamp_ns = 0
        # Recent poses in map: the key is the pose at the capture time of the frame it stands for.
        self._poses = PoseHistory()
        self._schedule: ScheduleMsg | None = None
        self._schedule_before: ScheduleMsg | None = None  # the previous schedule, for slots the newest does not cover
        self.schedule_misses = self.no_frame = self.no_pose = 0
        detector = (SceneChangeDetector(ratio=self.params.scene_change_ratio)
                    if self.params.scene_change_ratio > 0 else None)
        self.core = UplinkCore(self.link, self.slot_s, self.params.jpeg_quality, self.params.default_upload_image,
                               detector, self.params.scene_change_wait_slots)
        self.ledger = self.core.ledger
        self.backlog = UplinkBacklog(stale_after_s=self.params.uplink_ack_stale_s)

        self._pub_key = self.create_publisher(Vector3Stamped, "uplink/pose_key", UPLINK_QOS)
        self._pub_img = self.create_publisher(CompressedImage, "uplink/image_raw/compressed", IMAGE_UPLOAD_QOS)
        self._pub_ledger = self.create_publisher(Float64MultiArray, "gsrmr/ledger", UPLINK_QOS)
        self._pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._pub_info = self.create_publisher(CameraInfo, "uplink/camera_info", CAMERA_INFO_QOS)
        # the camera as uploaded: calibration → rectifier at uplink_width_px (guarded by _lock)
        self.camera = UplinkCamera(self.params.uplink_width_px)
        self._info_sent: tuple[Intrinsics, str] | None = None  # (intrinsics, frame_id) last on uplink/camera_info
        self._calibration_problem: str | None = None  # why the last camera_info was refused (None: it was usable)
        self.camera_info_changes = 0  # uplink/camera_info publications
        self.frames_uncalibrated = 0  # slots whose fresh frame was withheld: no calibration, or another size
        # what is taken from the graph, and from whom (docs/security.md, "Application checks")
        self.implausible = Implausible()
        self._schedule_seq = SeqTracker()
        self._schedule_limits = ScheduleLimits(max_power_w=p.max_tx_power_w)
        self.gain_band = GainBand(self.link.rician_k, self.link.pathloss_exponent)
        self.inputs = GatedInputs(self)
        for kind, topic, callback, qos, writers, rate_hz, burst in (
                (Image, "camera/image_raw", self._on_image, qos_profile_sensor_data, p.camera_writers, 100.0, 100.0),
                (CameraInfo, "camera/camera_info", self._on_camera_info, qos_profile_sensor_data, p.camera_writers,
                 100.0, 100.0),
                (Odometry, "odom", self._on_odom, 20, p.odom_writers, 200.0, 200.0),
                (Float64MultiArray, CHANNEL_TOPIC, self._on_channel, 10, p.channel_writers, 40.0, 40.0)):
            self.inputs.subscribe(kind, topic, lambda msg, _gid, cb=callback: cb(msg), qos, writers, rate_hz=rate_hz,
                                  burst=burst)
        # the schedule's seq must grow per writer endpoint: its callback takes the GID
        self.inputs.subscribe(Float64MultiArray, "gsrmr/schedule", self._on_schedule, SCHEDULE_QOS,
                              p.schedule_writers, rate_hz=20.0, burst=20.0)
        self._gains: dict[int, tuple[float, int]] = {}  # slot → the radio's (measured gain, round slot)
        self.channel_unmeasured = 0
        self._image_readers = frozenset(resolve_writer_name(r, self.get_namespace()) for r in p.image_readers)
        self.stranger_readers: tuple[str, ...] = ()  # readers of the image topic that are not image_readers
        self.create_timer(1.0, self._check_image_readers)
        # 5 ms tick: slot starts are detected with ≤ 5 ms jitter without a drifting periodic timer.
        # run each slot 1 ms after it starts (polling the clock at 200 Hz cost ~5 % of a core)
        aligned_timer(self, self.clock, 0.001, self._tick)
        self.create_timer(1.0, self._publish_diagnostics)
        # while an image is unacknowledged: poll the image writer's acknowledgements every 5 ms
        self._ack_timer = self.create_timer(0.005, self._poll_acks)
        self._ack_timer.cancel()
        self._tf_static = None
        tf2_ros, why = load_tf2_ros()
        if tf2_ros is None:
            self.get_logger().info(f"TF not published: {why}; map → {self.odom_frame} and {self.base_frame} → "
                                   f"{self.params.camera_frame_id} need a ROS 2 install with tf2_ros")
        else:
            self._tf_static = tf2_ros.StaticTransformBroadcaster(self)
            self._send_static_tf()
        self.get_logger().info(f"robot uplink: τ={self.slot_s}s, JPEG q={self.params.jpeg_quality}, "
                               f"server at {self.link.server_position_m}")

    def _send_static_tf(self) -> None:
        """(Re)send map → odom and base_link → camera on /tf_static, both in one message.

        rclpy's StaticTransformBroadcaster latches only the last message it sent (depth 1), so every
        send must carry all of this node's static transforms.
        """
        if self._tf_static is None:
            return
        stamp = self.get_clock().now().to_msg()
        self._tf_static.sendTransform([
            transform_to_msg(MAP_FRAME, self.odom_frame, map_from_odom_transform(*self.params.map_from_odom), stamp),
            transform_to_msg(self.base_frame, self.params.camera_frame_id,
                             base_from_camera_optical_transform(self.mount), stamp)])

    def _validate(self, params) -> SetParametersResult:
        """On-set: refuse a change :class:`RobotParameters` gives a reason for (read-only, type, range, an empty
        frame, a map_from_odom that is no pose); change nothing."""
        for p in params:
            problem = RobotParameters.change_problem(p.name, p.value)
            if problem:
                return SetParametersResult(successful=False, reason=problem)
        refusal = self.audit.refusal(p.name for p in params)
        if refusal:
            return SetParametersResult(successful=False, reason=refusal)
        return SetParametersResult(successful=True)

    def _after_set(self, params) -> None:
        """Post-set: apply the accepted values; re-send the static TF when a frame or map_from_odom changed, rebuild
        the rectifier for a new ``uplink_width_px`` and re-publish ``uplink/camera_info`` when it changed."""
        old = self.params
        with self._lock:
            self.params = self.params.with_values({p.name: p.value for p in params})
            self.audit.record({p.name: (getattr(old, p.name, None), getattr(self.params, p.name, p.value))
                               for p in params})
            self.core.jpeg_quality = self.params.jpeg_quality
            self.core.default_upload_image = self.params.default_upload_image
            self.backlog.stale_after_s = self.params.uplink_ack_stale_s
            self.camera.set_uplink_width(self.params.uplink_width_px)
        if any(p.name in ("map_from_odom", "camera_frame_id") for p in params):
            self._send_static_tf()
        self._publish_camera_info()  # a new uplink width or camera_frame_id is a new uplink camera

    # ---------------------------------------------------------------- inputs
    def _on_camera_info(self, msg: CameraInfo) -> None:
        """Adopt the camera's calibration (maps rebuilt only when it changed) and publish the uplink camera when
        that changed; refuse an unusable one (one WARN per distinct problem), keeping the last usable one."""
        try:
            calib = CameraCalibration.from_camera_info(msg)
        except CalibrationError as err:
            problem = str(err)
            if problem != self._calibration_problem:
                with self._lock:
                    kept = self.camera.describe()
                self.get_logger().warning(f"camera_info refused ({kept}): {problem}")
            self._calibration_problem = problem
            return
        self._calibration_problem = None
        with self._lock:
            self.camera.offer(calib)
        self._publish_camera_info()

    def _publish_camera_info(self) -> None:
        """Publish the uplink camera on ``uplink/camera_info`` (latched) when it differs from the last one sent."""
        with self._lock:
            intrinsics, frame_id = self.camera.intrinsics, self.params.camera_frame_id
            if intrinsics is None or (intrinsics, frame_id) == self._info_sent:
                return
            self._info_sent = (intrinsics, frame_id)
            self.camera_info_changes += 1
            described = self.camera.describe()
        self._pub_info.publish(camera_info_from_intrinsics(intrinsics, self.get_clock().now().nanoseconds, frame_id))
        self.get_logger().info(f"camera_info → uplink/camera_info: {described}, frame {frame_id!r}")

    def _on_image(self, msg: Image) -> None:
        try:
            rgb = image_from_msg(msg)
            stamp_ns = stamp_to_ns(msg.header.stamp)
        except ValueError as err:
            self.get_logger().warning(f"camera frame refused: {err}", throttle_duration_sec=5.0)
            return
        with self._lock:
            self._frame, self._frame_ns = rgb, self.get_clock().now().nanoseconds
            self._frame_stamp_ns = stamp_ns

    def _on_odom(self, msg: Odometry) -> None:
        p = msg.pose.pose
        try:
            stamp_ns = stamp_to_ns(msg.header.stamp)
        except ValueError as err:
            self.get_logger().warning(f"odometry refused: {err}", throttle_duration_sec=5.0)
            return
        with self._lock:
            self._poses.add(stamp_ns, odom_to_map(self.params.map_from_odom, p.position.x, p.position.y,
                                                  yaw_of(p.orientation)), self.get_clock().now().nanoseconds)

    def _on_channel(self, msg: Float64MultiArray) -> None:
        try:
            sample = channel_sample_from_msg(msg)
        except ValueError as err:
            self.get_logger().warning(f"channel sample refused: {err}", throttle_duration_sec=5.0)
            return
        with self._lock:
            pose = self._poses.latest
            if pose is not None:  # the Rician band around the path-loss prediction where the robot is
                distance = self.link.distance_m(pose[:2])
                reason = self.gain_band.problem(sample.gain, self.link.mean_gain(pose[:2]), distance)
                if reason:
                    self.implausible[reason] += 1
                    self.get_logger().warning(f"channel sample refused ({reason}): gain {sample.gain:.3g} for slot "
                                              f"{sample.slot}", throttle_duration_sec=5.0)
                    return
            self._gains[sample.slot] = (sample.gain, sample.round_slot)
            if len(self._gains) > 64:
                for old in sorted(self._gains)[:-32]:
                    del self._gains[old]

    def _on_schedule(self, msg: Float64MultiArray, gid: bytes = b"") -> None:
        """A schedule from an admitted writer: refused (counted) when malformed, of another τ, implausible (T, slots,
        powers) or not newer than the last one of the same writer endpoint (seq)."""
        try:
            sched = schedule_from_msg(msg)
        except ValueError as err:
            self.implausible["schedule_malformed"] += 1
            self.get_logger().error(f"schedule refused: {err}", throttle_duration_sec=5.0)
            return
        if abs(sched.slot_s - self.slot_s) > 1e-9:
            self.implausible["schedule_slot_s"] += 1
            self.get_logger().error(f"schedule refused: slot_s {sched.slot_s} != {self.slot_s}",
                                    throttle_duration_sec=5.0)
            return
        reason = schedule_problem(sched, self.clock.slot_at(self.get_clock().now().nanoseconds),
                                  self._schedule_limits)
        if reason is None:
            seq = self._schedule_seq.check(gid, sched.seq)
            if seq == "repeat":  # the same schedule delivered again (latched): nothing new
                return
            reason = "schedule_seq" if seq == "older" else None
        if reason:
            self.implausible[reason] += 1
            self.get_logger().warning(f"schedule seq {sched.seq} refused ({reason}) from "
                                      f"{self.inputs.writer_of('gsrmr/schedule', gid)}", throttle_duration_sec=5.0)
            return
        with self._lock:  # the one before stays for the slots the new one starts after (one that began)
            self._schedule, self._schedule_before = sched, self._schedule

    # ---------------------------------------------------------------- slots
    def _tick(self) -> None:
        now_ns = self.get_clock().now().nanoseconds
        due = self._ticker.poll(now_ns)
        if due is None:
            return
        slot, skipped = due
        if skipped:
            self.get_logger().warning(f"{skipped} slot(s) skipped (node overloaded)", throttle_duration_sec=5.0)
        self.run_slot(slot, now_ns)

    def run_slot(self, slot: int, now_ns: int) -> None:
        """Gather the slot's inputs, let the core decide, publish (public for tests)."""
        with self._lock:
            fresh = self._frame is not None and not stale(self._frame_stamp_ns, self._frame_ns, now_ns,
                                                          round(self.params.max_frame_age_s * 1e9))
            raw = self._frame if fresh else None
            frame = self._uplink_frame(raw) if raw is not None else None
            frame_stamp_ns = self._frame_stamp_ns if frame is not None else None
            pose = self._poses.at(frame_stamp_ns, now_ns, round(self.params.max_pose_age_s * 1e9))
            sched = covering_schedule(slot, self._schedule, self._schedule_before)
            frame_id = self.params.camera_frame_id
            gain, round_slot = self._gains.get(slot, (None, -1))
            now_s = now_ns / 1e9
            queued = self.params.hold_images_while_queued and self.backlog.queued(now_s)
            decision = self.core.run_slot(SlotInputs(slot, frame, frame_stamp_ns, pose,
                                                     sched.lookup(slot) if sched is not None else None, gain,
                                                     sched.threshold(slot) if sched is not None else None,
                                                     round_slot, queued, self.backlog.rate_bps))
        self.channel_unmeasured += int(gain is None)
        if decision.scene_changed:
            det = self.core.scene_change
            self.get_logger().info(f"scene change in slot {slot} (frame difference {det.last_score:.4f}, recent "
                                   f"median {det.baseline():.4f}): an image goes at the first fair fade within "
                                   f"{self.params.scene_change_wait_slots} slots")
        self.schedule_misses += int(not decision.scheduled)
        self.no_frame += int(raw is None)
        self.frames_uncalibrated += int(raw is not None and frame is None)
        self.no_pose += int(decision.key is None)
        stamp_ns = self.clock.start_ns(slot)
        if decision.publish_row:  # first: the server waits for it to know whether an image follows
            self._pub_ledger.publish(ledger_to_msg(decision.row))
        if decision.jpeg is not None:
            self._pub_img.publish(compressed_to_msg(decision.jpeg, stamp_ns, frame_id))
            self.backlog.sent(8 * len(decision.jpeg), self.get_clock().now().nanoseconds / 1e9)
            if self._ack_timer.is_canceled():
                self._ack_timer.reset()
        if decision.key is not None:
            self._pub_key.publish(pose_key_to_msg(decision.key, self.clock))

    def _uplink_frame(self, raw: np.ndarray) -> np.ndarray | None:
        """The raw frame rectified and sized for the uplink (the very array when it passes through); None when it
        cannot be: no calibration yet (INFO) or a frame of another size (WARN), both throttled."""
        try:
            return self.camera.frame(raw)
        except CalibrationError as err:
            log = self.get_logger()
            if self.camera.is_calibrated:
                log.warning(f"frame not uploaded: {err}", throttle_duration_sec=5.0)
            else:
                log.info("frames are not uploaded (pose keys only) until camera/camera_info arrives",
                         throttle_duration_sec=10.0)
            return None

    def _poll_acks(self) -> None:
        """Every image published so far acknowledged by every matched reader: book the delay, stop polling."""
        if not self.backlog.waiting or not self.backlog.acks_trusted:  # untrusted: the throughput model times it
            self._ack_timer.cancel()
            return
        if self._pub_img.wait_for_all_acked(Duration(seconds=0)):
            self.backlog.acked(self.get_clock().now().nanoseconds / 1e9)
            self._ack_timer.cancel()

    def _check_image_readers(self) -> None:
        """Trust the image writer's acknowledgements only while every matched reader is one of ``image_readers``."""
        readers = {join_node_name(i.node_namespace, i.node_name)
                   for i in self.get_subscriptions_info_by_topic(self._pub_img.topic_name)}
        strangers = tuple(sorted(readers - self._image_readers))
        if strangers != self.stranger_readers:
            self.get_logger().warning(
                f"image readers not in image_readers: {', '.join(strangers)} — their acknowledgements are not waited "
                "for: the hold-back times images by the measured throughput" if strangers else
                "every image reader is a known one again: the hold-back follows the acknowledgements")
        self.stranger_readers = strangers
        with self._lock:
            self.backlog.acks_trusted = not strangers
        if not strangers and self.backlog.waiting and self._ack_timer.is_canceled():
            self._ack_timer.reset()

    def _publish_diagnostics(self) -> None:
        totals = self.ledger.totals()
        extra = {"schedule_misses": self.schedule_misses, "no_frame": self.no_frame, "no_pose": self.no_pose,
                 "schedule_seq": self._schedule.seq if self._schedule else -1,
                 "channel_unmeasured": self.channel_unmeasured,
                 "camera_info_changes": self.camera_info_changes, "frames_uncalibrated": self.frames_uncalibrated,
                 "uplink_camera": self.camera.describe(), "tf_published": self._tf_static is not None,
                 "uplink_rate_bps_estimate": round(self.backlog.rate_bps, 1),
                 "image_ack_delay_ms": round(1e3 * self.backlog.last_ack_delay_s, 2),
                 "image_queued_for_ms": round(1e3 * self.backlog.queued_for_s(
                     self.get_clock().now().nanoseconds / 1e9), 1),
                 "image_readers_unknown": ",".join(self.stranger_readers) or "none",
                 "images_delivered_by_model": self.backlog.model_deliveries,
                 "scene_changes": self.core.scene_change.changes if self.core.scene_change else -1,
                 "scene_change_images": self.core.change_images,
                 "implausible": json.dumps(self.implausible.values_for_diagnostics()),
                 **{k: json.dumps(v) if isinstance(v, dict) else v
                    for k, v in {**self.inputs.diagnostic_values(), **self.audit.diagnostic_values()}.items()}}
        self._pub_diag.publish(diagnostics_msg(
            self, name=f"{self.get_name()}: uplink energy ledger", hardware_id="gsrmr_robot",
            values={**totals, **extra}, problems=self._problems()))

    def on_shutdown(self) -> None:
        """Log what the input checks refused (called by run_node on exit)."""
        self.inputs.log_summary(self.implausible, image_readers_unknown=list(self.stranger_readers),
                                images_delivered_by_model=self.backlog.model_deliveries)

    def _problems(self) -> list[str]:
        """What ``/diagnostics`` warns about: missing frames or pose, no calibration yet, a refused calibration."""
        out = ["missing frames or pose"] if self.no_frame or self.no_pose else []
        out += self.inputs.problems()
        if self.implausible:
            out.append("implausible inputs refused: " + ", ".join(f"{k} {n}" for k, n in
                                                                  sorted(self.implausible.items())))
        if self.stranger_readers:
            out.append(f"unknown readers of the uplink images: {', '.join(self.stranger_readers)}")
        if not self.camera.is_calibrated:
            out.append("waiting for camera_info")
        if self._calibration_problem is not None:
            out.append(f"camera_info refused: {self._calibration_problem}")
        return out


@console_main
def main(args: list[str] | None = None) -> int:
    """Console script ``gsrmr-robot`` (the uplink DDS profile unless one is set: :mod:`gsrmr_robot.dds_profile`)."""
    use_uplink_profile()
    return run_node(RobotNode, args)

