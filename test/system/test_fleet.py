"""A fleet (issue 17): N robots in namespaces /robot1 … /robotN, each with its own server, scheduler and world.

Pure tests of the process list (gsrmr_sim.sim_stack.fleet_stack) and of fleet.launch.py as ``ros2 launch``
parses it; one short live fleet of two robots (``ros``, ``slow``): each robot's MR stream in its own namespace,
nothing on the root namespace's topics, distinct channels, CPU counted per robot, nothing left behind.
"""

from __future__ import annotations

import ast
import os
from pathlib import Path
import shutil
import subprocess
import sys
import threading
import time

from conftest import next_domain_id
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import Image
from support.stack_harness import HEIGHT, WIDTH, make_point_model
import yaml

from gsrmr_sim.cpu_usage import CpuMeter, CpuSnapshot, cpu_group, cpu_seconds_by_group
from gsrmr_sim.fleet import run_fleet
from gsrmr_sim.limo.mock import GROUND_TRUTH_TOPIC
from gsrmr_sim.limo.mock_ros import GroundTruthPublisher
from gsrmr_sim.round_start import RADIO_GRACE_SLOTS, radio_round_row
from gsrmr_sim.scores import read_scores
from gsrmr_sim.sim_stack import (
    command_line,
    fleet_stack,
    link_budget,
    mock_limo_link,
    per_robot_path,
    sim_stack,
)
from gsrmr_sim.stack_runner import process_name, robot_runs
from gsrmr_sim.world.camera_node import MockCameraParameters
from gsrmr_sim.world.channel_node import SimChannelParameters

REPO = Path(__file__).resolve().parents[2]
FLEET_LAUNCH = REPO / "launch" / "fleet.launch.py"
NODES = ("gsrmr_mock_limo", "gsrmr_limo_base", "gsrmr_mock_camera", "gsrmr_route_follower", "gsrmr_sim_channel",
         "gsrmr_robot", "gsrmr_server", "gsrmr_sim_scorer", "gsrmr_scheduler")


def _fleet(robots: int = 3, **kw):
    return fleet_stack(robots=robots, model_path="/m.ply", config=REPO / "config", **kw)


def _by_robot(specs) -> dict[str, dict[str, object]]:
    out: dict[str, dict[str, object]] = {}
    for s in specs:
        out.setdefault(s.namespace, {})[s.name] = s
    return out


def test_fleet_stack_is_the_single_stack_once_per_namespace():
    specs = _fleet(3, record_dir="/rec")
    robots = _by_robot(specs)
    assert list(robots) == ["/robot1", "/robot2", "/robot3"]
    single = sim_stack(model_path="/m.ply", config=REPO / "config")
    for nodes in robots.values():
        assert tuple(nodes) == NODES == tuple(s.name for s in single)
        assert [s.executable for s in nodes.values()] == [s.executable for s in single]
        assert [s.host for s in nodes.values()] == [s.host for s in single]
    assert all(s.namespace for s in specs), "a node of the fleet in the root namespace"
    assert len({(s.namespace, s.name) for s in specs}) == len(specs) == 3 * len(NODES)


def test_fleet_robots_have_their_own_pty_recording_state_truth_and_channel():
    specs = _fleet(3, record_dir="/rec", state_dir="/out/{robot}/scheduler_state", truth_dir="/out/{robot}/truth",
                   link_path="/tmp/limo")
    robots = _by_robot(specs)
    links = [mock_limo_link(n["gsrmr_mock_limo"]) for n in robots.values()]
    assert links == ["/tmp/limo_robot1", "/tmp/limo_robot2", "/tmp/limo_robot3"]
    assert [n["gsrmr_limo_base"].params["port"] for n in robots.values()] == links  # each driver opens its own pty
    assert [n["gsrmr_server"].params["record_dir"] for n in robots.values()] == \
        ["/rec/robot1", "/rec/robot2", "/rec/robot3"]
    assert [n["gsrmr_scheduler"].params["state_dir"] for n in robots.values()] == \
        [f"/out/robot{k}/scheduler_state" for k in (1, 2, 3)]
    assert [n["gsrmr_mock_camera"].params["truth_dir"] for n in robots.values()] == \
        [n["gsrmr_sim_scorer"].params["truth_dir"] for n in robots.values()] == \
        [f"/out/robot{k}/truth" for k in (1, 2, 3)]
    assert [n["gsrmr_sim_scorer"].params["record_dir"] for n in robots.values()] == \
        ["/rec/robot1", "/rec/robot2", "/rec/robot3"]  # scores.csv beside each robot's slots.csv
    base = link_budget(str(REPO / "config" / "link.yaml")).channel_seed
    seeds = [n["gsrmr_sim_channel"].params["channel_seed"] for n in robots.values()]
    assert seeds == [base, base + 1, base + 2]  # robot 1 sees the single robot's channel
    assert seeds == [n["gsrmr_scheduler"].params["channel_seed"] for n in robots.values()]
    explicit = _by_robot(_fleet(2, channel_seed=20))
    assert [n["gsrmr_sim_channel"].params["channel_seed"] for n in explicit.values()] == [20, 21]
    # off stays off
    assert {n["gsrmr_server"].params["record_dir"] for n in _by_robot(_fleet(2)).values()} == {""}


