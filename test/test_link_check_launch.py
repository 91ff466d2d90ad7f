"""launch_testing: the DDS link check pair, as `colcon test` runs it on a ROS 2 install.

Skipped where `launch_testing` does not import (the PyPI ROS wheels ship no `launch`); the same
executables are tested as plain processes in test_link_check.py.
"""

import unittest

import pytest

pytest.importorskip("launch_testing", reason="launch_testing is not installed (no ROS 2 install)")
pytest.importorskip("launch")
pytest.importorskip("launch_ros")

import launch
import launch_ros.actions
import launch_testing.actions
import launch_testing.asserts


@pytest.mark.launch_test
def generate_test_description():
    echo = launch_ros.actions.Node(package="gsrmr", executable="gsrmr-link-echo", output="screen")
    probe = launch_ros.actions.Node(package="gsrmr", executable="gsrmr-link-probe", output="screen",
                                    parameters=[{"count": 50, "rate_hz": 50.0, "settle_s": 0.5}])
    return launch.LaunchDescription([echo, probe, launch_testing.actions.ReadyToTest()]), {"probe": probe}


class TestProbeFinishes(unittest.TestCase):
    def test_probe_reports(self, proc_info, proc_output, probe):
        proc_info.assertWaitForShutdown(process=probe, timeout=60)
        proc_output.assertWaitFor('"sent": 50', process=probe, timeout=5)


@launch_testing.post_shutdown_test()
class TestExitCodes(unittest.TestCase):
    def test_exit_codes(self, proc_info):
        launch_testing.asserts.assertExitCodes(proc_info)


