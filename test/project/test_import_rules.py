"""The import rules beyond what ``lint-imports`` checks statically (contracts in pyproject.toml).

* What each console script's module loads in a fresh interpreter: the robot side stays light, the
  workstation nodes load no simulator, the packages a console script enters through load nothing heavy.
* Every node's console script points at its node module's ``main``, decorated with
  :func:`gsrmr_common.interrupts.console_main`.
* No function-local ("late") import in the packages except the deliberate lazy ones, each listed with
  its reason in docs/architecture.md ("Deliberate lazy imports").
* The custom contract ``acyclic_wings`` (tools/import_contracts.py) finds a cycle where there is one.
"""

from __future__ import annotations

import ast
from concurrent.futures import Future, ThreadPoolExecutor
from importlib.metadata import entry_points
import json
import os
from pathlib import Path
import re
import subprocess
import sys

import pytest

from gsrmr_common.interrupts import CONSOLE_MAIN_MARK

REPO = Path(__file__).resolve().parents[2]
PACKAGES = ("gsrmr_common", "gsrmr_offline", "gsrmr_robot", "gsrmr_scheduler", "gsrmr_server", "gsrmr_shapes",
            "gsrmr_sim", "gsrmr_splat")
HEAVY = ("numba", "llvmlite", "cvxpy", "scipy", "torch", "plyfile", "matplotlib")
# Console scripts that run on the LIMO, with the module their entry point imports.
ROBOT_SIDE = {"gsrmr-robot": "gsrmr_robot.robot_node", "gsrmr-limo-base": "gsrmr_robot.limo.node",
              "gsrmr-link-probe": "gsrmr_common.link_check"}
# What a console script enters through before its node module: its package and the Ctrl-C guard's module.
LIGHT_ENTRY_MODULES = ("gsrmr_common.interrupts", "gsrmr_common", "gsrmr_offline", "gsrmr_robot", "gsrmr_scheduler",
                       "gsrmr_server", "gsrmr_sim", "gsrmr_splat")
# The ROS nodes among the console scripts: each enters through its node module's main, a console_main.
NODE_SCRIPTS = frozenset({"gsrmr-link-echo", "gsrmr-link-probe", "gsrmr-limo-base", "gsrmr-robot", "gsrmr-server",
                          "gsrmr-scheduler", "gsrmr-mock-limo", "gsrmr-mock-camera", "gsrmr-route-follower",
                          "gsrmr-sim-channel", "gsrmr-sim-scorer", "gsrmr-uplink-relay"})


def module_facts(module: str, attr: str | None = None) -> tuple[set[str], bool]:
    """``sys.modules`` after importing ``module`` in a new interpreter, and whether its ``attr`` is a
    :func:`~gsrmr_common.interrupts.console_main` (run ahead by :func:`_fresh_interpreters` where it is one of
    :func:`_facts_wanted`)."""
    future = _FACTS.get((module, attr))
    modules, mark = future.result() if future is not None else _fresh_interpreter_facts(module, attr)
    return set(modules), mark


def _fresh_interpreter_facts(module: str, attr: str | None,
                             env: dict[str, str] | None = None) -> tuple[set[str], bool]:
    """:func:`module_facts`, from a new interpreter that imports ``module`` (each time it is called), started with
    the environment ``env`` (default: a copy of this process's, taken now).

    The child always gets an environment array of its own: started from a worker thread with the process's
    (``env=None``), its exec read the C ``environ`` while pytest, in the main thread, set and removed
    ``PYTEST_CURRENT_TEST`` for the next test — ``setenv`` reallocates that array, and the exec failed with
    ``OSError: [Errno 14] Bad address`` (once in the 20 clean-clone runs on record; 500 of 1,934 spawns in a 20-s
    reproduction with the environment changing beside them, none with a copy passed)."""
    code = ("import importlib, json, sys; m = importlib.import_module(sys.argv[1]); "
            f"mark = bool(sys.argv[2]) and getattr(getattr(m, sys.argv[2]), {CONSOLE_MAIN_MARK!r}, False); "
            "print(json.dumps([sorted(sys.modules), mark]))")
    result = subprocess.run([sys.executable, "-c", code, module, attr or ""], capture_output=True, text=True,
                            timeout=120, env=dict(os.environ) if env is None else env)
    assert result.returncode == 0, result.stderr
    modules, mark = json.loads(result.stdout.splitlines()[-1])
    return set(modules), bool(mark)


