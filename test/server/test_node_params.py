"""The server's and the scheduler's parameter dataclasses (pure, no ROS): declared names, defaults, ranges
and read-only flags, the rules their nodes' on-set callbacks refuse a change with, and copies with new values.
"""

from __future__ import annotations

from dataclasses import FrozenInstanceError, fields
import json
import math
import subprocess
import sys

import pytest

from gsrmr_common.camera import CameraMount
from gsrmr_common.link_model import LinkBudget
from gsrmr_robot.limo.base_params import MOTION_MODES, LimoBaseParameters
from gsrmr_scheduler.loss_map import LossMap
from gsrmr_scheduler.planner import LIVE_FIELDS
from gsrmr_scheduler.scheduler_params import (
    PLANNING_PARAMETERS,
    STARTUP_EXPLORE_SAMPLES,
    SchedulerParameters,
    route_waypoints,
)
from gsrmr_server.server_params import LIVE_PARAMETERS, ServerParameters

# name: (default, (min, max) or None, read_only) — what the nodes declared before the parameters became a
# dataclass (launch files, config/*.yaml and `ros2 param set` depend on them); the server's simulation-only
# evaluate_ground_truth, hindsight_jpeg_quality and ground_truth_dir went to the simulation's scorer (issue 26).
SERVER_DECLARED = {
    "slot_s": (0.1, (0.01, 10.0), True),
    "process_delay_s": (0.03, (0.0, 5.0), False),
    "model_path": ("", None, False),  # issue 27: live (a model swap), when live changes are on
    "mr_content": ("sandbox", None, True),
    "background_rgb": ([0.5, 0.55, 0.6], None, True),
    "measure_loss": (True, None, False),
    "max_compose_level": (2, (0, 2), False),
    "record_dir": ("", None, True),
    "jpeg_quality": (85, (1, 100), False),
    "max_backlog_slots": (30, (1, 100_000), False),
    "render_threads": (1, (0, 256), True),
    # issue 28: the known-writer lists, live changes off unless started so, the top speed of the pose-key check
    "live_parameter_changes": (False, None, True),
    "robot_writers": (["gsrmr_robot"], None, True),
    "schedule_writers": (["gsrmr_scheduler"], None, True),
    "cmd_vel_writers": (["*"], None, True),
    "max_speed_mps": (1.5, (0.01, 20.0), True),
    # the server's localization of the robot
    "localization": (True, None, True),
    "localization_interval_s": (1.0, (0.1, 60.0), True),
}
SCHEDULER_DECLARED = {
    "slot_s": (0.1, (0.01, 10.0), True),
    "loss_threshold": (0.03, (0.0, 1.0), False),
    "horizon": (100, (1, 100_000), False),
    "method": ("exact", None, False),
    "solver_options": ("{}", None, False),
    "image_bits": (67200.0, (1.0, 1e9), False),
    "pose_bits": (192.0, (1.0, 1e6), False),
    "replan_period_s": (2.0, (0.1, 3600.0), False),
    "replan_on_loss_sample": (True, None, True),
    "drift_threshold": (0.02, (0.0, 1.0), False),
    "drift_window": (3, (1, 1000), False),
    "loss_margin": (0.01, (0.0, 0.99), False),
    "route_waypoints_m": ([0.0], None, True),
    "route_speed_mps": (0.3, (1e-3, 10.0), True),
    "loss_map_file": ("", None, False),  # issue 27: live (re-seeds the forecast after a model swap)
    "loss_prior": (0.05, (0.0, 1.0), True),
    "state_dir": ("", None, True),
    "in_slot_decision": (True, None, True),
    "explore_image_fraction": (0.1, (0.0, 1.0), True),
    "oracle_channel": (False, None, True),
    "image_slot_loss": (-1.0, (-1.0, 1.0), True),
    "loss_sample_offset": (-1.0, (-1.0, 1.0), True),
    "half_level_extra_loss": (0.003, (0.0, 1.0), True),
    "quarter_level_extra_loss": (0.020, (0.0, 1.0), True),
    "margin_quantile": (0.6, (0.0, 1.0), True),
    "burst_time_constant_slots": (25.0, (0.1, 1e6), True),
    "probe_gap_slots": (20, (0, 100_000), True),
    "stale_fix_m": (2.0, (0.0, 100.0), True),
    "round_slots": (0, (0, 10_000_000), True),
    # issue 28: the known-writer lists, live changes off unless started so, pose-key check, replan rate limit
    "live_parameter_changes": (False, None, True),
    "robot_writers": (["gsrmr_robot"], None, True),
    "loss_writers": (["gsrmr_server"], None, True),
    "channel_writers": (["gsrmr_sim_channel"], None, True),
    "max_speed_mps": (1.5, (0.01, 20.0), True),
    "replan_min_interval_s": (1.0, (0.0, 3600.0), True),
}


