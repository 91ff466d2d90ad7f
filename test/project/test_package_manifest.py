"""package.xml declares every dependency a ROS user's rosdep must install; the rest is a pip list.

Every package of requirements.txt is either declared in package.xml under its rosdep key (rosdistro
``rosdep/python.yaml``) or listed, with the same pin, in requirements-pip-only.txt (no rosdep key).
"""

from pathlib import Path
import re
import xml.etree.ElementTree as ET

import pytest

REPO = Path(__file__).resolve().parents[2]

# pip name -> rosdep key (checked against rosdistro rosdep/python.yaml); None: no key, pip only.
ROSDEP_KEYS = {
    "numpy": "python3-numpy", "scipy": "python3-scipy", "numba": "python3-numba", "llvmlite": "python3-numba",
    "cvxpy": "python3-cvxpy-pip", "opencv-contrib-python-headless": "python3-opencv", "pillow": "python3-pil",
    "pyserial": "python3-serial", "PyYAML": "python3-yaml", "matplotlib": "python3-matplotlib",
    "tqdm": "python3-tqdm", "psutil": "python3-psutil", "pytest": "python3-pytest",
    "pytest-timeout": "python3-pytest-timeout", "hypothesis": "python3-hypothesis",
    "plyfile": None, "mcap": None, "mcap-ros2-support": None, "clarabel": None, "scs": None, "osqp": None,
    "highspy": None, "rosbags": None, "apsw": None, "backports.zstd": None, "lz4": None, "ruamel.yaml": None,
    "typing_extensions": None, "zstandard": None, "catkin-pkg": "python3-catkin-pkg",
}
BUILD_TOOLS = {"setuptools", "wheel", "ruff", "import-linter", "grimp",  # build and lint tools, not the package's
               "docutils", "packaging", "pyparsing", "python-dateutil", "tzdata"}  # catkin-pkg's, pinned


def _pins(path: Path) -> dict[str, str]:
    pins = {}
    for line in path.read_text().splitlines():
        line = line.split("#")[0].strip()
        if line:
            name, version = line.split("==")
            pins[name] = version
    return pins


def _declared() -> dict[str, set[str]]:
    root = ET.parse(REPO / "package.xml").getroot()
    out: dict[str, set[str]] = {}
    for element in root:
        if element.tag.endswith("depend"):
            out.setdefault(element.tag, set()).add(element.text.strip())
    return out


def test_every_requirement_is_declared_or_pip_only():
    declared = _declared()
    keys = declared.get("exec_depend", set()) | declared.get("test_depend", set())
    pip_only = _pins(REPO / "requirements-pip-only.txt")
    pins = _pins(REPO / "requirements.txt")
    for name, version in pins.items():
        if name in BUILD_TOOLS:
            continue
        assert name in ROSDEP_KEYS, f"{name}: add its rosdep key (or None) to this test and to package.xml"
        key = ROSDEP_KEYS[name]
        if key is None:
            assert pip_only.get(name) == version, f"{name}=={version} missing from requirements-pip-only.txt"
        else:
            assert key in keys, f"{name}: rosdep key {key} not declared in package.xml"
    assert set(pip_only) <= set(pins), "requirements-pip-only.txt lists a package requirements.txt does not pin"


def test_every_ros_import_is_declared():
    """Each ROS package imported by the code or the tests is an exec or test dependency."""
    declared = _declared()
    keys = declared.get("exec_depend", set()) | declared.get("test_depend", set())
    ros_packages = {"rclpy", "ament_index_python", "builtin_interfaces", "rcl_interfaces", "std_msgs", "std_srvs",
                    "sensor_msgs", "geometry_msgs", "nav_msgs", "diagnostic_msgs", "tf2_ros", "tf2_msgs",
                    "cv_bridge", "launch", "launch_ros", "launch_testing", "launch_testing_ros"}
    sources = [*REPO.glob("gsrmr_*/**/*.py"), *REPO.glob("launch/*.py"), *REPO.glob("test/**/*.py")]
    used = set()
    for path in sources:
        for match in re.finditer(r"^\s*(?:from|import)\s+([a-z_0-9]+)", path.read_text(), re.MULTILINE):
            if match.group(1) in ros_packages:
                used.add(match.group(1))
    assert used, "no ROS import found: the scan is broken"
    assert used <= keys, f"imported but not declared in package.xml: {sorted(used - keys)}"


