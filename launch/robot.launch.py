"""On the LIMO: base driver + uplink node. The camera driver is yours (remap camera_image_topic).

ros2 launch gsrmr robot.launch.py port:=/dev/ttyTHS1 camera_image_topic:=/camera/color/image_raw
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
    robot = os.path.join(share, "config", "robot.yaml")
    return LaunchDescription([
        DeclareLaunchArgument("port", default_value="/dev/ttyTHS1", description="LIMO serial port"),
        DeclareLaunchArgument("camera_image_topic", default_value="/camera/color/image_raw",
                              description="sensor_msgs/Image of the robot camera"),
        Node(package="gsrmr", executable="gsrmr-limo-base", name="gsrmr_limo_base", output="screen",
             parameters=[robot, {"port": LaunchConfiguration("port")}]),
        Node(package="gsrmr", executable="gsrmr-robot", name="gsrmr_robot", output="screen",
             parameters=[link, robot],
             remappings=[("camera/image_raw", LaunchConfiguration("camera_image_topic"))]),
    ])
