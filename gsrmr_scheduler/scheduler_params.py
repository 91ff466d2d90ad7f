"""The scheduler node's parameters (:class:`SchedulerParameters`): names, defaults, descriptions, ranges and the rules a
change must meet (pure, no ROS); :meth:`SchedulerParameters.planner_config` maps them onto the planner's.

How the node applies a change: docs/nodes.md, "The scheduler"; which are live, and only with
``live_parameter_changes``: docs/security.md, "Services, parameters, readers".
"""

from __future__ import annotations

from dataclasses import dataclass, field
import json
import math
from pathlib import Path
from typing import Any

from gsrmr_common.link_model import IMAGE_BITS, KEY_BITS, SLOT_S, LinkBudget
from gsrmr_common.link_params import LinkParameters
from gsrmr_common.node_help import Endpoint, NodeInterface, ParameterGroup
from gsrmr_common.node_params import NodeParameters, ros_parameter
from gsrmr_common.writer_admission import writer_list_problem
from gsrmr_scheduler.loss_map import LossMap
from gsrmr_scheduler.planner import PlannerConfig
from gsrmr_scheduler.solve import METHODS

# Live parameters the plan depends on: a change builds a new planner configuration (planner_config) and requests
# a replan.
PLANNING_PARAMETERS = frozenset({"loss_threshold", "horizon", "method", "solver_options", "image_bits", "pose_bits",
                                 "drift_threshold", "drift_window", "loss_margin"})
# In-slot rule: images in the better half of the fades until the L_t model holds this many measurements (the seed
# map may be far off a round with changes)
STARTUP_EXPLORE_SAMPLES = 3
#: The read-only lists of node names allowed to write the scheduler's input topics (relative: in its namespace).
WRITER_LISTS = ("robot_writers", "loss_writers", "channel_writers")


def route_waypoints(flat: list[float] | tuple[float, ...]) -> list[tuple[float, float]]:
    """``[x0, y0, x1, y1, ...]`` (map, metres) → waypoints; a clear error for an unusable route."""
    reason = route_problem(flat)
    if reason:
        raise ValueError(f"parameter {reason}")
    return [(float(flat[i]), float(flat[i + 1])) for i in range(0, len(flat), 2)]


def route_problem(flat: list[float] | tuple[float, ...]) -> str | None:
    """Why ``flat`` is no usable route (≥ 3 finite (x, y) pairs), or None."""
    if len(flat) < 6 or len(flat) % 2 or not all(math.isfinite(v) for v in flat):
        return ("route_waypoints_m must be ≥ 3 finite (x, y) pairs [x0, y0, x1, y1, ...] in map [m] (a route "
                f"file: config/routes/*.yaml), got {list(flat)}")
    return None


def solver_options_problem(text: str) -> str | None:
    """Why ``text`` is not a JSON object of solver options, or None."""
    try:
        value = json.loads(text)
    except json.JSONDecodeError as err:
        return f"solver_options is not JSON: {err}"
    return None if isinstance(value, dict) else "solver_options must be a JSON object"