def test_ground_truth_topic_is_relative_and_wired_from_its_one_definition(monkeypatch):
    """The mock LIMO publishes its true pose on GROUND_TRUTH_TOPIC (gsrmr_sim.limo.mock), relative so that each
    robot of a fleet has its own; the stacks point the route follower at it, and the simulated camera's and
    radio's ``odom_topic`` default to it."""
    assert not GROUND_TRUTH_TOPIC.startswith("/")
    stacks = [*sim_stack(model_path="/m.ply", config=REPO / "config"), *_fleet(2)]
    for spec in stacks:
        for key, value in spec.params.items():
            if key.endswith("_topic"):
                assert not str(value).startswith("/"), (spec.name, key, value)
    assert {s.params["odom_topic"] for s in stacks if s.executable == "gsrmr-route-follower"} == {GROUND_TRUTH_TOPIC}
    # the subscribers' defaults, in the parameter dataclasses the nodes declare
    assert MockCameraParameters().odom_topic == SimChannelParameters().odom_topic == GROUND_TRUTH_TOPIC
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=next_domain_id())
    try:
        mock = type("Mock", (), {"rate_hz": 50.0, "link_path": "/tmp/no_limo"})()
        node = GroundTruthPublisher(mock, context=context, namespace="/robot2")  # the publisher, as a fleet runs it
        try:
            assert node._pub.topic_name == f"/robot2/{GROUND_TRUTH_TOPIC}"
        finally:
            node.destroy_node()
    finally:
        rclpy.shutdown(context=context)


def test_command_line_puts_each_robot_in_its_namespace(tmp_path):
    specs = _fleet(2, record_dir="/rec")
    argvs = {(s.namespace, s.name): command_line(s, tmp_path, tmp_path / "params") for s in specs}
    server2 = argvs[("/robot2", "gsrmr_server")]
    ros = server2[server2.index("--ros-args"):]
    assert ros[:5] == ["--ros-args", "-r", "__node:=gsrmr_server", "-r", "__ns:=/robot2"]
    for (ns, _name), argv in argvs.items():
        assert f"__ns:={ns}" in argv
    # the override files of the two servers are two files, each with its robot's values
    files = {ns: argv[len(argv) - 1 - argv[::-1].index("--params-file") + 1]
             for (ns, name), argv in argvs.items() if name == "gsrmr_server"}
    assert len(set(files.values())) == 2
    for ns, path in files.items():
        params = yaml.safe_load(Path(path).read_text())["/**"]["ros__parameters"]
        assert params["record_dir"] == f"/rec{ns}"
    # the single robot: no namespace, the command line as before (no __ns, override file directly in params/)
    single = next(s for s in sim_stack(model_path="/m.ply", config=REPO / "config") if s.name == "gsrmr_server")
    argv = command_line(single, tmp_path, tmp_path / "params")
    assert not any(a.startswith("__ns:=") for a in argv)
    assert argv[-1] == str(tmp_path / "params" / "gsrmr_server.yaml")


