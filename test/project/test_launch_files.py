"""Every launch file names executables that setup.py installs and config files that setup.py ships.

Launch files target real ROS 2 installs (no `launch` here); this checks them statically, plus the
process list of sim.launch.py (gsrmr_sim.sim_stack) that `make demo` and the integration tests run.
"""

import ast
from pathlib import Path
import re

import pytest
from support.setup_scripts import console_scripts

REPO = Path(__file__).resolve().parents[2]
LAUNCH_FILES = sorted((REPO / "launch").glob("*.launch.py"))


def test_launch_files_exist():
    names = {p.name for p in LAUNCH_FILES}
    assert {"robot.launch.py", "server.launch.py", "sim.launch.py"} <= names


@pytest.mark.parametrize("path", LAUNCH_FILES, ids=lambda p: p.name)
def test_launch_file_executables_and_configs(path):
    text = path.read_text()
    ast.parse(text)  # valid Python
    scripts = console_scripts()
    for exe in re.findall(r'executable="([^"]+)"', text):
        assert exe in scripts, f"{path.name}: executable {exe} is not a console script of setup.py"
    assert 'package="gsrmr"' in text or "sim_stack" in text
    for cfg in re.findall(r'"config", "([^"]+\.yaml)"', text):
        assert (REPO / "config" / cfg).is_file(), f"{path.name}: config/{cfg} missing"


def test_sim_stack_executables_and_param_files_are_installed():
    from gsrmr_sim.sim_stack import sim_stack

    scripts = console_scripts()
    specs = sim_stack(model_path="/nonexistent.ply", config=REPO / "config")
    assert len({s.name for s in specs}) == len(specs)
    for spec in specs:
        assert spec.executable in scripts, spec.executable
        for f in spec.param_files:
            assert Path(f).is_file() and Path(f).parent == REPO / "config", f


def test_setup_installs_every_config_and_launch_file():
    import importlib.util
    import os

    spec = importlib.util.spec_from_file_location("gsrmr_setup", REPO / "setup.py")
    module = importlib.util.module_from_spec(spec)
    cwd = os.getcwd()
    os.chdir(REPO)
    try:
        spec.loader.exec_module(module)  # __name__ != "__main__": setup() is not called
        files = module.data_files()
    finally:
        os.chdir(cwd)
    installed = {Path(f) for _, group in files for f in group}
    for path in [*LAUNCH_FILES, *(REPO / "config").rglob("*.yaml")]:
        assert path.relative_to(REPO) in installed, path


def test_param_files_are_valid_ros_parameter_yaml():
    import yaml

    for path in (REPO / "config").glob("*.yaml"):
        data = yaml.safe_load(path.read_text())
        for node, body in data.items():
            assert set(body) == {"ros__parameters"}, (path.name, node)


def test_param_files_are_keyed_wildcard_only():
    """The root of the launch-argument bug: rcl applies a node-name key after every ``/**`` key, and
    launch_ros writes a launch file's dict keyed ``/**``, so a node-keyed config value silently beat the
    launch argument (and stopped matching under a namespace). Every config file is one node's, keyed ``/**``."""
    import yaml

    for path in [*(REPO / "config").glob("*.yaml"), *(REPO / "config" / "routes").glob("*.yaml")]:
        assert list(yaml.safe_load(path.read_text())) == ["/**"], path.name


@pytest.mark.parametrize("name", ["sandbox", "garden"])
def test_route_files_match_the_scenes(name):
    """config/routes/<scene>.yaml (what the workstation's scheduler predicts along) is the scene's route."""
    import numpy as np
    import yaml

    from gsrmr_sim.world.scene import load_scene

    params = yaml.safe_load((REPO / "config" / "routes" / f"{name}.yaml").read_text())["/**"]["ros__parameters"]
    route = load_scene(name).route
    np.testing.assert_allclose(np.reshape(params["route_waypoints_m"], (-1, 2)), route.waypoints, atol=1e-6)
    assert params["route_speed_mps"] == route.speed_mps


def test_generated_override_file_is_keyed_wildcard(tmp_path):
    """The demo's and the test stacks' override files follow launch_ros: keyed ``/**``, passed last."""
    import yaml

    from gsrmr_sim.sim_stack import command_line, sim_stack

    spec = next(s for s in sim_stack(model_path="/m.ply", config=REPO / "config") if s.name == "gsrmr_server")
    argv = command_line(spec, tmp_path, tmp_path / "params")
    files = [argv[i + 1] for i, a in enumerate(argv) if a == "--params-file"]
    assert files[:-1] == spec.param_files
    data = yaml.safe_load(Path(files[-1]).read_text())
    assert list(data) == ["/**"] and data["/**"]["ros__parameters"]["model_path"] == "/m.ply"


