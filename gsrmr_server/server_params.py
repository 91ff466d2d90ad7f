"""The server node's parameters (:class:`ServerParameters`): names, defaults, descriptors and rules (pure, no ROS).

:class:`gsrmr_server.server_node.ServerNode` declares them, refuses a change :meth:`ServerParameters.change_problem`
gives a reason for and applies an accepted one by replacing its ``params``; live ones only with
``live_parameter_changes``. None is simulation-only: scoring the MR images against the simulator's truth is the
simulation's scorer node (``gsrmr-sim-scorer``, :mod:`gsrmr_sim.world.scorer_node`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gsrmr_common.camera import CameraMount
from gsrmr_common.link_model import SLOT_S, LinkBudget
from gsrmr_common.link_params import LinkParameters
from gsrmr_common.mount_params import MOUNT_PREFIX, CameraMountParameters
from gsrmr_common.node_help import Endpoint, NodeInterface, ParameterGroup
from gsrmr_common.node_params import NodeParameters, ros_parameter
from gsrmr_common.writer_admission import writer_list_problem

LIVE_PARAMETERS = frozenset({"process_delay_s", "measure_loss", "max_compose_level", "jpeg_quality",
                             "max_backlog_slots", "model_path"})
#: The read-only lists of node names allowed to write the server's input topics (relative: in its namespace; * any).
WRITER_LISTS = ("robot_writers", "schedule_writers", "cmd_vel_writers")


@dataclass(frozen=True)
class ServerParameters(NodeParameters):
    """Every parameter of the server node (ROS names; units in the names)."""

    slot_s: float = ros_parameter(SLOT_S, "Slot length τ [s]; must equal the robot's", min_value=0.01,
                                  max_value=10.0, read_only=True)
    process_delay_s: float = ros_parameter(
        0.03, "Compose slot k at the latest this long after its start [s], earlier once its uploads are "
        "complete (uploads arriving after composition are counted late)", min_value=0.0, max_value=5.0)
    model_path: str = ros_parameter(
        "", "Gaussian-splatting model (.ply, 3DGS layout); a new one set at run time is loaded off the slot path and "
        "used from the first slot after it is ready")
    mr_content: str = ros_parameter("sandbox", "MR content: the virtual agents and their lights (name in "
                                    "config/mr or a YAML path)", read_only=True)
    background_rgb: tuple[float, ...] = ros_parameter(
        (0.5, 0.55, 0.6), "Colour where the GS model has no density (its training background), linear RGB in "
        "[0, 1]", read_only=True)
    measure_loss: bool = ros_parameter(True, "Render Φ(s_t) in image slots and publish the measured GS loss")
    max_compose_level: int = ros_parameter(
        2, "Cheapest composition level a slot short of time may take: 0 = always the full-size render, 1 = the render "
        "at half size, 2 = at a quarter (enlarged; the loss sample and the localizer are skipped in such slots)",
        min_value=0, max_value=2)
    record_dir: str = ros_parameter("", "Write slots.csv and MCAP here ('' = off)", read_only=True)
    jpeg_quality: int = ros_parameter(85, "JPEG quality of mr/image/compressed", min_value=1, max_value=100)
    max_backlog_slots: int = ros_parameter(
        30, "Slots the node may fall behind and still compose every missed one (late); further behind it skips "
        "ahead and counts skipped_slots", min_value=1, max_value=100_000)
    render_threads: int = ros_parameter(
        1, "CPU threads of the GS render (0 = every core); one thread is steadier when other processes share "
        "the cores", min_value=0, max_value=256, read_only=True)
    live_parameter_changes: bool = ros_parameter(
        False, "Allow the live parameters to change while the node runs (any participant may call the parameter "
        "service without SROS2; every change is logged)", read_only=True)
    robot_writers: tuple[str, ...] = ros_parameter(
        ("gsrmr_robot",), "Nodes whose uplink/pose_key, uplink/image_raw/compressed, uplink/camera_info and "
        "gsrmr/ledger are taken: the robot (and a relay between; relative names resolve in the server's namespace)",
        read_only=True)
    schedule_writers: tuple[str, ...] = ros_parameter(("gsrmr_scheduler",), "Nodes whose gsrmr/schedule is taken",
                                                      read_only=True)
    cmd_vel_writers: tuple[str, ...] = ros_parameter(("*",), "Nodes whose cmd_vel is recorded (* = any)",
                                                     read_only=True)
    max_speed_mps: float = ros_parameter(
        1.5, "The robot's top speed: pose keys moving faster are refused (a relocalisation is accepted after 5 keys "
        "that agree with each other); the LIMO clamps each axis to 1 m/s, √2 diagonally in mecanum mode [m/s]",
        min_value=0.01, max_value=20.0, read_only=True)
    localization: bool = ros_parameter(
        True, "Localize the robot from the images it uploads (one registration a second at most, off the slot path) "
        "and publish map → odom corrections on gsrmr/map_correction", read_only=True)
    localization_interval_s: float = ros_parameter(
        1.0, "Register at most one received image per this many seconds", min_value=0.1, max_value=60.0,
        read_only=True)
    # Declared read-only by gsrmr_common.ros_node.declare_camera_mount / declare_link_budget (config/*.yaml).
    camera_mount: CameraMount = field(default_factory=CameraMount)
    link: LinkBudget = field(default_factory=LinkBudget)

    @classmethod
    def rule(cls, name: str, value: Any) -> str | None:
        """``model_path`` is required; ``background_rgb`` is 3 numbers in [0, 1]; a writer list names nodes."""
        if name == "model_path" and not value:
            return "model_path is required (a 3DGS .ply)"
        if name == "background_rgb" and (len(value) != 3 or not all(0.0 <= c <= 1.0 for c in value)):
            return "background_rgb must be 3 numbers in [0, 1]"
        if name in WRITER_LISTS:
            return writer_list_problem(name, value)
        return None

    @classmethod
    def change_problem(cls, name: str, value: Any) -> str | None:
        """As :meth:`NodeParameters.change_problem`; a new ``model_path`` must also be a file (the on-set check: at
        start-up a missing file fails the load with its own error)."""
        if name == "model_path" and value and not Path(str(value)).is_file():
            return f"model_path {value!r} is no file (a 3DGS .ply)"
        return super().change_problem(name, value)

    @property
    def render_threads_or_all(self) -> int | None:
        """``render_threads`` as the renderer takes it: None = every core."""
        return self.render_threads or None


#: What ``gsrmr-server --help`` prints.
INTERFACE = NodeInterface(
    executable="gsrmr-server", node="gsrmr_server",
    summary="The simulation server: each slot it composes the MR image from the received camera image, or from a "
            "Gaussian-splatting render at the pose key, with the virtual world (m = d·r + (1 − d)·v), and measures "
            "the GS loss in image slots.",
    subscribes=(Endpoint("uplink/pose_key", "geometry_msgs/msg/Vector3Stamped"),
                Endpoint("uplink/image_raw/compressed", "sensor_msgs/msg/CompressedImage"),
                Endpoint("uplink/camera_info", "sensor_msgs/msg/CameraInfo", "latched"),
                Endpoint("gsrmr/schedule", "std_msgs/msg/Float64MultiArray"),
                Endpoint("gsrmr/ledger", "std_msgs/msg/Float64MultiArray"),
                Endpoint("cmd_vel", "geometry_msgs/msg/Twist", "where the robot is heading (fallback pose)")),
    publishes=(Endpoint("mr/image", "sensor_msgs/msg/Image", "rgb8"),
               Endpoint("mr/image/compressed", "sensor_msgs/msg/CompressedImage"),
               Endpoint("mr/slot_info", "std_msgs/msg/Float64MultiArray", "what each MR image was composed from"),
               Endpoint("gsrmr/loss_sample", "std_msgs/msg/Float64MultiArray", "the GS loss at an image slot's key"),
               Endpoint("gsrmr/map_correction", "std_msgs/msg/Float64MultiArray", "the robot's map → odom "
                        "correction, latched (localization)"),
               Endpoint("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")),
    parameters=(ParameterGroup(ServerParameters), ParameterGroup(CameraMountParameters, MOUNT_PREFIX),
                ParameterGroup(LinkParameters)))