def declared(cls) -> dict[str, tuple]:
    defaults = cls().ros_values()
    return {f.name: (defaults[f.name], None if spec.min_value is None else (spec.min_value, spec.max_value),
                     spec.read_only) for f, spec in cls.specs()}


@pytest.mark.parametrize(("cls", "want"), [(ServerParameters, SERVER_DECLARED),
                                           (SchedulerParameters, SCHEDULER_DECLARED)])
def test_defaults_ranges_and_read_only_flags_are_the_declared_ones(cls, want):
    got = declared(cls)
    assert list(got) == list(want)  # the declaration order too
    for name, (default, rng, read_only) in want.items():
        assert got[name] == (default, rng, read_only), name
        assert type(got[name][0]) is type(default), name  # the ROS type: 0.0 is a double, 0 an integer
        assert cls.problem(name, default) in (None, "model_path is required (a 3DGS .ply)",
                                              "route_waypoints_m must be ≥ 3 finite (x, y) pairs [x0, y0, x1, y1, "
                                              "...] in map [m] (a route file: config/routes/*.yaml), got [0.0]")


def test_nested_link_budget_and_camera_mount_default_to_theirs():
    assert ServerParameters().link == LinkBudget() == SchedulerParameters().link
    assert ServerParameters().camera_mount == CameraMount()
    assert ServerParameters.problem("bandwidth_hz", -1.0) is None  # declared (read-only) by their own helpers


def test_live_and_read_only_parameters():
    assert ServerParameters.read_only_names() == set(SERVER_DECLARED) - LIVE_PARAMETERS
    assert {"process_delay_s", "measure_loss", "max_compose_level", "jpeg_quality", "max_backlog_slots",
            "model_path"} == LIVE_PARAMETERS
    live = set(SCHEDULER_DECLARED) - SchedulerParameters.read_only_names()
    assert live == PLANNING_PARAMETERS | {"replan_period_s", "loss_map_file"}


@pytest.mark.parametrize(("name", "value", "reason"), [
    ("jpeg_quality", 0, "jpeg_quality must be in [1, 100], got 0"),
    ("jpeg_quality", 101, "in [1, 100]"),
    ("jpeg_quality", 85.0, "jpeg_quality must be an integer"),
    ("jpeg_quality", True, "must be an integer"),
    ("process_delay_s", -0.01, "process_delay_s must be in [0.0, 5.0]"),
    ("process_delay_s", 5.5, "in [0.0, 5.0]"),
    ("process_delay_s", math.nan, "in [0.0, 5.0]"),
    ("process_delay_s", "0.1", "must be a number"),
    ("max_backlog_slots", 0, "in [1, 100000]"),
    ("measure_loss", 1, "measure_loss must be a bool"),
    ("background_rgb", [0.5, 0.5], "background_rgb must be 3 numbers in [0, 1]"),
    ("background_rgb", [0.5, 1.5, 0.0], "3 numbers in [0, 1]"),
    ("background_rgb", "grey", "must be a list of numbers"),
    ("model_path", "", "model_path is required"),
    ("render_threads", 257, "in [0, 256]"),
])
def test_server_problem_refuses_with_a_reason(name, value, reason):
    got = ServerParameters.problem(name, value)
    assert got is not None and reason in got, got


@pytest.mark.parametrize(("name", "value"), [
    ("jpeg_quality", 1), ("jpeg_quality", 100), ("process_delay_s", 0.0), ("process_delay_s", 5.0),
    ("process_delay_s", 1), ("max_backlog_slots", 100_000), ("measure_loss", False),
    ("background_rgb", [0.0, 1.0, 0.25]), ("model_path", "/tmp/scene.ply"), ("render_threads", 0),
])
def test_server_problem_accepts_valid_values(name, value):
    assert ServerParameters.problem(name, value) is None


def test_change_problem_refuses_read_only_parameters_and_passes_live_ones_to_problem():
    assert "render_threads is read-only" in ServerParameters.change_problem("render_threads", 2)
    assert "slot_s is read-only" in ServerParameters.change_problem("slot_s", 0.1)
    assert "read-only" in SchedulerParameters.change_problem("oracle_channel", True)
    assert ServerParameters.change_problem("jpeg_quality", 70) is None
    assert "in [1, 100]" in ServerParameters.change_problem("jpeg_quality", 500)
    assert SchedulerParameters.change_problem("use_sim_time", True) is None  # not ours: rclpy's