def test_per_robot_path_and_cpu_groups():
    assert per_robot_path("", "robot2") == ""
    assert per_robot_path("/a", "robot2") == "/a/robot2"
    assert per_robot_path("/a/{robot}/rec", "robot2") == "/a/robot2/rec"
    groups = {s.name: cpu_group(s) for s in _fleet(1)}
    assert groups == {"gsrmr_mock_limo": "world", "gsrmr_limo_base": "robot", "gsrmr_mock_camera": "world",
                      "gsrmr_route_follower": "world", "gsrmr_sim_channel": "world", "gsrmr_robot": "robot",
                      "gsrmr_server": "server", "gsrmr_sim_scorer": "world", "gsrmr_scheduler": "server"}
    with pytest.raises(ValueError):
        _fleet(0)


def test_round_start_from_the_radio_log_when_the_server_saw_neither_round_slot_nor_motion():
    rows = [{"slot": 1000 + i} for i in range(50)]
    log = "[INFO] [1.0] [robot2.gsrmr_sim_channel]: robot moving: round clock of the channel starts at slot 1012\n"
    assert radio_round_row(rows, log) == 12
    assert radio_round_row(rows, "") is None  # the radio has not started its round
    assert radio_round_row(rows[:12 + RADIO_GRACE_SLOTS - 1], log) is None  # too early to give up on slots.csv


def test_runner_finds_each_robot_in_the_process_list():
    """The stack runner takes everything per robot from the specs: recording (its server's), seed (its radio's)."""
    (single,) = robot_runs(sim_stack(model_path="/m.ply", config=REPO / "config", record_dir="/out/recording",
                                     channel_seed=3)).values()
    assert (single.name, single.namespace, single.label) == ("", "", "the robot")
    assert (single.record_dir, single.report_dir, single.channel_seed) == (Path("/out/recording"), Path("/out"), 3)
    assert single.processes["gsrmr-sim-scorer"] == "gsrmr_sim_scorer"
    runs = robot_runs(_fleet(3, record_dir="/out/{robot}/recording", channel_seed=20))
    assert list(runs) == ["robot1", "robot2", "robot3"]
    assert [r.report_dir for r in runs.values()] == [Path(f"/out/robot{k}") for k in (1, 2, 3)]
    assert [r.channel_seed for r in runs.values()] == [20, 21, 22]
    assert runs["robot2"].processes["gsrmr-sim-channel"] == "robot2/gsrmr_sim_channel"
    assert {process_name(s) for s in _fleet(2)} == {f"robot{k}/{n}" for k in (1, 2) for n in NODES}
    with pytest.raises(ValueError, match="records nowhere"):
        robot_runs(_fleet(2))  # no record_dir: the round's slots.csv is nowhere to follow


def test_a_robot_sets_off_only_once_its_scheduler_has_planned(tmp_path):
    """The runner waits for each scheduler's first plan (schedule.json in its state_dir) before the round starts;
    a scheduler without a state_dir gives no such sign (then only the server's composing counts)."""
    (run,) = robot_runs(sim_stack(model_path="/m.ply", config=REPO / "config", record_dir=str(tmp_path / "rec"),
                                  state_dir=str(tmp_path / "state"))).values()
    assert run.scheduler_state == tmp_path / "state" and not run.planned
    (tmp_path / "state").mkdir()
    (tmp_path / "state" / "schedule.json").write_text("{}")
    assert run.planned
    (stateless,) = robot_runs(sim_stack(model_path="/m.ply", config=REPO / "config",
                                        record_dir="/out/recording")).values()
    assert stateless.scheduler_state is None and stateless.planned
    fleet = robot_runs(_fleet(2, record_dir="/out/{robot}/recording", state_dir="/out/{robot}/state"))
    assert [r.scheduler_state for r in fleet.values()] == [Path(f"/out/robot{k}/state") for k in (1, 2)]


def test_cpu_meter_counts_from_the_last_snapshot_before_the_round_to_the_last_one():
    meter = CpuMeter([11, 12])
    meter.snapshots += [CpuSnapshot(100.0, {11: 1.0, 12: 2.0}, 50.0), CpuSnapshot(101.0, {11: 1.5, 12: 2.0}, 51.0),
                        CpuSnapshot(105.0, {11: 3.5, 12: 4.0}, 58.0)]
    usage = meter.round_usage(round_start_s=102.0)  # from the snapshot at 101 s to the one at 105 s
    assert usage.window_s == 4.0 and usage.by_group_s == {11: 2.0, 12: 2.0}
    assert usage.machine_busy_cores == pytest.approx(7.0 / 4.0)
    assert usage.other_cores == pytest.approx(7.0 / 4.0 - 4.0 / 4.0)
    assert meter.round_usage(round_start_s=50.0).window_s == 5.0  # before every snapshot: from the first
    with pytest.raises(ValueError):
        CpuMeter([11]).round_usage(0.0)
    snap = CpuMeter([]).take()
    assert snap.by_group_s == {} and snap.machine_busy_s > 0