def test_shipped_link_and_plan_constants_are_the_link_models():
    """config/link.yaml and config/scheduler.yaml ship the paper's link: the constants of
    gsrmr_common.link_model / channel that LinkBudget, Problem and the node parameters default to."""
    import math

    import yaml

    from gsrmr_common import channel, link_model
    from gsrmr_scheduler.problem import Problem

    link = yaml.safe_load((REPO / "config" / "link.yaml").read_text())["/**"]["ros__parameters"]
    plan = yaml.safe_load((REPO / "config" / "scheduler.yaml").read_text())["/**"]["ros__parameters"]
    assert link["slot_s"] == link_model.SLOT_S and link["bandwidth_hz"] == link_model.BANDWIDTH_HZ
    assert 10 ** (link["noise_dbm"] / 10) / 1e3 == pytest.approx(link_model.NOISE_W, rel=1e-12)
    assert (link["pathloss_db_at_1m"], link["pathloss_exponent"], link["rician_k"]) == \
        (channel.PATHLOSS_DB_AT_1M, channel.PATHLOSS_EXPONENT, channel.RICIAN_K)
    assert (plan["image_bits"], plan["pose_bits"]) == (link_model.IMAGE_BITS, link_model.KEY_BITS)
    budget, problem = link_model.LinkBudget(), Problem([1.0, 1.0], [0.1, 0.1], 0.1)
    assert (budget.bandwidth_hz, budget.noise_w, budget.rician_k) == \
        (problem.bandwidth_hz, problem.noise_w, channel.RICIAN_K)
    assert (problem.image_bits, problem.pose_bits, problem.slot_s) == (67_200.0, 192.0, 0.1)
    assert math.isclose(10 * math.log10(budget.noise_w * 1e3), -60.0)


def test_launch_nodes_come_from_the_process_specs_through_one_function():
    """sim.launch.py and fleet.launch.py build every Node with gsrmr_sim.launch_nodes (none by hand): the
    spec's executable, name, arguments, parameter files then overrides (last, as command_line passes them),
    remappings, niceness and namespace."""
    pytest.importorskip("launch_ros")
    from gsrmr_sim.launch_nodes import launch_node, node_arguments
    from gsrmr_sim.sim_stack import fleet_stack, nice_prefix, sim_stack

    for spec in sim_stack(model_path="/m.ply", config=REPO / "config"):
        kw = node_arguments(spec, namespace="/ns")
        assert (kw["package"], kw["executable"], kw["name"], kw["namespace"]) == (
            "gsrmr", spec.executable, spec.name, "/ns")
        assert kw["parameters"] == ([*spec.param_files, spec.params] if spec.params else spec.param_files)
        assert (kw["arguments"], kw["remappings"]) == (spec.arguments, spec.remappings)
        assert kw["prefix"] == (" ".join(nice_prefix(spec)) or None)
        node = launch_node(spec)
        assert (node.node_package, node.node_executable) == ("gsrmr", spec.executable)
    fleet = fleet_stack(robots=2, model_path="/m.ply", config=REPO / "config")
    assert {node_arguments(s)["namespace"] for s in fleet} == {"/robot1", "/robot2"}
    for name in ("sim.launch.py", "fleet.launch.py"):
        text = (REPO / "launch" / name).read_text()
        assert "launch_node(" in text and not re.search(r"(?<!launch_)Node\(", text), name


def test_sim_stack_refuses_overrides_for_no_node():
    from gsrmr_sim.sim_stack import sim_stack

    with pytest.raises(ValueError, match="gsrmr-route-follower"):  # an executable's name is no node name
        sim_stack(model_path="/m.ply", config=REPO / "config", overrides={"gsrmr-route-follower": {"laps": 0}})
    specs = sim_stack(model_path="/m.ply", config=REPO / "config", overrides={"gsrmr_route_follower": {"laps": 0}})
    assert next(s for s in specs if s.name == "gsrmr_route_follower").params["laps"] == 0


def test_sim_launch_sets_the_robot_off_once_the_server_composes():
    """sim.launch.py starts every process at once: its route follower waits for the server's first slot."""
    pytest.importorskip("launch_ros")
    import importlib.util

    import launch

    loader = importlib.util.spec_from_file_location("sim_launch_under_test", REPO / "launch" / "sim.launch.py")
    module = importlib.util.module_from_spec(loader)
    loader.loader.exec_module(module)
    module.launch_node = lambda spec, namespace=None: spec  # the specs the launch file maps to Nodes
    context = launch.LaunchContext()
    context.launch_configurations.update({"scene": "sandbox", "model_path": "/m.ply", "record_dir": "",
                                          "loss_threshold": "0.03", "laps": "1", "method": "exact",
                                          "serial_link": "/tmp/limo", "namespace": ""})
    specs = {spec.name: spec for spec in module._nodes(context)}
    assert specs["gsrmr_route_follower"].params.get("wait_for_server") is True
