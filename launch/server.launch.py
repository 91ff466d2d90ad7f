"""On the workstation: MR composition server + online scheduler.

ros2 launch gsrmr server.launch.py model_path:=/path/to/sandbox.ply loss_threshold:=0.03
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description() -> LaunchDescription:
    share = get_package_share_directory("gsrmr")
    link = os.path.join(share, "config", "link.yaml")
    server = os.path.join(share, "config", "server.yaml")
    return LaunchDescription([
        DeclareLaunchArgument("model_path", description="Gaussian-splatting model (.ply)"),
        DeclareLaunchArgument("scene", default_value="sandbox"),
        DeclareLaunchArgument("loss_threshold", default_value="0.03"),
        DeclareLaunchArgument("record_dir", default_value="", description="slots.csv + MCAP ('' = off)"),
        Node(package="gsrmr", executable="gsrmr-server", name="gsrmr_server", output="screen",
             parameters=[link, server, {"model_path": LaunchConfiguration("model_path"),
                                        "scene": LaunchConfiguration("scene"),
                                        "record_dir": LaunchConfiguration("record_dir")}]),
        Node(package="gsrmr", executable="gsrmr-scheduler", name="gsrmr_scheduler", output="screen",
             parameters=[link, server, {"scene": LaunchConfiguration("scene"),
                                        "loss_threshold": LaunchConfiguration("loss_threshold")}]),
    ])