#: ``(module, attr) → future`` of :func:`_fresh_interpreter_facts`, while this module's tests run
_FACTS: dict[tuple[str, str | None], Future] = {}


def _facts_wanted() -> list[tuple[str, str | None]]:
    """Every ``(module, attr)`` the tests below ask :func:`module_facts` about, in the order they ask."""
    wanted: list[tuple[str, str | None]] = [(ROBOT_SIDE[script], None) for script in sorted(ROBOT_SIDE)]
    wanted += [(m, None) for m in ("gsrmr_server.server_node", "gsrmr_scheduler.scheduler_node",
                                   "gsrmr_sim.world.camera_node", *LIGHT_ENTRY_MODULES)]
    wanted += [(value.split(":")[0], value.split(":")[1].strip()) for _, value in sorted(console_scripts().items())]
    return list(dict.fromkeys(wanted))


@pytest.fixture(scope="module", autouse=True)
def _fresh_interpreters():
    """Run the new interpreters of :func:`module_facts` ahead of the tests, a few at once (each only imports; one
    after the other, and the same module again for each test that asks, they took 40 s of the suite): every test
    still reads a fresh interpreter's ``sys.modules`` for its module."""
    env = dict(os.environ)  # copied here, in the main thread (see _fresh_interpreter_facts)
    with ThreadPoolExecutor(max_workers=max(2, os.cpu_count() or 1)) as pool:
        try:
            for key in _facts_wanted():
                _FACTS[key] = pool.submit(_fresh_interpreter_facts, *key, env)
            yield
        finally:
            _FACTS.clear()
            pool.shutdown(cancel_futures=True)


def loaded_modules(module: str) -> set[str]:
    """``sys.modules`` after importing ``module`` in a new interpreter."""
    return module_facts(module)[0]


def offenders(modules: set[str], roots: tuple[str, ...]) -> list[str]:
    return sorted(m for m in modules if m.split(".")[0] in roots)


@pytest.mark.parametrize("script", sorted(ROBOT_SIDE))
def test_robot_side_node_loads_no_server_code_and_no_heavy_numerics(script):
    modules = loaded_modules(ROBOT_SIDE[script])
    assert ROBOT_SIDE[script] in modules
    assert offenders(modules, HEAVY) == [], f"{script} loads heavy modules"
    assert offenders(modules, ("gsrmr_server", "gsrmr_scheduler", "gsrmr_offline", "gsrmr_splat", "gsrmr_sim",
                               "gsrmr_shapes")) == [], f"{script} loads workstation, simulator or ray-caster code"


@pytest.mark.parametrize("module", ["gsrmr_server.server_node", "gsrmr_scheduler.scheduler_node"])
def test_workstation_nodes_load_no_simulated_world(module):
    """The server takes intrinsics from camera_info and its virtual agents from the MR content; the
    scheduler its route from parameters: neither loads the simulator's scene, camera or stacks."""
    modules = loaded_modules(module)
    assert module in modules
    assert offenders(modules, ("gsrmr_sim",)) == []


def test_scheduler_node_loads_no_renderer():
    modules = loaded_modules("gsrmr_scheduler.scheduler_node")
    assert sorted(m for m in modules if m.startswith(("gsrmr_splat", "gsrmr_server.mr",
                                                       "gsrmr_server.compose", "gsrmr_shapes", "torch"))) == []


def test_the_check_can_fail():
    """The same checks do find what is there: the scheduler needs the solvers, the server the renderer and
    the ray caster, and the simulator's nodes load the simulator."""
    assert "numba" in {m.split(".")[0] for m in loaded_modules("gsrmr_scheduler.scheduler_node")}
    assert {"gsrmr_shapes.raycast", "gsrmr_splat.render"} <= loaded_modules("gsrmr_server.server_node")
    assert "gsrmr_sim.world.scene" in loaded_modules("gsrmr_sim.world.camera_node")


