"""The simulated system as a list of processes: one definition for ``sim.launch.py`` and ``make demo``.

:func:`sim_stack` (one robot) and :func:`fleet_stack` (N) return every node of the closed loop as a
:class:`ProcessSpec`; launch files turn each into a ``launch_ros`` ``Node``, the demo and the tests run the same
executables with :func:`command_line`, so what is tested is what ``ros2 launch gsrmr sim.launch.py`` runs.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
import os
from pathlib import Path
import shutil
import sys
import tempfile
from typing import Any

import yaml

from gsrmr_common.link_model import LinkBudget
from gsrmr_common.link_params import LinkParameters
from gsrmr_common.pose2d import Pose2D
from gsrmr_sim.limo.mock import GROUND_TRUTH_TOPIC
from gsrmr_sim.limo.odometry_errors import OdometryErrorDraw, OdometryErrors
from gsrmr_sim.world.kinematics import start_pose
from gsrmr_sim.world.scene import load_scene

REPO_CONFIG = Path(__file__).resolve().parents[1] / "config"


def config_dir() -> Path:
    """The package's config folder: the installed share dir on a ROS install, else the source tree."""
    try:
        from ament_index_python.packages import get_package_share_directory

        share = Path(get_package_share_directory("gsrmr")) / "config"
        if share.is_dir():
            return share
    except Exception:
        pass
    return REPO_CONFIG


@dataclass
class ProcessSpec:
    """One node of the stack."""

    executable: str
    name: str
    param_files: list[str] = field(default_factory=list)
    params: dict[str, Any] = field(default_factory=dict)
    arguments: list[str] = field(default_factory=list)
    remappings: list[tuple[str, str]] = field(default_factory=list)
    ros: bool = True  # False: a plain CLI (arguments only)
    nice: int = 0  # scheduling niceness added to the process (see WORLD_NICE)
    host: str = "robot"  # the machine it runs on in a two-host deployment: "robot" or "server"
    namespace: str = ""  # ROS namespace of the node ("/robot2" in a fleet; "" = the root, as one robot runs)


# The simulated world (mock LIMO, mock camera, route follower) stands in for hardware and physics that
# do not share the server's CPU on a real deployment. On one small machine it runs at a lower CPU
# priority, so that it takes the cores the system under test leaves idle instead of delaying the
# server's slots; it still gets most of a core when the system idles.
WORLD_NICE = 10
# The scorer is bookkeeping, not the world: nothing waits for it during a round (it queues a round's slots and the
# demo waits for it afterwards), so it takes only the CPU that the system and the world leave.
SCORER_NICE = 19

# Who writes each deployment node's inputs in the simulated stack (docs/security.md, "Application checks"): the
# read-only writer lists, by node name relative to the node's namespace (so a fleet's /robot2 reads its own). The
# readers of the robot's uplink images whose acknowledgements the hold-back waits for: the server.
SIM_WRITERS: dict[str, dict[str, list[str]]] = {
    "gsrmr_robot": {"schedule_writers": ["gsrmr_scheduler"], "channel_writers": ["gsrmr_sim_channel"],
                    "camera_writers": ["gsrmr_mock_camera"], "odom_writers": ["gsrmr_limo_base"],
                    "image_readers": ["gsrmr_server"], "correction_writers": ["gsrmr_server"]},
    "gsrmr_server": {"robot_writers": ["gsrmr_robot"], "schedule_writers": ["gsrmr_scheduler"],
                     "cmd_vel_writers": ["gsrmr_route_follower"]},
    "gsrmr_scheduler": {"robot_writers": ["gsrmr_robot"], "loss_writers": ["gsrmr_server"],
                        "channel_writers": ["gsrmr_sim_channel"]},
    "gsrmr_limo_base": {"cmd_vel_writers": ["gsrmr_route_follower"]},
    # the measuring instrument: a rogue's ledger or camera_info must not bend the scores either
    "gsrmr_sim_scorer": {"robot_writers": ["gsrmr_robot"], "server_writers": ["gsrmr_server"],
                         "camera_writers": ["gsrmr_mock_camera"]},
}


