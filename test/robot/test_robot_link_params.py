"""The robot node's parameters (gsrmr_robot.robot_params) and config/link.yaml's (gsrmr_common.link_params) as
NodeParameters tables: what the nodes declared before (names, defaults, ranges, read-only flags, descriptions),
the rules their on-set callbacks refuse with, and one table read by the nodes and the simulator alike.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import rclpy
from rclpy.exceptions import InvalidParameterValueException
from rclpy.parameter import Parameter
import yaml

from gsrmr_common.camera import CameraMount
from gsrmr_common.link_model import LinkBudget
from gsrmr_common.link_params import LinkParameters, dbm_to_w, w_to_dbm
from gsrmr_common.ros_node import declare_link_budget
from gsrmr_robot.robot_node import RobotNode
from gsrmr_robot.robot_params import LIVE_PARAMETERS, RobotParameters
from gsrmr_sim.sim_stack import link_budget

REPO = Path(__file__).resolve().parents[2]

# name: (default, (min, max) or None, read_only, description) — what the robot node declared inline before
# (and uplink_width_px, added with the uplink's rectification).
ROBOT_DECLARED = {
    "slot_s": (0.1, (0.01, 10.0), True, "Slot length τ [s]; must equal the server's"),
    "jpeg_quality": (80, (1, 100), False, "JPEG quality of uploaded images (1-100)"),
    "uplink_width_px": (320, (16, 4096), False, "Width of uploaded images [px]: camera frames are rectified to the "
                        "pinhole camera and scaled down to it (aspect kept; narrower frames are not enlarged); "
                        "uplink/camera_info describes the result"),
    "default_upload_image": (True, None, False, "Upload the image in slots no schedule covers"),
    "max_frame_age_s": (0.5, (0.0, 10.0), False, "Older camera frames are not uploaded [s]"),
    "max_pose_age_s": (0.5, (0.02, 10.0), False, "No pose key is sent when the newest odometry pose arrived longer "
                       "ago than this [s] (odometry or this node stalled: the server renders at its extrapolated "
                       "pose instead)"),
    "map_from_odom": ([0.0, 0.0, 0.0], None, False, "Pose of the odom frame in map: [a_m, b_m, theta_rad]"),
    "camera_frame_id": ("camera_optical_frame", None, False,
                        "Frame of uploaded images: the camera's optical frame (x right, y down, z forward)"),
    "hold_images_while_queued": (True, None, False, "Send the pose key only (ledger held_back = 1) when the schedule "
                                 "asks for an image while the last one is still unacknowledged by the server "
                                 "(queued on the link)"),
    "uplink_ack_stale_s": (1.0, (0.05, 60.0), False,
                           "An image unacknowledged this long no longer holds the next one back [s]"),
    # issue 25: images for sudden changes of the camera's view
    "scene_change_ratio": (4.0, (0.0, 100.0), True, "Send an image when the camera's view changes suddenly: a slot's "
                           "frame differs from the previous slot's by more than this many times the recent median "
                           "difference (gsrmr_robot.scene_change; 0 = off)"),
    "scene_change_wait_slots": (5, (1, 100), True, "After a scene change, the slots (that one included) in which an "
                                "image goes at the first fair fade (above the 30 % quantile of fades at once, the 10 % "
                                "one in the last slot)"),
    "odom_frame_id": ("odom", None, True, "Odometry frame (child of map in TF)"),
    "base_frame_id": ("base_link", None, True, "Robot body frame (parent of the camera in TF)"),
    # issue 28: live changes off unless started so; the known-writer lists; the radio's maximum power
    "live_parameter_changes": (False, None, True, "Allow the live parameters to change while the node runs (any "
                               "participant may call the parameter service without SROS2; every change is logged)"),
    "schedule_writers": (["gsrmr_scheduler"], None, True, "Nodes whose gsrmr/schedule is taken (relative names "
                         "resolve in the robot's namespace; * = any)"),
    "channel_writers": (["*"], None, True, "Nodes whose radio/channel_gain is taken: the radio driver (* = any)"),
    "camera_writers": (["*"], None, True, "Nodes whose camera/image_raw and camera/camera_info are taken: the camera "
                       "driver (* = any)"),
    "odom_writers": (["*"], None, True, "Nodes whose odom is taken: the base driver (* = any)"),
    "image_readers": (["gsrmr_server"], None, True, "Readers of uplink/image_raw/compressed whose acknowledgements "
                      "hold images back; with another reader matched the hold-back times images by the measured "
                      "throughput instead"),
    "max_tx_power_w": (0.1, (1e-06, 10.0), True, "The radio's maximum transmit power [W]: a schedule asking for more "
                       "is refused"),
    # the server's localization: where map → odom comes from and which corrections are taken
    "localization": ("server", None, True, "Where map → odom comes from: server = map_from_odom corrected by the "
                     "server's gsrmr/map_correction (the server localizes the robot from its images); pose = another "
                     "localizer's base pose in map on amcl_pose (AMCL; slam_toolbox: remap amcl_pose:=pose) with the "
                     "odometry at its stamp; tf = that localizer's map → odom on /tf (needs tf2_msgs: a ROS 2 "
                     "install); off = map_from_odom alone"),
    "odometry_calibration": (True, None, True, "With localization server: scale the odometry's distances by a gain "
                             "and a turn slip learned from the server's corrections (keys between fixes err less on "
                             "wheels that slip)"),
    "correction_writers": (["gsrmr_server", "amcl", "slam_toolbox"], None, True, "Nodes whose map → odom is taken: "
                           "gsrmr/map_correction (localization server), amcl_pose (pose) or map → odom on /tf (tf)"),
    "max_correction_step_m": (0.5, (0.01, 10.0), True, "A correction moving map → odom further than this from the one "
                              "in force is refused [m]"),
    "max_correction_step_deg": (20.0, (0.1, 180.0), True, "… or turning it more than this [deg]"),
}
# config/link.yaml's parameters, as ros_node.declare_link_budget declared them inline before.
LINK_DECLARED = {
    "bandwidth_hz": (1e6, (1.0, 1e12), True, "Uplink bandwidth B [Hz]"),
    "noise_dbm": (-60.0, (-250.0, 100.0), True, "Noise power σ² [dBm]"),
    "pathloss_db_at_1m": (-30.0, (-300.0, 0.0), True, "Path loss ρ0 at 1 m [dB]"),
    "pathloss_exponent": (3.0, (0.0, 10.0), True, "Path-loss exponent α"),
    "rician_k": (1.0, (0.0, 1e6), True, "Rician K-factor (LoS/NLoS power)"),
    "server_position_m": ([10.0, 0.0], None, True, "Server (x, y) in map [m]"),
    "channel_seed": (7, (0, 2**31 - 1), True, "Seed of the per-slot fading realisation"),
}


def declared(cls) -> dict[str, tuple]:
    defaults = cls().ros_values()
    return {f.name: (defaults[f.name], None if spec.min_value is None else (spec.min_value, spec.max_value),
                     spec.read_only, spec.description) for f, spec in cls.specs()}


@pytest.mark.parametrize(("cls", "want"), [(RobotParameters, ROBOT_DECLARED), (LinkParameters, LINK_DECLARED)])
def test_names_defaults_ranges_read_only_flags_and_descriptions_are_the_declared_ones(cls, want):
    got = declared(cls)
    assert list(got) == list(want)  # the declaration order too
    for name, row in want.items():
        assert got[name] == row, name
        assert type(got[name][0]) is type(row[0]), name  # the ROS type: 0.0 is a double, 0 an integer
        assert cls.problem(name, row[0]) is None, name


def test_robot_live_and_nested_parameters():
    assert set(ROBOT_DECLARED) - RobotParameters.read_only_names() == LIVE_PARAMETERS
    assert RobotParameters().link == LinkBudget() and RobotParameters().camera_mount == CameraMount()


@pytest.mark.parametrize(("name", "value", "reason"), [
    ("map_from_odom", [1.0, 2.0], "map_from_odom must be 3 finite numbers"),
    ("map_from_odom", [1.0, 2.0, math.nan], "3 finite numbers"),
    ("camera_frame_id", "", "camera_frame_id must not be empty"),
    ("jpeg_quality", 0, "jpeg_quality must be in [1, 100]"),
    ("max_frame_age_s", 11.0, "in [0.0, 10.0]"),
    ("uplink_ack_stale_s", 0.01, "in [0.05, 60.0]"),
    ("uplink_width_px", 8, "uplink_width_px must be in [16, 4096]"),
    ("default_upload_image", 1, "must be a bool"),
    ("scene_change_ratio", 1.0, "scene_change_ratio must be 0 (off) or > 1"),
    ("scene_change_wait_slots", 0, "in [1, 100]"),
])
def test_robot_problem_refuses_with_a_reason(name, value, reason):
    got = RobotParameters.problem(name, value)
    assert got is not None and reason in got, got


def test_robot_change_problem_refuses_read_only_and_passes_live_ones():
    assert "slot_s is read-only" in RobotParameters.change_problem("slot_s", 0.2)
    assert "read-only" in RobotParameters.change_problem("odom_frame_id", "odom2")
    assert RobotParameters.change_problem("jpeg_quality", 60) is None
    assert RobotParameters().with_values({"map_from_odom": [1, 2, 3]}).map_from_odom == (1.0, 2.0, 3.0)


def test_link_parameters_describe_the_link_budget():
    assert LinkParameters().budget() == LinkBudget(noise_w=dbm_to_w(-60.0))
    assert w_to_dbm(LinkBudget().noise_w) == pytest.approx(-60.0, abs=1e-12)
    p = LinkParameters().with_values({"noise_dbm": -90.0, "server_position_m": [1.0, 2.0], "channel_seed": 3,
                                      "slot_s": 0.1})  # slot_s: link.yaml's too, but no link-budget parameter
    assert p.budget().noise_w == pytest.approx(1e-12) and p.budget().server_position_m == (1.0, 2.0)
    assert p.budget().channel_seed == 3
    assert "server_position_m must be 2 finite numbers" in LinkParameters.problem("server_position_m", [1.0])


def test_link_yaml_is_read_through_the_same_table(tmp_path):
    """config/link.yaml holds every parameter of the table; the simulator's reader refuses what a node would."""
    data = yaml.safe_load((REPO / "config" / "link.yaml").read_text())
    params = data["/**"]["ros__parameters"]
    assert set(LINK_DECLARED) <= set(params)
    assert link_budget(str(REPO / "config" / "link.yaml")) == LinkParameters().with_values(params).budget()
    assert link_budget(str(REPO / "config" / "link.yaml"), channel_seed=11).channel_seed == 11
    bad = tmp_path / "link.yaml"
    bad.write_text(yaml.safe_dump({"/**": {"ros__parameters": {**params, "rician_k": -1.0}}}))
    with pytest.raises(ValueError, match=r"parameter rician_k must be in \[0.0, 1000000.0\]"):
        link_budget(str(bad))




