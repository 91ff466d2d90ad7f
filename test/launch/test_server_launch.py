"""launch_testing: the installed ``server.launch.py`` under a namespace; every launch argument reaches its node.

The launch file is included from the ament index with every argument set to a non-default value and
``namespace:=gsrmr_ws``; ``ros2 param get`` (the CLI, as a user types it) reads each value back from the
node it was meant for. This is the regression test of the parameter precedence bug: a launch argument
that a node-keyed YAML also set was silently ignored (rcl applies node-name keys after ``/**`` keys).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
import sys
import tempfile
import unittest

# `launch_test test/launch/<file>` loads this file by its path, with no conftest and test/ not on sys.path: put it
# there for the helpers below, test/support/ (under pytest, whose pythonpath is test/, it already is).
if str(Path(__file__).resolve().parents[1]) not in sys.path:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import pytest
from support.launch_support import isolate_this_process, launch_file, require_ros_tooling, ros2, ros2_until

needs_ros_tooling = require_ros_tooling()

from ament_index_python.packages import get_package_share_directory  # noqa: E402
import launch  # noqa: E402
from launch.launch_description_sources import PythonLaunchDescriptionSource  # noqa: E402
import launch_testing.actions  # noqa: E402
import launch_testing.asserts  # noqa: E402
from support.stack_harness import make_point_model  # noqa: E402

NAMESPACE = "gsrmr_ws"


def _route_file(folder: Path) -> Path:
    """A route file of the user's own (the sandbox loop at 0.25 m/s), keyed ``/**`` like the shipped ones."""
    path = folder / "route.yaml"
    path.write_text("/**:\n  ros__parameters:\n    route_waypoints_m: [-1.0, -1.1, 1.0, -1.1, 1.2, 0.9, -1.0, 1.1]\n"
                    "    route_speed_mps: 0.25\n")
    return path


@needs_ros_tooling
@pytest.mark.launch_test
def generate_test_description():
    isolate_this_process()
    folder = Path(tempfile.mkdtemp(prefix="gsrmr-server-launch-"))
    args = {
        "model_path": str(make_point_model(folder, n=1000)),
        "loss_threshold": "0.035",
        "mr_content": str(Path(get_package_share_directory("gsrmr")) / "config" / "mr" / "sandbox.yaml"),
        "record_dir": str(folder / "record"),
        "method": "rounding",
        "route_file": str(_route_file(folder)),
        "namespace": NAMESPACE,
    }
    server = launch.actions.IncludeLaunchDescription(PythonLaunchDescriptionSource(launch_file("server.launch.py")),
                                                     launch_arguments=args.items())
    return launch.LaunchDescription([server, launch_testing.actions.ReadyToTest()]), {"args": args}


ANSWERS = ("value is:", "values are:")
#: ``ros2 param get`` commands run at once: each is a CLI process that mostly waits (interpreter start, discovery of
#: the node), so a few overlap well even on two cores: one after the other the 11 took 30-40 s, 6 at a time 7-12 s.
PARALLEL_GETS = 6


def param_get(node: str, name: str) -> str:
    """``ros2 param get --no-daemon /<ns>/<node> <name>``'s answer (retried while discovery settles)."""
    # "String value is: …" for a scalar, "Double values are: […]" for an array
    result = ros2_until("param", "get", "--no-daemon", "--timeout", "10", f"/{NAMESPACE}/{node}", name,
                        ok=ANSWERS, attempts=6)
    answer = (result.stdout + result.stderr).strip()
    if not any(a in answer for a in ANSWERS):  # say what the graph held
        nodes = ros2("node", "list", "--no-daemon", "--spin-time", "5")
        answer += f" (ros2 node list: {nodes.stdout.split()} {nodes.stderr.strip()})"
    return answer


class TestServerLaunchArguments(unittest.TestCase):
    def test_every_argument_reaches_its_node(self, proc_info, args):
        expected = {
            ("gsrmr_server", "model_path"): f"String value is: {args['model_path']}",
            ("gsrmr_server", "mr_content"): f"String value is: {args['mr_content']}",
            ("gsrmr_server", "record_dir"): f"String value is: {args['record_dir']}",
            ("gsrmr_scheduler", "route_speed_mps"): "Double value is: 0.25",
            ("gsrmr_scheduler", "route_waypoints_m"): "Double values are: [-1.0, -1.1, 1.0, -1.1, 1.2, 0.9, -1.0, "
                                                      "1.1]",
            ("gsrmr_scheduler", "loss_threshold"): "Double value is: 0.035",
            ("gsrmr_scheduler", "method"): "String value is: rounding",
            # and the package's config files still apply where no argument overrides them
            ("gsrmr_scheduler", "horizon"): "Integer value is: 100",
            ("gsrmr_server", "jpeg_quality"): "Integer value is: 85",
            ("gsrmr_scheduler", "bandwidth_hz"): "Double value is: 1000000.0",
            ("gsrmr_server", "camera_mount.height_m"): "Double value is: 0.15",  # config/camera_mount.yaml
        }
        with ThreadPoolExecutor(max_workers=PARALLEL_GETS) as pool:
            answers = dict(zip(expected, pool.map(lambda key: param_get(*key), expected), strict=True))
        for (node, name), answer in expected.items():
            self.assertEqual(answers[(node, name)], answer, f"{node}.{name}")
        exited = [n for n in proc_info.process_names() if getattr(proc_info[n], "returncode", None) is not None]
        self.assertEqual(exited, [], "a node died")
        self.assertTrue(Path(args["record_dir"]).is_dir(), "the server did not open the record_dir it was given")


@launch_testing.post_shutdown_test()
class TestServerLaunchExit(unittest.TestCase):
    def test_exit_codes(self, proc_info):
        launch_testing.asserts.assertExitCodes(proc_info)
        self.assertEqual(len(proc_info.process_names()), 2)