def robot_jpeg_quality(robot_yaml: str) -> int:
    """The robot's JPEG quality from its parameter file (the scorer's hindsight encodes true frames alike)."""
    data = yaml.safe_load(Path(robot_yaml).read_text()) or {}
    for section in data.values():
        quality = (section or {}).get("ros__parameters", {}).get("jpeg_quality")
        if quality is not None:
            return int(quality)
    return 80


def link_budget(link_yaml: str, channel_seed: int | None = None) -> LinkBudget:
    """The uplink a ``link.yaml`` describes (the robot's, the scheduler's and the simulated radio's), with
    ``channel_seed`` overriding its fading seed (as ``gsrmr-demo --channel-seed`` does): the file's values
    go through the nodes' parameter table (:class:`~gsrmr_common.link_params.LinkParameters`: names, types,
    ranges; ValueError for a value a node would refuse), missing ones take its defaults."""
    data = yaml.safe_load(Path(link_yaml).read_text()) or {}
    params: dict[str, Any] = {}
    for section in data.values():
        params.update((section or {}).get("ros__parameters", {}))
    if channel_seed is not None:
        params["channel_seed"] = int(channel_seed)
    return LinkParameters().with_values(params).budget()


def sim_stack(*, scene: str = "sandbox", model_path: str, record_dir: str = "", loss_threshold: float = 0.03,
              link_path: str = "/tmp/gsrmr_limo", laps: int = 1, method: str = "exact",
              loss_map_file: str = "", state_dir: str = "", overrides: dict[str, dict] | None = None,
              config: Path | None = None, channel_seed: int | None = None,
              oracle_channel: bool = False, truth_dir: str = "", odometry: OdometryErrors = OdometryErrors(),
              odometry_seed: int = 0, localization: bool = True) -> list[ProcessSpec]:
    """Every process of the simulated closed loop (mock base, camera and radio, robot, server, scheduler).

    Each process says which machine it belongs to (``host``): the robot (base, camera, robot node and the
    simulated world that stands in for the robot's hardware and surroundings) or the server (server,
    scheduler, and the simulation's scorer, which scores every MR image against the truth into
    ``record_dir/scores.csv``); the mock base and the simulated radio log there too (:data:`TRUTH_LOG`,
    :data:`CHANNEL_LOG`). ``truth_dir`` routes the scorer's ground-truth frames through that folder (the
    simulation backplane, :mod:`gsrmr_sim.truth_frames`) instead of over DDS, as two hosts need.

    ``channel_seed`` overrides ``config/link.yaml``'s for the simulated radio (and the scheduler, which
    only uses it with ``oracle_channel``: planning with the simulator's future fading, an upper bound).
    ``overrides``: parameters per node name (``{"gsrmr_server": {...}}``), applied last; ValueError for a
    name that is no node of the stack. ``odometry``: what the mock base's odometry gets wrong (drawn from
    ``odometry_seed``): the robot is set down off its believed start (``map_from_odom``) by the draw's start error.
    ``localization``: the server localizes the robot and the robot takes its corrections.
    """
    cfg = config or config_dir()
    link, base, robot, server, scheduler = (
        str(cfg / n) for n in ("link.yaml", "limo_base.yaml", "robot.yaml", "server.yaml", "scheduler.yaml"))
    sc = load_scene(scene)
    a0, b0, t0 = start_pose(sc.route)  # where the robot believes it starts
    draw = OdometryErrorDraw(odometry, odometry_seed)
    ta, tb, tt = draw.true_start(Pose2D(a0, b0, t0))  # where it really does
    m = sc.camera.mount  # the simulated camera's mount: the robot's /tf_static and the server's render pose
    mount = m.as_parameters()
    over = overrides or {}
    seed = {} if channel_seed is None else {"channel_seed": int(channel_seed)}
    # what the server composes with: the scorer rebuilds its slots with the same (and the server's overrides of it)
    composition = {"mr_content": sc.mr_content, "background_rgb": [float(c) for c in sc.background], **mount,
                   "model_path": model_path}
    composition.update({k: v for k, v in over.get("gsrmr_server", {}).items() if k in composition})
    specs = [
        ProcessSpec("gsrmr-mock-limo", "gsrmr_mock_limo", ros=True,
                    arguments=["--link", link_path, f"--start-pose={ta},{tb},{tt}", "--odometry",
                               ",".join(f"{f.name}={getattr(odometry, f.name)!r}" for f in fields(odometry)),
                               f"--odometry-seed={odometry_seed}",
                               *([f"--truth-log={Path(record_dir) / TRUTH_LOG}"] if record_dir else [])],
                    nice=WORLD_NICE),
        ProcessSpec("gsrmr-limo-base", "gsrmr_limo_base", [base], {"port": link_path}),
        ProcessSpec("gsrmr-mock-camera", "gsrmr_mock_camera", [],
                    {"scene": scene, "round": 2, "clock_from_motion": True, "truth_dir": truth_dir}, nice=WORLD_NICE),
        ProcessSpec("gsrmr-route-follower", "gsrmr_route_follower", [],
                    {"scene": scene, "laps": laps, "odom_topic": GROUND_TRUTH_TOPIC}, nice=WORLD_NICE),
        ProcessSpec("gsrmr-sim-channel", "gsrmr_sim_channel", [link],
                    {**seed, **({"publish_log": str(Path(record_dir) / CHANNEL_LOG)} if record_dir else {})},
                    nice=WORLD_NICE),
        ProcessSpec("gsrmr-robot", "gsrmr_robot", [link, robot],
                    {"map_from_odom": [a0, b0, t0], "localization": "server" if localization else "off", **mount}),
        ProcessSpec("gsrmr-server", "gsrmr_server", [link, server], host="server",
                    params={**composition, "record_dir": record_dir, "localization": localization}),
        # the simulation's ground-truth scoring of the server's MR images, beside the server (scores.csv in its
        # record_dir); composes as the server does, at the lowest priority (SCORER_NICE)
        ProcessSpec("gsrmr-sim-scorer", "gsrmr_sim_scorer", [link], host="server", nice=SCORER_NICE,
                    params={**composition, "record_dir": record_dir, "truth_dir": truth_dir,
                            "hindsight_jpeg_quality": robot_jpeg_quality(robot)}),
        ProcessSpec("gsrmr-scheduler", "gsrmr_scheduler", [link, scheduler], host="server",
                    params={"route_waypoints_m": [float(v) for xy in sc.route.waypoints for v in xy],
                     "route_speed_mps": float(sc.route.speed_mps), "loss_threshold": loss_threshold, "method": method,
                     # oracle_channel also plans on the loss map as it is: the oracle's map is a survey of the
                     # scored round itself (the paper's "L_t known"), not corrected from the few images it sends
                     "loss_map_file": loss_map_file, "state_dir": state_dir, "oracle_channel": oracle_channel,
                     "round_slots": int(sc.slots), **seed}),
    ]
    for spec in specs:
        spec.params.update({k: list(v) for k, v in SIM_WRITERS.get(spec.name, {}).items()})
    unknown = sorted(set(over) - {spec.name for spec in specs})
    if unknown:
        raise ValueError(f"overrides for no node of the stack: {unknown} (keys are node names: "
                         f"{[spec.name for spec in specs]})")
    for spec in specs:
        spec.params.update(over.get(spec.name, {}))
    return specs