def test_cpu_seconds_by_group_counts_a_busy_process():
    proc = subprocess.Popen([sys.executable, "-c", "import time\nt = time.process_time()\n"
                             "while time.process_time() - t < 0.6: pass\ntime.sleep(30)"], process_group=0)
    try:
        deadline = time.monotonic() + 20
        used = 0.0
        while time.monotonic() < deadline and used < 0.6:
            time.sleep(0.1)
            used = cpu_seconds_by_group().get(proc.pid, 0.0)
        assert 0.6 <= used < 3.0, used
    finally:
        proc.kill()
        proc.wait()


def _launch_nodes(robots: int, **args: str):
    """fleet.launch.py's nodes as ``ros2 launch`` builds them: the file loaded by launch's Python loader, its
    declared defaults and the given arguments in a launch context, its OpaqueFunction run."""
    pytest.importorskip("launch_ros")
    from launch import LaunchContext
    from launch.actions import DeclareLaunchArgument, OpaqueFunction
    from launch.launch_description_sources import get_launch_description_from_python_launch_file

    description = get_launch_description_from_python_launch_file(str(FLEET_LAUNCH))
    context = LaunchContext()
    for entity in description.entities:
        if isinstance(entity, DeclareLaunchArgument) and entity.default_value is not None:
            entity.visit(context)
    context.launch_configurations.update({"robots": str(robots), "model_path": "/m.ply", **args})
    (opaque,) = [e for e in description.entities if isinstance(e, OpaqueFunction)]
    nodes = opaque.execute(context)
    for node in nodes:
        node._perform_substitutions(context)  # what launch does before it runs a Node: name and namespace
    return nodes


def test_fleet_launch_file_declares_the_sim_arguments_and_robots():
    tree = ast.parse(FLEET_LAUNCH.read_text())
    declared = {n.args[0].value for n in ast.walk(tree) if isinstance(n, ast.Call)
                and getattr(n.func, "id", "") == "DeclareLaunchArgument"}
    sim = ast.parse((REPO / "launch" / "sim.launch.py").read_text())
    sim_args = {n.args[0].value for n in ast.walk(sim) if isinstance(n, ast.Call)
                and getattr(n.func, "id", "") == "DeclareLaunchArgument"}
    # the namespaces are the fleet's own; keystore is not offered: config/security/policy.xml grants nodes in "/",
    # a fleet in /robot<k> needs a policy with a profile per robot (docs/security.md, the "Namespaces" item)
    assert sim_args - {"namespace", "keystore"} <= declared
    assert "keystore" not in declared
    assert {"robots", "channel_seed"} <= declared


@pytest.mark.parametrize("robots", [1, 3])
def test_fleet_launch_file_runs_every_robot_in_its_namespace(robots):
    from support.setup_scripts import console_scripts

    nodes = _launch_nodes(robots, record_dir="/rec")
    assert len(nodes) == robots * len(NODES)
    names = [n.node_name for n in nodes]
    assert len(set(names)) == len(names)
    assert sorted(names) == sorted(f"/robot{k}/{name}" for k in range(1, robots + 1) for name in NODES)
    assert {n.expanded_node_namespace for n in nodes} == {f"/robot{k}" for k in range(1, robots + 1)}
    assert {n.node_package for n in nodes} == {"gsrmr"}
    assert {n.node_executable for n in nodes} <= console_scripts()


