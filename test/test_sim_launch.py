"""launch_testing: sim.launch.py brings the whole simulated system up (ROS 2 install only).

Skipped where `launch_testing` does not import; the same process list (gsrmr_server.sim_stack) is
tested as real processes over DDS in test_node_suite.py.
"""

import os
import tempfile
import unittest

import pytest

pytest.importorskip("launch_testing", reason="launch_testing is not installed (no ROS 2 install)")
pytest.importorskip("launch")

from ament_index_python.packages import get_package_share_directory
import launch
from launch.launch_description_sources import PythonLaunchDescriptionSource
import launch_testing.actions
import numpy as np


def _tiny_model() -> str:
    from gsrmr_server.splatting.model import GaussianModel

    pts = np.random.default_rng(0).uniform(-2, 2, (2000, 3)) * [1, 1, 0.3] + [0, 0, 0.3]
    path = os.path.join(tempfile.mkdtemp(), "tiny.ply")
    GaussianModel.from_points(pts, np.full((2000, 3), 0.5), scales_m=0.05, opacities=0.8).save_ply(path)
    return path


@pytest.mark.launch_test
def generate_test_description():
    sim = launch.actions.IncludeLaunchDescription(
        PythonLaunchDescriptionSource(os.path.join(get_package_share_directory("gsrmr"), "launch", "sim.launch.py")),
        launch_arguments={"model_path": _tiny_model(), "laps": "0"}.items())
    return launch.LaunchDescription([sim, launch_testing.actions.ReadyToTest()])


class TestMrImages(unittest.TestCase):
    def test_server_publishes_mr_images(self, proc_output):
        import rclpy
        from sensor_msgs.msg import Image

        rclpy.init()
        try:
            node = rclpy.create_node("sim_launch_probe")
            got = []
            node.create_subscription(Image, "mr/image", got.append, 10)
            deadline = node.get_clock().now().nanoseconds + 60 * 10**9
            while len(got) < 10 and node.get_clock().now().nanoseconds < deadline:
                rclpy.spin_once(node, timeout_sec=0.1)
            self.assertGreaterEqual(len(got), 10)
        finally:
            rclpy.shutdown()