#: The mock base's true poses, in the record folder (``stamp_ns,x_m,y_m,yaw_rad,tick_late_ms``): the hindsight pose
#: errors, and how late the base ran (:mod:`gsrmr_sim.world_lateness`).
TRUTH_LOG = "truth_poses.csv"
#: The simulated radio's publish log, in the record folder (``slot,round_slot,slot_start_ns,published_ns``).
CHANNEL_LOG = "channel_publish.csv"

ROBOT_NAMESPACE_PREFIX = "robot"


def robot_namespace(k: int, prefix: str = ROBOT_NAMESPACE_PREFIX) -> str:
    """``/robot<k>``: the namespace of robot ``k`` (1-based) of a fleet."""
    return f"/{prefix}{k}"


def per_robot_path(path: str, robot: str) -> str:
    """``path`` for one robot of a fleet: ``{robot}`` in it replaced by the robot's name (``robot2``), else
    ``path/robot2``; ``""`` (off) stays off."""
    if not path:
        return ""
    return path.replace("{robot}", robot) if "{robot}" in path else os.path.join(path, robot)


def fleet_stack(*, robots: int, scene: str = "sandbox", model_path: str, record_dir: str = "",
                loss_threshold: float = 0.03, link_path: str = "/tmp/gsrmr_limo", laps: int = 1,
                method: str = "exact", loss_map_file: str = "", state_dir: str = "",
                overrides: dict[str, dict] | None = None, config: Path | None = None,
                channel_seed: int | None = None, oracle_channel: bool = False, truth_dir: str = "",
                prefix: str = ROBOT_NAMESPACE_PREFIX, odometry: OdometryErrors = OdometryErrors(),
                odometry_seed: int | None = None, localization: bool = True) -> list[ProcessSpec]:
    """``robots`` closed loops side by side: every process of :func:`sim_stack` once per robot, robot k
    (1-based) in namespace ``/robot<k>`` with its own server, scheduler and simulated world.

    Per robot: the mock LIMO's pty ``<link_path>_robot<k>``; ``record_dir``, ``state_dir`` and ``truth_dir``
    through :func:`per_robot_path` (``<dir>/robot<k>``, or ``{robot}`` in the path replaced); channel seed
    ``channel_seed + k - 1`` (default base: ``config/link.yaml``'s seed), so robot 1 sees the single robot's
    channel and every other robot a different one. All robots start at the route's start pose (the
    simulated robots do not collide). ``loss_map_file`` (read only) and the model are shared.
    """
    if robots < 1:
        raise ValueError("robots must be >= 1")
    cfg = config or config_dir()
    base_seed = link_budget(str(cfg / "link.yaml")).channel_seed if channel_seed is None else int(channel_seed)
    specs: list[ProcessSpec] = []
    for k in range(1, robots + 1):
        ns = robot_namespace(k, prefix)
        name = ns.strip("/")
        for spec in sim_stack(scene=scene, model_path=model_path, record_dir=per_robot_path(record_dir, name),
                              loss_threshold=loss_threshold, link_path=f"{link_path}_{name}", laps=laps,
                              method=method, loss_map_file=loss_map_file,
                              state_dir=per_robot_path(state_dir, name), overrides=overrides, config=cfg,
                              channel_seed=base_seed + k - 1, oracle_channel=oracle_channel,
                              truth_dir=per_robot_path(truth_dir, name), odometry=odometry,
                              odometry_seed=(base_seed if odometry_seed is None else odometry_seed) + k - 1,
                              localization=localization):
            spec.namespace = ns
            specs.append(spec)
    return specs