@pytest.mark.parametrize("module", LIGHT_ENTRY_MODULES)
def test_what_a_console_script_loads_before_its_guard_is_light(module):
    """A console script enters through its package (whose ``__init__`` arms the Ctrl-C guard) and the guard's
    module: neither loads anything slow, so the guard is in place before the node module's heavy imports."""
    modules = loaded_modules(module)
    assert offenders(modules, (*HEAVY, "numpy", "cv2", "rclpy", "yaml")) == []
    assert sorted(m for m in modules if m.split(".")[0] in PACKAGES) == sorted(
        {"gsrmr_common", "gsrmr_common.interrupts", module})


def console_scripts() -> dict[str, str]:
    """Every ``gsrmr-*`` console script of the installed package → its entry point (``module:function``)."""
    return {ep.name: ep.value for ep in entry_points(group="console_scripts") if ep.name.startswith("gsrmr-")}


def test_every_console_script_is_covered():
    scripts = console_scripts()
    if not scripts:
        pytest.skip("package not installed (no console_scripts metadata)")
    assert {"gsrmr-robot", "gsrmr-server", "gsrmr-scheduler", "gsrmr-demo", "gsrmr-experiments"} <= set(scripts)
    assert set(scripts) >= NODE_SCRIPTS, sorted(NODE_SCRIPTS - set(scripts))


@pytest.mark.parametrize("script", sorted(console_scripts()))
def test_console_script_module_respects_its_wing(script):
    """Each console script's module in a fresh interpreter: only the simulator's scripts load the simulator; the
    library and offline tools (scheduling, splatting, dataset, survey, update) load no ROS; a node's entry is its
    node module's own ``main`` (no wrapper naming the module by string), decorated with ``console_main``."""
    module, function = console_scripts()[script].split(":")
    modules, is_console_main = module_facts(module, function.strip())
    assert module in modules
    if not module.startswith("gsrmr_sim"):
        assert offenders(modules, ("gsrmr_sim",)) == [], f"{script} ({module}) loads the simulator"
    if script not in NODE_SCRIPTS and module.startswith(("gsrmr_scheduler", "gsrmr_splat", "gsrmr_offline")):
        assert offenders(modules, ("rclpy", "launch", "launch_ros")) == [], f"{script} ({module}) loads ROS"
    if script in NODE_SCRIPTS:
        assert function.strip().endswith("main") and module != "gsrmr_common.interrupts", console_scripts()[script]
        assert is_console_main, f"{script}: {module}:{function} is not decorated with console_main"
        assert "rclpy" in modules, f"{script} ({module}) is no ROS node"


# ------------------------------------------------------------------------------------------ late imports

LAZY_HEADING = "## Deliberate lazy imports"


