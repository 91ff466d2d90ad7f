"""Every console script answers ``--help`` and exits 0 without starting anything; a node's help names each of its
topics and parameters (from the dataclasses it declares), and every node declares its parameters only through
those dataclasses."""

from __future__ import annotations

import ast
from concurrent.futures import ThreadPoolExecutor
from importlib import import_module
from importlib.metadata import entry_points
import os
from pathlib import Path
import subprocess
import sys

import pytest

from gsrmr_common.node_help import NodeInterface, format_help, wants_help
from gsrmr_common.node_params import NodeParameters, ros_parameter

REPO = Path(__file__).resolve().parents[2]
SCRIPTS = {ep.name: ep.value for ep in entry_points(group="console_scripts") if ep.name.startswith("gsrmr-")}


def interface_of(script: str) -> NodeInterface | None:
    """The :class:`NodeInterface` of a node script (found in its entry module), None for a plain CLI."""
    module = import_module(SCRIPTS[script].split(":")[0])
    found = [v for v in vars(module).values() if isinstance(v, NodeInterface) and v.executable == script]
    return found[0] if found else None


def run_help(script: str) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).parent / script
    return subprocess.run([str(exe), "--help"], capture_output=True, text=True, timeout=120, env=dict(os.environ),
                          stdin=subprocess.DEVNULL)


@pytest.fixture(scope="module")
def helps() -> dict[str, subprocess.CompletedProcess]:
    """``<script> --help`` of every console script, a few at a time (each only imports and prints)."""
    if not SCRIPTS:
        pytest.skip("package not installed (no console_scripts metadata)")
    with ThreadPoolExecutor(max_workers=max(2, os.cpu_count() or 1)) as pool:
        return dict(zip(sorted(SCRIPTS), pool.map(run_help, sorted(SCRIPTS)), strict=True))


@pytest.mark.parametrize("script", sorted(SCRIPTS))
def test_every_console_script_answers_help_and_exits_0(helps, script):
    result = helps[script]
    assert result.returncode == 0, f"{script} --help: exit {result.returncode}\n{result.stderr[-2000:]}"
    assert "usage" in result.stdout.lower(), result.stdout[:500]
    interface = interface_of(script)
    if interface is not None:  # a node: what it is, every topic and every parameter
        assert interface.summary.split()[0] in result.stdout
        for endpoint in (*interface.subscribes, *interface.publishes, *interface.services):
            assert endpoint.name in result.stdout, f"{script} --help does not name {endpoint.name}"
        for name in interface.parameter_names():
            assert f"  {name} (" in result.stdout, f"{script} --help does not list parameter {name}"


def test_the_node_scripts_are_the_ones_with_an_interface():
    """Each ROS node (its module imports rclpy's Node) has a NodeInterface its --help prints."""
    nodes = {s for s in SCRIPTS if interface_of(s) is not None}
    assert nodes >= {"gsrmr-robot", "gsrmr-server", "gsrmr-scheduler", "gsrmr-limo-base", "gsrmr-link-echo",
                     "gsrmr-link-probe", "gsrmr-mock-camera", "gsrmr-sim-channel", "gsrmr-route-follower",
                     "gsrmr-sim-scorer", "gsrmr-uplink-relay", "gsrmr-mock-limo"}, sorted(nodes)


def test_help_is_asked_only_before_ros_args():
    assert wants_help(["gsrmr-robot", "--help"]) and wants_help(["gsrmr-robot", "-h", "--ros-args"])
    assert not wants_help(["gsrmr-robot", "--ros-args", "-p", "x:=1", "--help"])
    assert not wants_help(["gsrmr-robot"])


def test_help_lists_type_default_range_and_read_only():
    from dataclasses import dataclass

    from gsrmr_common.node_help import ParameterGroup

    @dataclass(frozen=True)
    class Demo(NodeParameters):
        rate_hz: float = ros_parameter(20.0, "Ping rate [Hz]", min_value=0.1, max_value=1000.0)
        names: tuple[str, ...] = ros_parameter(("a", "b"), "Writers", read_only=True)

    text = format_help(NodeInterface("gsrmr-demo-node", "demo", "A demo node.", parameters=(
        ParameterGroup(Demo), ParameterGroup(Demo, "sub."))))
    assert "  rate_hz (float, default 20 [0.1, 1000])" in text
    assert "  names (list, default ['a', 'b'], read-only)" in text
    assert "  sub.rate_hz (float" in text and "Ping rate [Hz]" in text


def _declaring_calls(path: Path) -> list[str]:
    """Calls of rclpy's ``declare_parameter(s)`` or of our raw ``declare(...)`` in a module."""
    calls = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Call):
            name = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", "")
            if name in ("declare", "declare_parameter") or (name == "declare_parameters" and isinstance(
                    node.func, ast.Attribute)):
                calls.append(f"{path.relative_to(REPO)}:{node.lineno} {name}")
    return calls


def test_nodes_declare_parameters_only_through_their_dataclasses():
    """Outside gsrmr_common/ros_node.py no module declares a parameter by hand: what a node declares is what its
    dataclasses (and so its --help) say."""
    modules = [p for pkg in ("gsrmr_common", "gsrmr_robot", "gsrmr_server", "gsrmr_scheduler", "gsrmr_sim")
               for p in (REPO / pkg).rglob("*.py") if p != REPO / "gsrmr_common" / "ros_node.py"]
    assert [c for p in modules for c in _declaring_calls(p)] == []