@pytest.mark.parametrize(("name", "value", "reason"), [
    ("method", "bogus", "method 'bogus' is not one of"),
    ("solver_options", "{not json", "solver_options is not JSON"),
    ("solver_options", "[1, 2]", "solver_options must be a JSON object"),
    ("loss_threshold", -0.5, "loss_threshold must be in [0.0, 1.0]"),
    ("horizon", 0, "horizon must be in [1, 100000]"),
    ("horizon", 10.0, "horizon must be an integer"),
    ("loss_margin", 0.995, "in [0.0, 0.99]"),
    ("route_waypoints_m", [0.0, 0.0, 1.0, 0.0], "route_waypoints_m must be ≥ 3 finite (x, y) pairs"),
    ("route_waypoints_m", [0.0, 0.0, 1.0, 0.0, 1.0], "≥ 3 finite"),
    ("route_waypoints_m", [0.0, 0.0, 1.0, 0.0, 1.0, math.inf], "≥ 3 finite"),
    ("replan_period_s", 0.05, "in [0.1, 3600.0]"),
])
def test_scheduler_problem_refuses_with_a_reason(name, value, reason):
    got = SchedulerParameters.problem(name, value)
    assert got is not None and reason in got, got


@pytest.mark.parametrize(("name", "value"), [
    ("method", "exact"), ("solver_options", '{"time_limit_s": 0.05}'), ("loss_threshold", 0.0),
    ("horizon", 1), ("oracle_channel", True), ("route_waypoints_m", [0.0, 0.0, 1.0, 0.0, 1.0, 1.0]),
    ("image_bits", 1e9), ("replan_period_s", 0.5),
])
def test_scheduler_problem_accepts_valid_values(name, value):
    assert SchedulerParameters.problem(name, value) is None


def test_with_values_returns_a_new_instance_with_the_change():
    before = ServerParameters()
    after = before.with_values({"jpeg_quality": 70, "process_delay_s": 0, "background_rgb": [0.0, 0.0, 0.0],
                                "use_sim_time": True})
    assert (after.jpeg_quality, after.process_delay_s, after.background_rgb) == (70, 0.0, (0.0, 0.0, 0.0))
    assert isinstance(after.process_delay_s, float)
    assert after is not before and before == ServerParameters() and before.jpeg_quality == 85
    assert after.link == before.link
    with pytest.raises(FrozenInstanceError):
        after.jpeg_quality = 50  # type: ignore[misc]
    with pytest.raises(ValueError, match=r"^parameter jpeg_quality must be in \[1, 100\]"):
        before.with_values({"jpeg_quality": 0})
    with pytest.raises(ValueError, match=r"^parameter model_path is required \(a 3DGS \.ply\)$"):
        before.with_values({"model_path": ""})


def test_scheduler_with_values_and_derived_values():
    p = SchedulerParameters().with_values({"solver_options": '{"iterations": 10}', "method": "apo",
                                           "route_waypoints_m": [0, 0, 2, 0, 2, 1]})
    assert (p.options, p.method) == ({"iterations": 10}, "apo")
    assert p.route_waypoints_m == (0.0, 0.0, 2.0, 0.0, 2.0, 1.0)
    assert p.waypoints == [(0.0, 0.0), (2.0, 0.0), (2.0, 1.0)] == route_waypoints(p.route_waypoints_m)
    assert SchedulerParameters().with_values({"loss_threshold": 0.5}).loss_threshold == 0.5
    with pytest.raises(ValueError, match="not one of"):
        p.with_values({"method": "bogus"})
    with pytest.raises(ValueError, match=r"^parameter route_waypoints_m must be ≥ 3 finite"):
        route_waypoints([0.0])