def test_robot_node_declares_the_table_and_checks_changes(ros_context):
    node = RobotNode(context=ros_context, parameter_overrides=[Parameter("jpeg_quality", value=60),
                                                              Parameter("rician_k", value=2.0),
                                                              Parameter("live_parameter_changes", value=True)])
    try:
        assert node.params.jpeg_quality == node.core.jpeg_quality == 60 and node.link.rician_k == 2.0
        for table in (ROBOT_DECLARED, LINK_DECLARED):
            descriptors = node.describe_parameters(list(table))
            for (name, (_, rng, read_only, description)), d in zip(table.items(), descriptors, strict=True):
                assert (d.read_only, d.description) == (read_only, description), name
                ranges = [*d.integer_range, *d.floating_point_range]
                assert (None if not ranges else (ranges[0].from_value, ranges[0].to_value)) == rng, name
        refused = node.set_parameters([Parameter("camera_frame_id", value=""),
                                       Parameter("map_from_odom", value=[1.0, 2.0])])
        assert not any(r.successful for r in refused)
        assert "camera_frame_id must not be empty" in refused[0].reason
        assert node.params.camera_frame_id == "camera_optical_frame"  # a refused value changes nothing
        assert node.set_parameters([Parameter("uplink_ack_stale_s", value=2.5)])[0].successful
        assert node.params.uplink_ack_stale_s == node.backlog.stale_after_s == 2.5
        assert not node.set_parameters([Parameter("bandwidth_hz", value=2e6)])[0].successful  # read-only
    finally:
        node.destroy_node()


