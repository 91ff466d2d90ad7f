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
    assert offenders(modules, ("gsrmr_server", "gsrmr_sim")) == [], f"{script} loads server/simulator code"


def test_scheduler_node_loads_no_simulated_world():
    """The workstation's scheduler takes its route from parameters, not from the simulator's scene."""
    modules = loaded_modules("gsrmr_server.scheduler_node")
    sim = ("gsrmr_server.world", "gsrmr_server.sim_stack", "gsrmr_server.demo", "gsrmr_server.survey",
           "gsrmr_server.fault_relay", "gsrmr_server.experiments", "gsrmr_sim")
    assert sorted(m for m in modules if m.startswith(sim)) == []


def test_the_check_can_fail():
    """The same check on the scheduler node (which needs the solvers) does find them."""
    modules = loaded_modules("gsrmr_server.scheduler_node")
    assert "numba" in {m.split(".")[0] for m in modules}
    # and the server node still loads the simulated world (virtual agents, intrinsics): the next step
    assert any(m.startswith("gsrmr_server.world") for m in loaded_modules("gsrmr_server.server_node"))


def test_console_entry_module_is_light():
    """The entry wrapper every node script goes through imports nothing before the guard is in place."""
    modules = loaded_modules("gsrmr_common.interrupts")
    assert offenders(modules, (*HEAVY, "numpy", "rclpy", "gsrmr_server", "gsrmr_robot")) == []