def test_planner_config_is_the_one_mapping_of_the_scheduler_parameters():
    """Each parameter lands in its PlannerConfig field; image_slot_loss −1 takes the seed map's measured image
    loss; the oracle also plans on the loss map as it is; a value the planner refuses raises ValueError."""
    seed = LossMap(image_loss=0.0067, sample_offset=0.0031)
    p = SchedulerParameters().with_values({
        "slot_s": 0.2, "loss_threshold": 0.025, "horizon": 60, "method": "ranking",
        "solver_options": '{"time_limit_s": 0.5}', "image_bits": 50_000.0, "pose_bits": 200.0, "drift_threshold": 0.03,
        "drift_window": 4, "loss_margin": 0.1, "in_slot_decision": False, "explore_image_fraction": 0.2,
        "margin_quantile": 0.5, "burst_time_constant_slots": 12.0, "probe_gap_slots": 8, "round_slots": 288,
        "stale_fix_m": 1.5})
    c = p.planner_config(seed)
    assert (c.slot_s, c.loss_threshold, c.horizon_slots, c.method, dict(c.solver_options), c.image_bits,
            c.pose_bits, c.drift_threshold, c.drift_window_samples, c.loss_margin, c.in_slot_decision,
            c.explore_image_fraction, c.margin_quantile, c.burst_time_constant_slots, c.probe_gap_slots,
            c.round_slots, c.stale_fix_m) == (0.2, 0.025, 60, "ranking", {"time_limit_s": 0.5}, 50_000.0, 200.0, 0.03,
                                              4, 0.1, False, 0.2, 0.5, 12.0, 8, 288, 1.5)
    assert c.image_slot_loss == 0.0067 and p.planner_config(LossMap()).image_slot_loss == 0.0
    assert p.with_values({"image_slot_loss": 0.01}).planner_config(seed).image_slot_loss == 0.01
    # loss_sample_offset: −1 by default, the seed map's (0 without one); 0 = samples as measured; else as given
    assert c.loss_sample_offset == 0.0031 and p.planner_config(LossMap()).loss_sample_offset == 0.0
    assert p.with_values({"loss_sample_offset": 0.0}).planner_config(seed).loss_sample_offset == 0.0
    assert p.with_values({"loss_sample_offset": -1.0}).planner_config(seed).loss_sample_offset == 0.0031
    assert p.with_values({"loss_sample_offset": -1.0}).planner_config(LossMap()).loss_sample_offset == 0.0
    assert p.with_values({"loss_sample_offset": 0.002}).planner_config(seed).loss_sample_offset == 0.002
    assert not c.oracle_channel and not c.trust_loss_map and c.startup_explore_samples == STARTUP_EXPLORE_SAMPLES
    oracle = p.with_values({"oracle_channel": True}).planner_config(seed)
    assert oracle.oracle_channel and oracle.trust_loss_map
    with pytest.raises(ValueError, match="image_bits must exceed pose_bits"):
        p.with_values({"image_bits": 100.0}).planner_config(seed)


def test_each_live_parameter_changes_only_live_planner_fields():
    """What `ros2 param set` may change maps onto what a running planner may change (OnlinePlanner.reconfigure)."""
    seed = LossMap(image_loss=0.0067)
    base = SchedulerParameters().planner_config(seed)
    changes = {"loss_threshold": 0.02, "horizon": 50, "method": "ranking", "solver_options": '{"time_limit_s": 1.0}',
               "image_bits": 60_000.0, "pose_bits": 100.0, "drift_threshold": 0.05, "drift_window": 7,
               "loss_margin": 0.2}
    assert set(changes) == PLANNING_PARAMETERS
    for name, value in changes.items():
        new = SchedulerParameters().with_values({name: value}).planner_config(seed)
        changed = {f.name for f in fields(base) if getattr(base, f.name) != getattr(new, f.name)}
        assert len(changed) == 1 and changed <= LIVE_FIELDS, (name, changed)
        assert base.live_change_problem(new) is None


def test_parameter_modules_import_no_ros_and_the_scheduler_one_no_renderer():
    code = ("import json, sys; import gsrmr_server.server_params, gsrmr_scheduler.scheduler_params; "
            "print(json.dumps(sorted(sys.modules)))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    modules = set(json.loads(result.stdout.splitlines()[-1]))
    assert "gsrmr_scheduler.scheduler_params" in modules
    assert sorted(m for m in modules if m.split(".")[0] in ("rclpy", "rcl_interfaces", "torch")) == []
    assert sorted(m for m in modules if m.startswith(("gsrmr_splat", "gsrmr_server.compose"))) == []


def test_limo_base_parameters_defaults_rules_and_read_only():
    p = LimoBaseParameters()
    assert (p.port, p.baud, p.motion_mode, p.heading_source, p.command_rate_hz) == (
        "/dev/ttyTHS1", 460800, "auto", "imu", 50.0)
    assert LimoBaseParameters.read_only_names() == {f for f in p.ros_values()} - {"motion_mode", "heading_source"}
    assert "one of" in LimoBaseParameters.change_problem("motion_mode", "tank")
    assert "one of" in LimoBaseParameters.change_problem("heading_source", "compass")
    assert "read-only" in LimoBaseParameters.change_problem("baud", 115200)
    assert "must be in" in LimoBaseParameters.problem("baud", 100)
    for mode in MOTION_MODES:
        assert LimoBaseParameters.change_problem("motion_mode", mode) is None
    q = p.with_values({"motion_mode": "diff", "max_linear_mps": 0.5})
    assert q.motion_mode == "diff" and q.limits.max_linear_mps == 0.5 and p.motion_mode == "auto"
    with pytest.raises(ValueError, match="motion_mode"):
        p.with_values({"motion_mode": "tank"})