def mock_limo_link(spec: ProcessSpec) -> str | None:
    """The pty path a ``gsrmr-mock-limo`` spec creates (its ``--link`` argument), else None."""
    if spec.executable != "gsrmr-mock-limo" or "--link" not in spec.arguments:
        return None
    return spec.arguments[spec.arguments.index("--link") + 1]


def nice_prefix(spec: ProcessSpec) -> list[str]:
    """``nice -n N`` for a process with a niceness (the launch files' ``prefix``), else nothing."""
    return ["nice", "-n", str(spec.nice)] if spec.nice else []


def executable_path(name: str) -> Path:
    """Where the installed package exposes console script ``name``, found as ``ros2 run`` finds it.

    In order: ``<prefix>/lib/gsrmr/<name>`` of the ament-indexed package (``colcon build`` and a
    sourced ``install/setup.bash``, or a ROS install), the folder of the running interpreter (a venv's
    ``bin`` after ``pip install``), then ``PATH``. Raises ``FileNotFoundError`` naming every place
    looked at.
    """
    tried: list[str] = []
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_prefix

        try:
            candidate = Path(get_package_prefix("gsrmr")) / "lib" / "gsrmr" / name
            if candidate.is_file() and os.access(candidate, os.X_OK):
                return candidate
            tried.append(str(candidate))
        except (PackageNotFoundError, LookupError, OSError):  # OSError: AMENT_PREFIX_PATH not set at all
            tried.append("ament index (gsrmr not indexed: AMENT_PREFIX_PATH)")
    except ImportError:
        tried.append("ament index (ament_index_python not installed)")
    candidate = Path(sys.executable).parent / name
    if candidate.is_file() and os.access(candidate, os.X_OK):
        return candidate
    tried.append(str(candidate))
    found = shutil.which(name)
    if found:
        return Path(found)
    tried.append("PATH")
    raise FileNotFoundError(f"console script {name} not found; looked in: {', '.join(tried)}")