def module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def function_local_imports(path: Path, module: str) -> list[tuple[str, int]]:
    """``(imported module, line)`` of every import inside a function of module ``module`` (file ``path``)."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found: list[tuple[str, int]] = []

    def visit(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inside = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            if in_function and isinstance(child, ast.Import):
                found.extend((alias.name, child.lineno) for alias in child.names)
            elif in_function and isinstance(child, ast.ImportFrom):
                base = package.split(".")[: len(package.split(".")) - child.level + 1] if child.level else []
                found.append((".".join([*base, *([child.module] if child.module else [])]), child.lineno))
            visit(child, inside)

    visit(ast.parse(path.read_text(), str(path)), False)
    return found


def late_imports() -> dict[tuple[str, str], list[int]]:
    """``{(module, imported module): [lines]}`` over every module of every package."""
    out: dict[tuple[str, str], list[int]] = {}
    for package in PACKAGES:
        for path in sorted((REPO / package).rglob("*.py")):
            for imported, line in function_local_imports(path, module_name(path)):
                out.setdefault((module_name(path), imported), []).append(line)
    return out


def lazy_allowlist(text: str) -> dict[tuple[str, str], str]:
    """The table under :data:`LAZY_HEADING`: ``{(module, imported module): reason}`` (backticked names)."""
    section = text.split(LAZY_HEADING, 1)[1].split("\n## ", 1)[0]
    rows = {}
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 3 and cells[0].startswith("`") and cells[1].startswith("`"):
            rows[(cells[0].strip("`"), cells[1].strip("`"))] = cells[2]
    return rows


def test_the_late_import_walk_finds_them(tmp_path):
    """The walk sees an import in a nested function, a method and a relative one, and nothing at module level."""
    sample = tmp_path / "probe.py"
    sample.write_text("import os\nfrom typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import json\n\n"
                      "def f():\n    def g():\n        import csv\n\nclass C:\n    def m(self):\n"
                      "        from . import sim_stack\n        from ..world import scene\n")
    assert function_local_imports(sample, "gsrmr_sim.limo.probe") == [
        ("csv", 8), ("gsrmr_sim.limo", 12), ("gsrmr_sim.world", 13)]


def test_no_late_imports_but_the_deliberate_lazy_ones():
    """Every function-local import is a row of the table in docs/architecture.md (module, imported module,
    reason); every row is still needed and gives a reason."""
    allowed = lazy_allowlist((REPO / "docs" / "architecture.md").read_text())
    assert allowed, f"no table under {LAZY_HEADING!r} in docs/architecture.md"
    found = late_imports()
    unlisted = {f"{module} imports {imported} in a function (lines {lines})"
                for (module, imported), lines in found.items() if (module, imported) not in allowed}
    assert not unlisted, "late imports (move them to the top, or list them with a reason):\n" + "\n".join(
        sorted(unlisted))
    assert sorted(set(allowed) - set(found)) == [], "rows of the table that no late import needs any more"
    assert all(len(reason) > 10 for reason in allowed.values()), allowed


# ------------------------------------------------------------------------------- the acyclic_wings contract

def run_lint_imports(tmp_path: Path, files: dict[str, str]) -> subprocess.CompletedProcess:
    """``lint-imports`` with only an ``acyclic_wings`` contract over the package ``files`` describes."""
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    config = tmp_path / "contracts.toml"
    config.write_text('[tool.importlinter]\nroot_packages = ["wingpkg"]\n'
                      'contract_types = ["acyclic_wings: tools.import_contracts.AcyclicWingsContract"]\n\n'
                      '[[tool.importlinter.contracts]]\nname = "no cycle"\ntype = "acyclic_wings"\n'
                      'wings = ["one: wingpkg", "two: wingpkg.lib"]\n')
    lint = Path(sys.executable).parent / "lint-imports"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), str(REPO)]))
    return subprocess.run([str(lint), "--config", str(config), "--no-cache"], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=120)


def test_acyclic_wings_contract_reports_a_cycle_through_a_late_import(tmp_path):
    files = {"wingpkg/__init__.py": "", "wingpkg/a.py": "from wingpkg import b\n",
             "wingpkg/b.py": "def f():\n    from wingpkg import c\n",
             "wingpkg/c.py": "import wingpkg.a\n", "wingpkg/lib/__init__.py": "",
             "wingpkg/lib/x.py": "import wingpkg.a\n"}  # another wing: its imports close no cycle of wing one
    result = run_lint_imports(tmp_path, files)
    assert result.returncode == 1, result.stdout + result.stderr
    text = re.sub(r"\s+", " ", result.stdout)
    assert "Import cycle in the one wing among wingpkg.a, wingpkg.b, wingpkg.c" in text, result.stdout
    assert "wingpkg.b -> wingpkg.c (l.2)" in text, result.stdout


def test_acyclic_wings_contract_keeps_a_cycle_free_wing(tmp_path):
    files = {"wingpkg/__init__.py": "", "wingpkg/a.py": "from wingpkg import b\n", "wingpkg/b.py": "import json\n",
             "wingpkg/lib/__init__.py": "", "wingpkg/lib/x.py": "import wingpkg.a\n",
             "wingpkg/lib/y.py": "import wingpkg.lib.x\n"}
    result = run_lint_imports(tmp_path, files)
    assert result.returncode == 0 and "KEPT" in result.stdout, result.stdout + result.stderr
