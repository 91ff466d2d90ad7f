"""What each node's module loads in a fresh interpreter: the robot side stays light.

The import-linter contracts in pyproject.toml (run by `make test` as `lint-imports`) check the static
import graph; this checks what really lands in ``sys.modules`` when a console script's module is
imported, transitive and lazy-at-import-time imports included.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

HEAVY = ("numba", "llvmlite", "cvxpy", "scipy", "torch", "plyfile", "matplotlib")
# Console scripts that run on the LIMO, with the module their entry point imports.
ROBOT_SIDE = {"gsrmr-robot": "gsrmr_robot.robot_node", "gsrmr-limo-base": "gsrmr_robot.limo.node",
              "gsrmr-link-probe": "gsrmr_common.link_check"}


def loaded_modules(module: str) -> set[str]:
    """``sys.modules`` after importing ``module`` in a new interpreter."""
    code = f"import importlib, json, sys; importlib.import_module({module!r}); print(json.dumps(sorted(sys.modules)))"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    return set(json.loads(result.stdout.splitlines()[-1]))


def offenders(modules: set[str], roots: tuple[str, ...]) -> list[str]:
    return sorted(m for m in modules if m.split(".")[0] in roots)


@pytest.mark.parametrize("script", sorted(ROBOT_SIDE))
def test_robot_side_node_loads_no_server_code_and_no_heavy_numerics(script):
    modules = loaded_modules(ROBOT_SIDE[script])
    assert ROBOT_SIDE[script] in modules
    assert offenders(modules, HEAVY) == [], f"{script} loads heavy modules"
    assert offenders(modules, ("gsrmr_server", "gsrmr_sim", "gsrmr_shapes")) == [], \
        f"{script} loads server, simulator or ray-caster code"


@pytest.mark.parametrize("module", ["gsrmr_server.server_node", "gsrmr_server.scheduler_node"])
def test_workstation_nodes_load_no_simulated_world(module):
    """The server takes intrinsics from camera_info and its virtual agents from the MR content; the
    scheduler its route from parameters: neither loads the simulator's scene, camera or stacks."""
    modules = loaded_modules(module)
    assert module in modules
    assert offenders(modules, ("gsrmr_sim",)) == []


def test_scheduler_node_loads_no_renderer():
    modules = loaded_modules("gsrmr_server.scheduler_node")
    assert sorted(m for m in modules if m.startswith(("gsrmr_server.splatting", "gsrmr_server.mr",
                                                       "gsrmr_server.compose", "gsrmr_shapes", "torch"))) == []


def test_the_check_can_fail():
    """The same checks do find what is there: the scheduler needs the solvers, the server the renderer and
    the ray caster, and the simulator's nodes load the simulator."""
    assert "numba" in {m.split(".")[0] for m in loaded_modules("gsrmr_server.scheduler_node")}
    assert {"gsrmr_shapes.raycast", "gsrmr_server.splatting.render"} <= loaded_modules("gsrmr_server.server_node")
    assert "gsrmr_sim.world.scene" in loaded_modules("gsrmr_sim.world.camera_node")


@pytest.mark.parametrize("module", ["gsrmr_common.interrupts", "gsrmr_sim.entries"])
def test_console_entry_module_is_light(module):
    """The entry wrappers every node script goes through import nothing before the guard is in place."""
    modules = loaded_modules(module)
    assert offenders(modules, (*HEAVY, "numpy", "rclpy", "gsrmr_server", "gsrmr_robot")) == []


def console_scripts() -> dict[str, str]:
    """Every ``gsrmr-*`` console script of the installed package → the module its entry point names."""
    from importlib.metadata import entry_points

    return {ep.name: ep.value.split(":")[0] for ep in entry_points(group="console_scripts")
            if ep.name.startswith("gsrmr-")}


def test_every_console_script_is_covered():
    scripts = console_scripts()
    if not scripts:
        pytest.skip("package not installed (no console_scripts metadata)")
    assert {"gsrmr-robot", "gsrmr-server", "gsrmr-scheduler", "gsrmr-demo", "gsrmr-experiments"} <= set(scripts)


@pytest.mark.parametrize("script", sorted(console_scripts()))
def test_console_script_module_respects_its_wing(script):
    """Each console script's module in a fresh interpreter: only the simulator's scripts load the simulator;
    the library tools (scheduling, splatting) load no ROS; the node wrappers stay light (above)."""
    module = console_scripts()[script]
    modules = loaded_modules(module)
    assert module in modules
    if not module.startswith("gsrmr_sim"):
        assert offenders(modules, ("gsrmr_sim",)) == [], f"{script} ({module}) loads the simulator"
    if module.startswith(("gsrmr_server.scheduling", "gsrmr_server.splatting")):
        assert offenders(modules, ("rclpy", "launch", "launch_ros")) == [], f"{script} ({module}) loads ROS"
