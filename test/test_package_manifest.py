"""package.xml declares every dependency a ROS user's rosdep must install; the rest is a pip list.

Every package of requirements.txt is either declared in package.xml under its rosdep key (rosdistro
``rosdep/python.yaml``) or listed, with the same pin, in requirements-pip-only.txt (no rosdep key).
"""

from pathlib import Path
import re
import xml.etree.ElementTree as ET

REPO = Path(__file__).resolve().parents[1]

# pip name -> rosdep key (checked against rosdistro rosdep/python.yaml); None: no key, pip only.
ROSDEP_KEYS = {
    "numpy": "python3-numpy", "scipy": "python3-scipy", "numba": "python3-numba", "llvmlite": "python3-numba",
    "cvxpy": "python3-cvxpy-pip", "opencv-contrib-python-headless": "python3-opencv", "pillow": "python3-pil",
    "pyserial": "python3-serial", "PyYAML": "python3-yaml", "matplotlib": "python3-matplotlib",
    "tqdm": "python3-tqdm", "psutil": "python3-psutil", "pytest": "python3-pytest",
    "pytest-timeout": "python3-pytest-timeout", "hypothesis": "python3-hypothesis",
    "plyfile": None, "mcap": None, "mcap-ros2-support": None, "clarabel": None, "scs": None, "osqp": None,
    "highspy": None, "rosbags": None, "apsw": None, "backports.zstd": None, "lz4": None, "ruamel.yaml": None,
    "typing_extensions": None, "zstandard": None,
}
BUILD_TOOLS = {"setuptools", "wheel", "ruff", "import-linter", "grimp"}  # build and lint tools, not the package's


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
    sources = [*REPO.glob("gsrmr_*/**/*.py"), *REPO.glob("launch/*.py"), *REPO.glob("test/*.py")]
    used = set()
    for path in sources:
        for match in re.finditer(r"^\s*(?:from|import)\s+([a-z_0-9]+)", path.read_text(), re.MULTILINE):
            if match.group(1) in ros_packages:
                used.add(match.group(1))
    assert used, "no ROS import found: the scan is broken"
    assert used <= keys, f"imported but not declared in package.xml: {sorted(used - keys)}"