def test_ros2_launch_shows_the_fleet_arguments():
    """``ros2 launch <fleet.launch.py> --show-args``, as test_ros2_launch_cli checks the installed files."""
    if shutil.which("ros2") is None and not (Path(sys.executable).parent / "ros2").exists():
        pytest.skip("the ros2 command is not installed")
    pytest.importorskip("launch_ros")
    ros2 = shutil.which("ros2") or str(Path(sys.executable).parent / "ros2")
    shown = subprocess.run([ros2, "launch", str(FLEET_LAUNCH), "--show-args"], capture_output=True, text=True,
                           timeout=60)
    assert shown.returncode == 0, shown.stderr
    for arg in ("robots", "model_path", "scene", "record_dir", "loss_threshold", "method", "laps", "serial_link",
                "channel_seed"):
        assert f"'{arg}'" in shown.stdout, (arg, shown.stdout)


# ------------------------------------------------------------------------------------------------ live


class _Probe:
    """Counts MR images per robot namespace (and on the root namespace's topic, which must stay silent)."""

    def __init__(self, domain: int, robots: int) -> None:
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.node = rclpy.create_node("fleet_probe", context=self.context)
        self.count = {f"/robot{k}/mr/image": 0 for k in range(1, robots + 1)} | {"/mr/image": 0}
        for topic in self.count:
            self.node.create_subscription(Image, topic, lambda _m, t=topic: self._on(t), 20)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def _on(self, topic: str) -> None:
        self.count[topic] += 1

    def spin_while(self, alive) -> None:
        while alive():
            self.executor.spin_once(timeout_sec=0.1)

    def close(self) -> None:
        self.executor.remove_node(self.node)
        self.node.destroy_node()
        self.context.try_shutdown()


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.long  # 18 processes on the two cores: on a slow day it overloads the machine (`make test-long`)
def test_live_fleet_of_two_robots(tmp_path, monkeypatch):
    domain = next_domain_id()
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    model = make_point_model(tmp_path, n=2000)
    box: dict = {}
    slots = 60

    def run() -> None:
        try:
            box["runs"] = run_fleet(
                robots=2, scene="sandbox", model_path=model, loss_map="", run_dir=tmp_path / "fleet",
                loss_threshold=0.03, slots=slots, method="exact", timeout_s=60.0, domain_id=domain,
                overrides={"gsrmr_mock_camera": {"width": WIDTH, "height": HEIGHT},
                           "gsrmr_scheduler": {"horizon": 60, "replan_period_s": 1.0}})
        except BaseException as e:  # reported by the test thread
            box["error"] = e

    thread = threading.Thread(target=run, daemon=True)
    t0 = time.monotonic()
    thread.start()
    probe = _Probe(domain, 2)
    try:
        probe.spin_while(lambda: thread.is_alive() and time.monotonic() - t0 < 150)
    finally:
        probe.close()
    thread.join(60)
    assert not thread.is_alive(), "the fleet did not stop"
    if "error" in box:
        raise box["error"]
    runs = box["runs"]
    print(f"fleet of 2: {time.monotonic() - t0:.0f} s; MR images {probe.count}; "
          f"CPU {[r.cpu.get('server_cores') for r in runs]} server cores", flush=True)
    assert [r.namespace for r in runs] == ["/robot1", "/robot2"]
    assert [len(r.rows) for r in runs] == [slots, slots]
    assert probe.count["/robot1/mr/image"] >= slots and probe.count["/robot2/mr/image"] >= slots, probe.count
    assert probe.count["/mr/image"] == 0, "an MR image on the root namespace"
    # distinct channels: the simulated radios' gains differ (seeds 7 and 8)
    gains = [[row["energy_upload_all_j"] for row in r.rows] for r in runs]
    assert gains[0] != gains[1]
    assert runs[0].channel_seed + 1 == runs[1].channel_seed
    for r in runs:
        assert (r.report_dir / "recording" / "slots.csv").is_file()
        # the scorer caught up with the round: every composed slot scored, its columns joined into the rows
        assert {row["slot"] for row in r.rows} <= set(read_scores(r.report_dir / "recording"))
        assert sum(row["loss"] is not None for row in r.rows) >= 0.9 * slots
        assert r.cpu["server_cores"] > 0.01 and r.cpu["world_cores"] > 0.01 and r.cpu["window_s"] > 4.0, r.cpu
        assert set(r.cpu["by_node_cpu_s"]) == set(NODES)
        assert (tmp_path / "fleet" / "logs" / r.name / "gsrmr_server.log").is_file()
    assert not [p for p in Path("/tmp").glob(f"gsrmr_limo_{os.getpid()}_robot*")], "pty links left behind"