# ------------------------------------------------------------------------------------------- a robot-only install
HEAVY_KEYS = {"python3-pytorch-pip", "python3-numba", "python3-cvxpy-pip", "python3-scipy", "python3-matplotlib"}
ROBOT_SCRIPTS_MODULES = ("gsrmr_robot.robot_node", "gsrmr_robot.limo.node", "gsrmr_common.link_check")


def _dependencies(role: str | None) -> set[str]:
    """Every dependency rosdep installs for ``GSRMR_ROLE=role`` (unset: None), conditions evaluated by catkin_pkg
    as rosdep does (REP 149)."""
    from catkin_pkg.package import parse_package

    package = parse_package(str(REPO / "package.xml"))
    package.evaluate_conditions({} if role is None else {"GSRMR_ROLE": role})
    return {d.name for d in (*package.build_depends, *package.buildtool_depends, *package.exec_depends,
                             *package.test_depends, *package.build_export_depends) if d.evaluated_condition}


@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # catkin_pkg's condition parser on pyparsing 3
def test_the_robot_role_installs_no_solver_renderer_or_heavy_numerics():
    robot, everything = _dependencies("robot"), _dependencies(None)
    assert robot & HEAVY_KEYS == set(), sorted(robot & HEAVY_KEYS)
    assert everything >= HEAVY_KEYS  # the workstation (the variable unset) still gets them
    assert {"rclpy", "python3-numpy", "python3-opencv", "python3-serial", "python3-yaml"} <= robot
    assert _dependencies("workstation") == everything


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_the_robot_requirements_are_what_the_robot_side_imports_with_the_same_pins():
    """requirements-robot.txt pins, as requirements.txt does, every package of ours the robot's console scripts load
    (ROS wheels and what they require excepted), and its rosdep key is installed in the robot role."""
    import importlib.metadata as metadata
    import json
    import subprocess
    import sys

    code = ("import importlib, json, sys; [importlib.import_module(m) for m in sys.argv[1:]]; "
            "print(json.dumps(sorted({k.split('.')[0] for k in sys.modules})))")
    result = subprocess.run([sys.executable, "-c", code, *ROBOT_SCRIPTS_MODULES], capture_output=True, text=True,
                            timeout=120, check=True)
    loaded = set(json.loads(result.stdout.splitlines()[-1]))
    by_module = metadata.packages_distributions()
    def norm(name: str) -> str:  # PEP 503
        return re.sub(r"[-_.]+", "-", name).lower()

    ros_requires = {norm(re.split(r"[;\[=<>! ]", r, maxsplit=1)[0]) for d in metadata.distributions()
                    if d.metadata["Name"].lower().startswith("ros-") for r in (d.requires or [])}
    ours = {norm(name): name for name in _pins(REPO / "requirements.txt")}
    needed = {ours[norm(dist)] for module in loaded for dist in by_module.get(module, [])
              if norm(dist) in ours and norm(dist) not in ros_requires}
    robot_pins, pins = _pins(REPO / "requirements-robot.txt"), _pins(REPO / "requirements.txt")
    assert needed, "no third-party import found on the robot side: the scan is broken"
    assert needed <= set(robot_pins), f"the robot side loads {sorted(needed - set(robot_pins))}"
    assert all(pins[name] == version for name, version in robot_pins.items())
    robot = _dependencies("robot")
    assert {ROSDEP_KEYS[name] for name in robot_pins if ROSDEP_KEYS.get(name)} <= robot
