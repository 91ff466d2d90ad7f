"""The robot node (``gsrmr-robot``): each slot, upload the camera image or only the pose key.

Topics and parameters: ``gsrmr-robot --help`` (:data:`~gsrmr_robot.robot_params.INTERFACE`); what it does each slot,
its calibration and TF: ``docs/nodes.md``, "The robot"; what it takes from the graph: ``docs/security.md``. Its logic
is in pure objects: :class:`~gsrmr_robot.uplink_core.UplinkCore`, :class:`~gsrmr_robot.camera_rectify.UplinkCamera`,
:mod:`gsrmr_robot.robot_inputs` and :class:`~gsrmr_robot.uplink_backlog.UplinkBacklog`.
"""

from __future__ import annotations

from dataclasses import replace
import json
import threading

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Vector3Stamped
from nav_msgs.msg import Odometry
import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Float64MultiArray

from gsrmr_common.interrupts import console_main
from gsrmr_common.plausibility import Implausible
from gsrmr_common.pose2d import Pose2D, yaw_from_quaternion
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
    UPLINK_QOS,
    compressed_to_msg,
    image_from_msg,
    ledger_to_msg,
    pose_key_to_msg,
    stamp_to_ns,
)
from gsrmr_common.slot_clock import SlotClock, SlotTicker
from gsrmr_common.wire import MapCorrection
from gsrmr_robot.dds_profile import use_uplink_profile
from gsrmr_robot.external_localizer import ExternalLocalizer
from gsrmr_robot.image_acks import ImageAcks
from gsrmr_robot.key_poses import KeyPoses
from gsrmr_robot.robot_params import INTERFACE, RobotParameters
from gsrmr_robot.scene_change import SceneChangeDetector
from gsrmr_robot.static_tf import StaticFrames
from gsrmr_robot.uplink_backlog import UplinkBacklog
from gsrmr_robot.uplink_camera_port import UplinkCameraPort
from gsrmr_robot.uplink_core import SlotInputs, UplinkCore, stale
from gsrmr_robot.workstation_inputs import WorkstationInputs


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
        self.port = UplinkCameraPort(self, self._pub_info, self.params.uplink_width_px, self._lock)
        self.camera = self.port.camera
        # what is taken from the graph, and from whom (docs/security.md, "Application checks")
        self.implausible = Implausible()
        self.inputs = GatedInputs(self)
        for kind, topic, callback, qos, writers, rate_hz, burst in (
                (Image, "camera/image_raw", self._on_image, qos_profile_sensor_data, p.camera_writers, 100.0, 100.0),
                (CameraInfo, "camera/camera_info", self._on_camera_info, qos_profile_sensor_data, p.camera_writers,
                 100.0, 100.0),
                (Odometry, "odom", self._on_odom, 20, p.odom_writers, 200.0, 200.0)):
            self.inputs.subscribe(kind, topic, lambda msg, _gid, cb=callback: cb(msg), qos, writers, rate_hz=rate_hz,
                                  burst=burst)
        self.workstation = WorkstationInputs(self, self.inputs, p, self.link, self.clock, self._lock, self.implausible,
                                             self._position, self._correction_applied)
        self.schedules, self.gains, self.maps = (self.workstation.schedules, self.workstation.gains,
                                                 self.workstation.maps)
        # the key is map → odom ∘ the (calibrated) odometry pose at the capture time of its frame
        self.keys = KeyPoses(self.maps, p.localization == "server" and p.odometry_calibration)
        self.localizer = ExternalLocalizer(self, self.inputs, p, self.maps, self.keys, self._lock, self.implausible,
                                           self.odom_frame)  # localization pose or tf: another localizer's
        self.acks = ImageAcks(self, self._pub_img, p.image_readers, self.backlog, self._lock)
        # 5 ms tick: slot starts are detected with ≤ 5 ms jitter without a drifting periodic timer.
        # run each slot 1 ms after it starts (polling the clock at 200 Hz cost ~5 % of a core)
        aligned_timer(self, self.clock, 0.001, self._tick)
        self.create_timer(1.0, self._publish_diagnostics)
        self.static_tf = StaticFrames(self, self.odom_frame, self.base_frame, self.params.camera_frame_id)
        self._send_static_tf()
        self.get_logger().info(f"robot uplink: τ={self.slot_s}s, JPEG q={self.params.jpeg_quality}, "
                               f"server at {self.link.server_position_m}")

    def _send_static_tf(self) -> None:
        self.static_tf.send_mount(self.base_frame, self.params.camera_frame_id, self.mount)

    def _validate(self, params) -> SetParametersResult:
        """On-set: refuse a change :class:`RobotParameters` gives a reason for (read-only, type, range, an empty
        frame, a map_from_odom that is no pose) or any change while live changes are off; change nothing."""
        reason = self.audit.problem(RobotParameters, params)
        return SetParametersResult(successful=reason is None, reason=reason or "")

    def _after_set(self, params) -> None:
        """Post-set: apply the accepted values; re-send the static TF when a frame or map_from_odom changed, rebuild
        the rectifier for a new ``uplink_width_px`` and re-publish ``uplink/camera_info`` when it changed."""
        with self._lock:
            self.params = self.audit.applied(self.params, params)
            self.core.jpeg_quality = self.params.jpeg_quality
            self.core.default_upload_image = self.params.default_upload_image
            self.backlog.stale_after_s = self.params.uplink_ack_stale_s
            self.camera.set_uplink_width(self.params.uplink_width_px)
        if any(p.name == "map_from_odom" for p in params):
            with self._lock:
                self.maps.set_parameter(Pose2D.of(self.params.map_from_odom))
        if any(p.name == "camera_frame_id" for p in params):
            self._send_static_tf()
        self.port.publish(self.params.camera_frame_id)  # a new uplink width or camera_frame_id is a new uplink camera

    # ---------------------------------------------------------------- inputs
    def _on_camera_info(self, msg: CameraInfo) -> None:
        self.port.on_camera_info(msg, self.params.camera_frame_id)

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
        p, q = msg.pose.pose, msg.pose.pose.orientation
        try:
            stamp_ns = stamp_to_ns(msg.header.stamp)
        except ValueError as err:
            self.get_logger().warning(f"odometry refused: {err}", throttle_duration_sec=5.0)
            return
        pose = Pose2D(p.position.x, p.position.y, yaw_from_quaternion(q.x, q.y, q.z, q.w))
        with self._lock:
            self.keys.odom(stamp_ns, pose, msg.twist.twist.angular.z, self.get_clock().now().nanoseconds)

    def _correction_applied(self, correction: MapCorrection) -> None:
        """A correction is in force (the lock held): its fix teaches the odometry calibration."""
        self.keys.correction_applied(self.clock.slot_named(round(correction.stamp_s * 1e9)))

    def _position(self) -> tuple[float, float] | None:
        """The robot's latest (x, y) in map (the caller holds the lock)."""
        return self.keys.position()

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
            frame = self.port.frame(raw) if raw is not None else None
            frame_stamp_ns = self._frame_stamp_ns if frame is not None else None
            pose, tf_map_from_odom = self.keys.key(slot, frame_stamp_ns, now_ns,
                                                   round(self.params.max_pose_age_s * 1e9))
            sched = self.schedules.covering(slot)
            frame_id = self.params.camera_frame_id
            gain, round_slot = self.gains.take(slot)
            now_s = now_ns / 1e9
            queued = self.params.hold_images_while_queued and self.backlog.queued(now_s)
            decision = self.core.run_slot(SlotInputs(slot, frame, frame_stamp_ns, pose,
                                                     sched.lookup(slot) if sched is not None else None, gain,
                                                     sched.threshold(slot) if sched is not None else None,
                                                     round_slot, queued, self.backlog.rate_bps, self.maps.seq))
        if self.params.localization in ("server", "off"):  # else the other localizer publishes it
            self.static_tf.send_map_to_odom(tf_map_from_odom, self.odom_frame)
        if decision.scene_changed:
            det = self.core.scene_change
            self.get_logger().info(f"scene change in slot {slot} (frame difference {det.last_score:.4f}, recent "
                                   f"median {det.baseline():.4f}): an image goes at the first fair fade within "
                                   f"{self.params.scene_change_wait_slots} slots")
        self.schedule_misses += int(not decision.scheduled)
        self.no_frame += int(raw is None)
        self.no_pose += int(decision.key is None)
        stamp_ns = self.clock.start_ns(slot)
        if decision.publish_row:  # first: the server waits for it to know whether an image follows
            self._pub_ledger.publish(ledger_to_msg(decision.row))
        if decision.jpeg is not None:
            self._pub_img.publish(compressed_to_msg(decision.jpeg, stamp_ns, frame_id))
            self.acks.sent(8 * len(decision.jpeg))
        if decision.key is not None:
            self._pub_key.publish(pose_key_to_msg(decision.key, self.clock))

    def _publish_diagnostics(self) -> None:
        totals = self.ledger.totals()
        extra = {"schedule_misses": self.schedule_misses, "no_frame": self.no_frame, "no_pose": self.no_pose,
                 "schedule_seq": self.schedules.newest.seq if self.schedules.newest else -1,
                 "correction_seq": self.maps.seq, "odometry_calibration": json.dumps(self.keys.calibration()),
                 "localizer_unmatched": self.localizer.unmatched,
                 "map_from_odom": json.dumps([round(v, 4) for v in self.maps.map_from_odom()]),
                 "channel_unmeasured": self.gains.unmeasured,
                 "camera_info_changes": self.port.changes, "frames_uncalibrated": self.port.frames_withheld,
                 "uplink_camera": self.camera.describe(), "tf_published": self.static_tf.published,
                 "uplink_rate_bps_estimate": round(self.backlog.rate_bps, 1),
                 "image_ack_delay_ms": round(1e3 * self.backlog.last_ack_delay_s, 2),
                 "image_queued_for_ms": round(1e3 * self.backlog.queued_for_s(
                     self.get_clock().now().nanoseconds / 1e9), 1),
                 "image_readers_unknown": ",".join(self.acks.stranger_readers) or "none",
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
        self.inputs.log_summary(self.implausible, image_readers_unknown=list(self.acks.stranger_readers),
                                images_delivered_by_model=self.backlog.model_deliveries)

    def _problems(self) -> list[str]:
        """What ``/diagnostics`` warns about: missing frames or pose, no calibration yet, a refused calibration."""
        out = ["missing frames or pose"] if self.no_frame or self.no_pose else []
        out += self.inputs.problems()
        if self.implausible:
            out.append("implausible inputs refused: " + ", ".join(f"{k} {n}" for k, n in
                                                                  sorted(self.implausible.items())))
        if self.acks.stranger_readers:
            out.append(f"unknown readers of the uplink images: {', '.join(self.acks.stranger_readers)}")
        return out + self.port.problems()


@console_main
def main(args: list[str] | None = None) -> int:
    """Console script ``gsrmr-robot`` (the uplink DDS profile unless one is set: :mod:`gsrmr_robot.dds_profile`)."""
    use_uplink_profile()
    return run_node(RobotNode, args, interface=INTERFACE)

