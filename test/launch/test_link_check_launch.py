"""launch_testing: the DDS link check pair, as ``colcon test`` runs it on a ROS 2 workspace.

The probe sends 50 pings to the echo over DDS and prints one JSON report on stdout; the test parses
it and checks that every ping came back and that the echo counted all of them. ``launch_test
test/launch/test_link_check_launch.py`` runs it too (README "Use it from ROS 2"), in a free ROS domain of its own.
"""

from __future__ import annotations

import json
from pathlib import Path
import sys
import unittest

# `launch_test test/launch/<file>` loads this file by its path, with no conftest and test/ not on sys.path: put it
# there for the helpers below, test/support/ (under pytest, whose pythonpath is test/, it already is).
if str(Path(__file__).resolve().parents[1]) not in sys.path:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import pytest
from support.launch_support import isolate_this_process, require_ros_tooling

needs_ros_tooling = require_ros_tooling()

import launch  # noqa: E402
import launch_ros.actions  # noqa: E402
import launch_testing.actions  # noqa: E402
import launch_testing.asserts  # noqa: E402

PINGS = 50


@needs_ros_tooling
@pytest.mark.launch_test
def generate_test_description():
    isolate_this_process()
    echo = launch_ros.actions.Node(package="gsrmr", executable="gsrmr-link-echo", output="screen")
    probe = launch_ros.actions.Node(package="gsrmr", executable="gsrmr-link-probe", output="screen",
                                    parameters=[{"count": PINGS, "rate_hz": 50.0, "settle_s": 0.5}])
    return launch.LaunchDescription([echo, probe, launch_testing.actions.ReadyToTest()]), {"probe": probe}


class TestProbeFinishes(unittest.TestCase):
    def test_probe_reports_every_ping_answered(self, proc_info, proc_output, probe):
        proc_info.assertWaitForShutdown(process=probe, timeout=60)
        # the report is printed on stdout (launch_testing's waitFor looks at stderr unless told)
        proc_output.assertWaitFor('"sent": ', process=probe, timeout=5, stream="stdout")
        lines = [line for io in proc_output[probe] for line in io.text.decode().splitlines()
                 if line.startswith("{") and '"sent"' in line]
        self.assertEqual(len(lines), 1, lines)
        report = json.loads(lines[0])
        self.assertEqual(report["sent"], PINGS)
        self.assertEqual(report["received"], PINGS, report)
        self.assertEqual(report["lost"], 0)
        self.assertEqual(report["echo"]["pings_received"], PINGS, report)
        self.assertIsNotNone(report["rtt_ms_p50"])


@launch_testing.post_shutdown_test()
class TestExitCodes(unittest.TestCase):
    def test_exit_codes(self, proc_info):
        launch_testing.asserts.assertExitCodes(proc_info)