def command_line(spec: ProcessSpec, bin_dir: str | Path | None = None,
                 param_dir: str | Path | None = None) -> list[str]:
    """argv that runs ``spec`` as a process (overrides go through a generated parameter file).

    Every file is keyed ``/**``, as ``launch_ros`` writes a launch file's parameter dict, so the
    overrides (the last file) win over the package's config files exactly as under ``ros2 launch``.
    """
    exe = executable_path(spec.executable) if bin_dir is None else Path(bin_dir) / spec.executable
    argv = [*nice_prefix(spec), str(exe), *spec.arguments]
    if not spec.ros:
        return argv
    ros = ["--ros-args", "-r", f"__node:={spec.name}"]
    if spec.namespace:
        ros += ["-r", f"__ns:={spec.namespace}"]
    for path in spec.param_files:
        ros += ["--params-file", path]
    if spec.params:
        folder = Path(param_dir or tempfile.mkdtemp(prefix="gsrmr-params-"))
        if spec.namespace:  # one override file per node *and* namespace: robots of a fleet share node names
            folder = folder / spec.namespace.strip("/").replace("/", "_")
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / f"{spec.name}.yaml"
        path.write_text(yaml.safe_dump({"/**": {"ros__parameters": spec.params}}))
        ros += ["--params-file", str(path)]
    for src, dst in spec.remappings:
        ros += ["-r", f"{src}:={dst}"]
    return argv + ros


# Fast DDS's default shared-memory transport does not survive a peer killed with -9: the dead
# process's ports can block other participants' writes for about a second and leave a restarted
# node's endpoints unmatched (eProsima/Fast-DDS #5469, #6535; docs/reliability.md). Stacks whose
# nodes may be killed use UDP on the loopback instead (robot and server talk UDP on a real deployment
# anyway). The demo keeps the default: on one machine shared memory costs less CPU per camera frame
# (≥ 287 of 288 slots on time in 10 of 10 demo runs with it; 281–288 with UDP). An explicit
# FASTDDS_BUILTIN_TRANSPORTS in the caller's environment wins.
KILL_SAFE_TRANSPORT = {"FASTDDS_BUILTIN_TRANSPORTS": "UDPv4"}


def environment(domain_id: int | None = None, base: dict[str, str] | None = None, *,
                kill_safe: bool = False) -> dict[str, str]:
    """Process environment (a copy of ``base``, default ``os.environ``): localhost-only discovery,
    unbuffered output, the given ROS domain and, with ``kill_safe``, the kill-safe Fast DDS transport."""
    env = dict(os.environ if base is None else base)
    if domain_id is not None:
        env["ROS_DOMAIN_ID"] = str(domain_id)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    if kill_safe:
        for key, value in KILL_SAFE_TRANSPORT.items():
            env.setdefault(key, value)
    env["PYTHONUNBUFFERED"] = "1"
    return env
