"""The robot node's parameters (:class:`RobotParameters`): names, defaults, descriptors and rules (pure, no ROS).

:class:`gsrmr_robot.robot_node.RobotNode` declares them, refuses a change :meth:`RobotParameters.change_problem`
gives a reason for and applies an accepted one by replacing its ``params``. Live: :data:`LIVE_PARAMETERS`, and only
with ``live_parameter_changes`` (``docs/security.md``, "Services, parameters, readers").
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
from typing import Any

from gsrmr_common.camera import CameraMount
from gsrmr_common.link_model import SLOT_S, LinkBudget
from gsrmr_common.link_params import LinkParameters
from gsrmr_common.mount_params import MOUNT_PREFIX, CameraMountParameters
from gsrmr_common.node_help import Endpoint, NodeInterface, ParameterGroup
from gsrmr_common.node_params import NodeParameters, ros_parameter
from gsrmr_common.tf_tree import BASE_FRAME, CAMERA_OPTICAL_FRAME, ODOM_FRAME
from gsrmr_common.writer_admission import writer_list_problem

LIVE_PARAMETERS = frozenset({"jpeg_quality", "uplink_width_px", "default_upload_image", "max_frame_age_s",
                             "max_pose_age_s", "map_from_odom", "camera_frame_id", "hold_images_while_queued",
                             "uplink_ack_stale_s"})
#: The read-only lists of node names (relative: in the robot's namespace; ``*``: any) allowed to write an input
#: topic, or — ``image_readers`` — whose acknowledgements the hold-back waits for.
WRITER_LISTS = ("schedule_writers", "channel_writers", "camera_writers", "odom_writers", "image_readers",
                "correction_writers")
#: Where map → odom comes from: the server's corrections of ``map_from_odom``; another localizer's base pose in
#: ``map`` (AMCL's ``amcl_pose``) or its ``map → odom`` on ``/tf``; or the parameter alone.
LOCALIZATION_SOURCES = ("server", "pose", "tf", "off")
#: The other localizer's pose of ``base_link`` in ``map`` (``localization`` pose); slam_toolbox: remap to ``pose``.
LOCALIZER_POSE_TOPIC = "amcl_pose"


@dataclass(frozen=True)
class RobotParameters(NodeParameters):
    """Every parameter of the robot node (ROS names; units in the names)."""

    slot_s: float = ros_parameter(SLOT_S, "Slot length τ [s]; must equal the server's", min_value=0.01,
                                  max_value=10.0, read_only=True)
    jpeg_quality: int = ros_parameter(80, "JPEG quality of uploaded images (1-100)", min_value=1, max_value=100)
    uplink_width_px: int = ros_parameter(
        320, "Width of uploaded images [px]: camera frames are rectified to the pinhole camera and scaled down to it "
        "(aspect kept; narrower frames are not enlarged); uplink/camera_info describes the result",
        min_value=16, max_value=4096)
    default_upload_image: bool = ros_parameter(True, "Upload the image in slots no schedule covers")
    max_frame_age_s: float = ros_parameter(0.5, "Older camera frames are not uploaded [s]", min_value=0.0,
                                           max_value=10.0)
    max_pose_age_s: float = ros_parameter(
        0.5, "No pose key is sent when the newest odometry pose arrived longer ago than this [s] (odometry or this "
        "node stalled: the server renders at its extrapolated pose instead)", min_value=0.02, max_value=10.0)
    map_from_odom: tuple[float, ...] = ros_parameter((0.0, 0.0, 0.0),
                                                     "Pose of the odom frame in map: [a_m, b_m, theta_rad]")
    camera_frame_id: str = ros_parameter(CAMERA_OPTICAL_FRAME, "Frame of uploaded images: the camera's optical "
                                         "frame (x right, y down, z forward)")
    hold_images_while_queued: bool = ros_parameter(
        True, "Send the pose key only (ledger held_back = 1) when the schedule asks for an image while the last one "
        "is still unacknowledged by the server (queued on the link)")
    uplink_ack_stale_s: float = ros_parameter(1.0, "An image unacknowledged this long no longer holds the next one "
                                              "back [s]", min_value=0.05, max_value=60.0)
    scene_change_ratio: float = ros_parameter(
        4.0, "Send an image when the camera's view changes suddenly: a slot's frame differs from the previous slot's "
        "by more than this many times the recent median difference (gsrmr_robot.scene_change; 0 = off)",
        min_value=0.0, max_value=100.0, read_only=True)
    scene_change_wait_slots: int = ros_parameter(
        5, "After a scene change, the slots (that one included) in which an image goes at the first fair fade "
        "(above the 30 % quantile of fades at once, the 10 % one in the last slot)", min_value=1, max_value=100,
        read_only=True)
    odom_frame_id: str = ros_parameter(ODOM_FRAME, "Odometry frame (child of map in TF)", read_only=True)
    base_frame_id: str = ros_parameter(BASE_FRAME, "Robot body frame (parent of the camera in TF)", read_only=True)
    live_parameter_changes: bool = ros_parameter(
        False, "Allow the live parameters to change while the node runs (any participant may call the parameter "
        "service without SROS2; every change is logged)", read_only=True)
    schedule_writers: tuple[str, ...] = ros_parameter(
        ("gsrmr_scheduler",), "Nodes whose gsrmr/schedule is taken (relative names resolve in the robot's namespace; "
        "* = any)", read_only=True)
    channel_writers: tuple[str, ...] = ros_parameter(
        ("*",), "Nodes whose radio/channel_gain is taken: the radio driver (* = any)", read_only=True)
    camera_writers: tuple[str, ...] = ros_parameter(
        ("*",), "Nodes whose camera/image_raw and camera/camera_info are taken: the camera driver (* = any)",
        read_only=True)
    odom_writers: tuple[str, ...] = ros_parameter(
        ("*",), "Nodes whose odom is taken: the base driver (* = any)", read_only=True)
    image_readers: tuple[str, ...] = ros_parameter(
        ("gsrmr_server",), "Readers of uplink/image_raw/compressed whose acknowledgements hold images back; with "
        "another reader matched the hold-back times images by the measured throughput instead", read_only=True)
    max_tx_power_w: float = ros_parameter(
        0.1, "The radio's maximum transmit power [W]: a schedule asking for more is refused", min_value=1e-6,
        max_value=10.0, read_only=True)
    localization: str = ros_parameter(
        "server", "Where map → odom comes from: server = map_from_odom corrected by the server's gsrmr/map_correction "
        "(the server localizes the robot from its images); pose = another localizer's base pose in map on amcl_pose "
        "(AMCL; slam_toolbox: remap amcl_pose:=pose) with the odometry at its stamp; tf = that localizer's map → odom "
        "on /tf (needs tf2_msgs: a ROS 2 install); off = map_from_odom alone", read_only=True,
        constraints="one of: server, pose, tf, off")
    odometry_calibration: bool = ros_parameter(
        True, "With localization server: scale the odometry's distances by a gain and a turn slip learned from the "
        "server's corrections (keys between fixes err less on wheels that slip)", read_only=True)
    correction_writers: tuple[str, ...] = ros_parameter(
        ("gsrmr_server", "amcl", "slam_toolbox"), "Nodes whose map → odom is taken: gsrmr/map_correction "
        "(localization server), amcl_pose (pose) or map → odom on /tf (tf)", read_only=True)
    max_correction_step_m: float = ros_parameter(
        0.5, "A correction moving map → odom further than this from the one in force is refused [m]", min_value=0.01,
        max_value=10.0, read_only=True)
    max_correction_step_deg: float = ros_parameter(
        20.0, "… or turning it more than this [deg]", min_value=0.1, max_value=180.0, read_only=True)
    # Declared read-only by gsrmr_common.ros_node.declare_camera_mount / declare_link_budget (config/*.yaml).
    camera_mount: CameraMount = field(default_factory=CameraMount)
    link: LinkBudget = field(default_factory=LinkBudget)

    @classmethod
    def rule(cls, name: str, value: Any) -> str | None:
        """``map_from_odom`` is 3 finite numbers; ``camera_frame_id`` is not empty; a writer list names nodes."""
        if name == "map_from_odom" and (len(value) != 3 or not all(math.isfinite(v) for v in value)):
            return "map_from_odom must be 3 finite numbers [a_m, b_m, theta_rad]"
        if name == "scene_change_ratio" and 0.0 < value <= 1.0:
            return "scene_change_ratio must be 0 (off) or > 1"
        if name == "camera_frame_id" and not value:
            return "camera_frame_id must not be empty"
        if name == "localization" and value not in LOCALIZATION_SOURCES:
            return f"localization must be one of {', '.join(LOCALIZATION_SOURCES)}, got {value!r}"
        if name in WRITER_LISTS:
            return writer_list_problem(name, value)
        return None


#: What ``gsrmr-robot --help`` prints.
INTERFACE = NodeInterface(
    executable="gsrmr-robot", node="gsrmr_robot",
    summary="The robot's uplink: each slot τ it uploads the rectified camera image (JPEG) or only the 192-bit pose "
            "key, as the schedule and the measured channel gain say, and books the energy in its ledger.",
    subscribes=(Endpoint("camera/image_raw", "sensor_msgs/msg/Image", "sensor-data QoS"),
                Endpoint("camera/camera_info", "sensor_msgs/msg/CameraInfo", "the driver's calibration"),
                Endpoint("odom", "nav_msgs/msg/Odometry", "odom → base_link (REP-105)"),
                Endpoint("gsrmr/schedule", "std_msgs/msg/Float64MultiArray", "the plan (x_t, p_t), latched"),
                Endpoint("radio/channel_gain", "std_msgs/msg/Float64MultiArray", "the radio's gain per slot"),
                Endpoint("gsrmr/map_correction", "std_msgs/msg/Float64MultiArray", "the server's map → odom "
                         "correction (localization server)"),
                Endpoint(LOCALIZER_POSE_TOPIC, "geometry_msgs/msg/PoseWithCovarianceStamped", "another localizer's "
                         "base_link in map (localization pose)"),
                Endpoint("/tf", "tf2_msgs/msg/TFMessage", "another localizer's map → odom (localization tf)")),
    publishes=(Endpoint("uplink/pose_key", "geometry_msgs/msg/Vector3Stamped", "(a_m, b_m, theta_rad) in map"),
               Endpoint("uplink/image_raw/compressed", "sensor_msgs/msg/CompressedImage", "JPEG, image slots"),
               Endpoint("uplink/camera_info", "sensor_msgs/msg/CameraInfo", "the uploaded pinhole camera, latched"),
               Endpoint("gsrmr/ledger", "std_msgs/msg/Float64MultiArray", "one energy-ledger row per slot"),
               Endpoint("/tf", "tf2_msgs/msg/TFMessage", "map → odom (localization server or off; with tf2_ros)"),
               Endpoint("/tf_static", "tf2_msgs/msg/TFMessage", "base_link → camera (with tf2_ros)"),
               Endpoint("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")),
    parameters=(ParameterGroup(RobotParameters), ParameterGroup(CameraMountParameters, MOUNT_PREFIX),
                ParameterGroup(LinkParameters)))