def test_a_whole_number_for_a_double_parameter_is_taken_as_that_float(ros_context):
    """`-p uplink_ack_stale_s:=2` or `map_from_odom: [1, 2, 0]` in a YAML are INTEGER / INTEGER_ARRAY to ROS: rclpy
    alone refuses them for a DOUBLE parameter, at start-up by ending the node. `declare` takes them as floats, at
    start-up and in `ros2 param set` (the parameter service's atomic set); other type mismatches are still refused."""
    node = RobotNode(context=ros_context, parameter_overrides=[Parameter("uplink_ack_stale_s", value=2),
                                                              Parameter("map_from_odom", value=[1, 2, 0]),
                                                              Parameter("rician_k", value=3),
                                                              Parameter("live_parameter_changes", value=True)])
    try:
        assert node.get_parameter("uplink_ack_stale_s").type_ == Parameter.Type.DOUBLE
        assert node.params.uplink_ack_stale_s == 2.0 and isinstance(node.params.uplink_ack_stale_s, float)
        assert node.get_parameter("map_from_odom").type_ == Parameter.Type.DOUBLE_ARRAY
        assert node.params.map_from_odom == (1.0, 2.0, 0.0)
        assert node.link.rician_k == 3.0
        assert node.set_parameters_atomically([Parameter("uplink_ack_stale_s", value=3)]).successful
        assert node.params.uplink_ack_stale_s == node.backlog.stale_after_s == 3.0
        assert node.get_parameter("uplink_ack_stale_s").type_ == Parameter.Type.DOUBLE
        refused = node.set_parameters([Parameter("uplink_ack_stale_s", value="3"),
                                       Parameter("jpeg_quality", value=60.0)])  # a string; a float for an INTEGER
        assert [r.successful for r in refused] == [False, False]
        assert "Wrong parameter type" in refused[0].reason and "Wrong parameter type" in refused[1].reason
        assert node.params.uplink_ack_stale_s == 3.0 and node.params.jpeg_quality != 60.0
        with pytest.raises(InvalidParameterValueException, match="uplink_ack_stale_s"):  # the range still applies
            RobotNode(context=ros_context, parameter_overrides=[Parameter("uplink_ack_stale_s", value=-1)],
                      namespace="range_probe")
    finally:
        node.destroy_node()


def test_a_start_up_value_the_table_refuses_stops_the_node(ros_context):
    with pytest.raises(ValueError, match="parameter map_from_odom must be 3 finite numbers"):
        RobotNode(context=ros_context, parameter_overrides=[Parameter("map_from_odom", value=[0.0, 1.0])])
    node = rclpy.create_node("link_probe", context=ros_context,
                             parameter_overrides=[Parameter("server_position_m", value=[1.0])])
    try:
        with pytest.raises(ValueError, match="parameter server_position_m must be 2 finite numbers"):
            declare_link_budget(node)
    finally:
        node.destroy_node()