@dataclass(frozen=True)
class SchedulerParameters(NodeParameters):
    """Every parameter of the scheduler node (ROS names; units in the names)."""

    slot_s: float = ros_parameter(SLOT_S, "Slot length τ [s]", min_value=0.01, max_value=10.0, read_only=True)
    loss_threshold: float = ros_parameter(0.03, "Average MR-loss budget L_th", min_value=0.0, max_value=1.0)
    horizon: int = ros_parameter(100, "Slots per plan", min_value=1, max_value=100_000)
    method: str = ros_parameter("exact", f"Scheduling method, one of {', '.join(METHODS)}",
                                constraints=f"one of {list(METHODS)}")
    solver_options: str = ros_parameter("{}", "JSON object of options passed to the solver (e.g. "
                                        "{\"time_limit_s\": 0.05} or {\"iterations\": 10})")
    image_bits: float = ros_parameter(IMAGE_BITS, "Image size I assumed by the plan [bit]", min_value=1.0,
                                      max_value=1e9)
    pose_bits: float = ros_parameter(KEY_BITS, "Pose-key size S [bit]", min_value=1.0, max_value=1e6)
    replan_period_s: float = ros_parameter(2.0, "Replan this often [s]", min_value=0.1, max_value=3600.0)
    replan_on_loss_sample: bool = ros_parameter(
        True, "The periodic replan waits for the next loss sample (a whole period at most) and runs right after it, "
        "as does a drift replan: the plan holds the newest measurement (false: at the timer's phase of the slot)",
        read_only=True)
    drift_threshold: float = ros_parameter(0.02, "Replan when the mean |measured − predicted| loss over "
                                           "drift_window samples exceeds this", min_value=0.0, max_value=1.0)
    drift_window: int = ros_parameter(3, "Samples in the drift test", min_value=1, max_value=1000)
    loss_margin: float = ros_parameter(0.01, "Plan for loss_threshold·(1 − loss_margin): a fixed back-off on top "
                                       "of the learned margin (margin_quantile); 0.01 covers the key slots' "
                                       "estimated loss running low (docs/scheduling.md)", min_value=0.0,
                                       max_value=0.99)
    route_waypoints_m: tuple[float, ...] = ros_parameter(
        (0.0,), "The robot's route loop, predicted along: [x0, y0, x1, y1, ...] in map [m], ≥ 3 points "
        "(config/routes/*.yaml)", read_only=True)
    route_speed_mps: float = ros_parameter(0.3, "Nominal speed along the route [m/s]", min_value=1e-3,
                                           max_value=10.0, read_only=True)
    loss_map_file: str = ros_parameter(
        "", "Seed loss map (JSON: gsrmr-survey, or a previous run); a new one set at run time (after a model swap) "
        "re-seeds the loss forecast and replans")
    loss_prior: float = ros_parameter(0.05, "Predicted loss where the map knows nothing", min_value=0.0,
                                      max_value=1.0, read_only=True)
    state_dir: str = ros_parameter("", "Save/restore the last schedule and loss map here", read_only=True)
    in_slot_decision: bool = ros_parameter(
        True, "Add per-slot gain thresholds to the schedule: the robot sends an image only if the gain it "
        "measures in the slot reaches it (a price on the loss budget; off with oracle_channel)", read_only=True)
    explore_image_fraction: float = ros_parameter(
        0.1, "In-slot rule: send an image at least when the slot's fade is in this best fraction (cheap images "
        "that keep measuring L_t)", min_value=0.0, max_value=1.0, read_only=True)
    oracle_channel: bool = ros_parameter(
        False, "Plan with the simulator's future channel realisation (learnt from radio/channel_gain) and on the "
        "loss map as it is (loss_map_file: a survey of the scored round; no burst correction, no learned margin); "
        "simulation only, an upper bound — a deployment plans with the channel's statistics",
        read_only=True)
    image_slot_loss: float = ros_parameter(
        -1.0, "MR loss an image slot leaves (its JPEG); −1 = the seed loss map's image_loss (measured on the "
        "mapping round), 0 without one", min_value=-1.0, max_value=1.0, read_only=True)
    loss_sample_offset: float = ros_parameter(
        -1.0, "Subtracted from every loss sample before the planner uses it: what the server's samples (its render "
        "against the decoded JPEG) read above the loss against the camera's frame that loss_threshold bounds; "
        "−1 = the seed loss map's sample_offset (measured by its survey; 0 without one); 0 = samples as measured "
        "(their JPEG bias then acts as a reserve: docs/scheduling.md)", min_value=-1.0, max_value=1.0,
        read_only=True)
    half_level_extra_loss: float = ros_parameter(
        0.003, "Extra MR loss of a key slot the server composed at its half level (its render at half size; the "
        "level comes on mr/slot_info): charged in the loss budget, and the recent mean added to the forecast of "
        "key slots (bench/perf/compose_levels.py measures it)", min_value=0.0, max_value=1.0, read_only=True)
    quarter_level_extra_loss: float = ros_parameter(
        0.020, "The same for the quarter level (its render at a quarter of the width and height)", min_value=0.0,
        max_value=1.0, read_only=True)
    margin_quantile: float = ros_parameter(
        0.6, "Learned margin: predictions × this quantile of measured / predicted L over the last 30 image "
        "slots (0 = off)", min_value=0.0, max_value=1.0, read_only=True)
    burst_time_constant_slots: float = ros_parameter(
        25.0, "How fast a measured burst of L fades into the run's average in the prediction [slots]",
        min_value=0.1, max_value=1e6, read_only=True)
    probe_gap_slots: int = ros_parameter(
        20, "In-slot rule: after this many slots without an image any fade at or above the median one sends an "
        "image (0 = off)", min_value=0, max_value=100_000, read_only=True)
    stale_fix_m: float = ros_parameter(
        2.0, "In-slot rule: once the robot's keys drove this far since the newest map → odom correction their ledger "
        "rows name (and half as far since an image), take ever poorer fades, up to the median one, so that the "
        "server can fix the robot's pose from an image [m]; 0 = never", min_value=0.0, max_value=100.0,
        read_only=True)
    round_slots: int = ros_parameter(
        0, "Slots of an operating round (T) whose mean loss must meet L_th: the round starts when the reported "
        "pose first moves (0 = no rounds: a running mean)", min_value=0, max_value=10_000_000, read_only=True)
    live_parameter_changes: bool = ros_parameter(
        False, "Allow the live parameters to change while the node runs (any participant may call the parameter "
        "service without SROS2; every change is logged)", read_only=True)
    robot_writers: tuple[str, ...] = ros_parameter(
        ("gsrmr_robot",), "Nodes whose uplink/pose_key and gsrmr/ledger are taken: the robot (and a relay between; "
        "relative names resolve in the scheduler's namespace)", read_only=True)
    loss_writers: tuple[str, ...] = ros_parameter(("gsrmr_server",), "Nodes whose gsrmr/loss_sample and "
                                                  "mr/slot_info are taken", read_only=True)
    channel_writers: tuple[str, ...] = ros_parameter(
        ("gsrmr_sim_channel",), "Nodes whose radio/channel_gain the oracle reads (oracle_channel only)", read_only=True)
    max_speed_mps: float = ros_parameter(
        1.5, "The robot's top speed: pose keys moving faster are refused (a relocalisation is accepted after 5 keys "
        "that agree with each other); the LIMO clamps each axis to 1 m/s, √2 diagonally in mecanum mode [m/s]",
        min_value=0.01, max_value=20.0, read_only=True)
    replan_min_interval_s: float = ros_parameter(
        1.0, "gsrmr/replan answers at most one call per this interval; calls in between are refused and counted [s]",
        min_value=0.0, max_value=3600.0, read_only=True)
    # Declared read-only by gsrmr_common.ros_node.declare_link_budget (config/link.yaml).
    link: LinkBudget = field(default_factory=LinkBudget)

    @classmethod
    def rule(cls, name: str, value: Any) -> str | None:
        """``method`` from its list, ``solver_options`` a JSON object, the route usable, a writer list names nodes."""
        if name == "method" and value not in METHODS:
            return f"method {value!r} is not one of {list(METHODS)}"
        if name == "solver_options":
            return solver_options_problem(value)
        if name == "route_waypoints_m":
            return route_problem(value)
        if name in WRITER_LISTS:
            return writer_list_problem(name, value)
        return None

    @property
    def options(self) -> dict[str, Any]:
        """``solver_options`` parsed: keyword arguments of the solver."""
        return json.loads(self.solver_options)

    @property
    def waypoints(self) -> list[tuple[float, float]]:
        """``route_waypoints_m`` as (x, y) pairs in map [m]."""
        return route_waypoints(self.route_waypoints_m)

    def live_change_problem(self, values: dict[str, Any], loss_map: LossMap) -> tuple[str | None, LossMap | None]:
        """Beyond :meth:`change_problem`: why the planner's configuration refuses ``values`` together (image_bits ≤
        pose_bits …), or a ``loss_map_file`` that is no loss map (read here, so that a bad file is refused, not
        applied). Returns the reason (None: accepted) and the new loss map, when one is named."""
        if PLANNING_PARAMETERS & values.keys():
            try:
                self.with_values(values).planner_config(loss_map)
            except ValueError as err:
                return str(err), None
        if "loss_map_file" not in values:
            return None, None
        try:
            return None, LossMap.load(Path(str(values["loss_map_file"])))
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as err:
            return (f"loss_map_file {values['loss_map_file']!r} is no loss map: {type(err).__name__}: {err}"), None

    def planner_config(self, loss_map: LossMap) -> PlannerConfig:
        """The planner's configuration: the one place that maps these parameters onto
        :class:`~gsrmr_scheduler.planner.PlannerConfig`'s fields. ``image_slot_loss`` −1 takes the seed ``loss_map``'s
        measured ``image_loss`` (0 without one), ``loss_sample_offset`` −1 its ``sample_offset`` (0 without one);
        ``oracle_channel`` also plans on the loss map as it is
        (``trust_loss_map``: the oracle's map is a survey of the scored round). Raises ValueError for values the
        planner refuses (e.g. ``image_bits`` ≤ ``pose_bits``)."""
        return PlannerConfig(
            loss_threshold=self.loss_threshold, horizon_slots=self.horizon, slot_s=self.slot_s,
            image_bits=self.image_bits, pose_bits=self.pose_bits, method=self.method, solver_options=self.options,
            drift_threshold=self.drift_threshold, drift_window_samples=self.drift_window, loss_margin=self.loss_margin,
            oracle_channel=self.oracle_channel, trust_loss_map=self.oracle_channel,
            in_slot_decision=self.in_slot_decision, explore_image_fraction=self.explore_image_fraction,
            startup_explore_samples=STARTUP_EXPLORE_SAMPLES, probe_gap_slots=self.probe_gap_slots,
            stale_fix_m=self.stale_fix_m,
            image_slot_loss=(self.image_slot_loss if self.image_slot_loss >= 0 else loss_map.image_loss or 0.0),
            loss_sample_offset=(self.loss_sample_offset if self.loss_sample_offset != -1.0
                                else loss_map.sample_offset or 0.0),
            burst_time_constant_slots=self.burst_time_constant_slots, margin_quantile=self.margin_quantile,
            round_slots=self.round_slots, half_level_extra_loss=self.half_level_extra_loss,
            quarter_level_extra_loss=self.quarter_level_extra_loss)


#: What ``gsrmr-scheduler --help`` prints.
INTERFACE = NodeInterface(
    executable="gsrmr-scheduler", node="gsrmr_scheduler",
    summary="The online scheduler: solves P_GS over a receding horizon (image or key x_t, transmit power p_t per "
            "slot) to minimise uplink energy under the average MR-loss budget, and publishes the schedule.",
    subscribes=(Endpoint("uplink/pose_key", "geometry_msgs/msg/Vector3Stamped"),
                Endpoint("gsrmr/loss_sample", "std_msgs/msg/Float64MultiArray"),
                Endpoint("gsrmr/ledger", "std_msgs/msg/Float64MultiArray"),
                Endpoint("mr/slot_info", "std_msgs/msg/Float64MultiArray"),
                Endpoint("radio/channel_gain", "std_msgs/msg/Float64MultiArray", "only with oracle_channel")),
    publishes=(Endpoint("gsrmr/schedule", "std_msgs/msg/Float64MultiArray", "latched"),
               Endpoint("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")),
    services=(Endpoint("gsrmr/replan", "std_srvs/srv/Trigger", "replan now; says what changed"),),
    parameters=(ParameterGroup(SchedulerParameters), ParameterGroup(LinkParameters)))
