"""On the LIMO: base driver + uplink node. The camera driver is yours: remap its topics here.

ros2 launch gsrmr robot.launch.py port:=/dev/ttyTHS1 camera_image_topic:=/camera/color/image_raw \
    camera_info_topic:=/camera/color/camera_info

Parameters: config/link.yaml (shared uplink model), config/limo_base.yaml, config/camera_mount.yaml (also
loaded by the server), config/robot.yaml — every
file keyed ``/**``, so the launch arguments below (passed after them) always win, also under
``namespace:=…``.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue


def generate_launch_description() -> LaunchDescription:
    config = os.path.join(get_package_share_directory("gsrmr"), "config")
    link, base, mount, robot = (os.path.join(config, name)
                                for name in ("link.yaml", "limo_base.yaml", "camera_mount.yaml", "robot.yaml"))
    namespace = LaunchConfiguration("namespace")
    return LaunchDescription([
        DeclareLaunchArgument("port", default_value="/dev/ttyTHS1", description="LIMO serial port"),
        DeclareLaunchArgument("camera_image_topic", default_value="/camera/color/image_raw",
                              description="sensor_msgs/Image of the robot camera"),
        DeclareLaunchArgument("camera_info_topic", default_value="/camera/color/camera_info",
                              description="sensor_msgs/CameraInfo of that camera"),
        DeclareLaunchArgument("jpeg_quality", default_value="80", description="JPEG quality of uploaded images"),
        DeclareLaunchArgument("namespace", default_value="", description="ROS namespace of both nodes"),
        Node(package="gsrmr", executable="gsrmr-limo-base", name="gsrmr_limo_base", namespace=namespace,
             output="screen",
             parameters=[base, {"port": ParameterValue(LaunchConfiguration("port"), value_type=str)}]),
        Node(package="gsrmr", executable="gsrmr-robot", name="gsrmr_robot", namespace=namespace, output="screen",
             parameters=[link, mount, robot, {"jpeg_quality": ParameterValue(LaunchConfiguration("jpeg_quality"),
                                                                      value_type=int)}],
             remappings=[("camera/image_raw", LaunchConfiguration("camera_image_topic")),
                         ("camera/camera_info", LaunchConfiguration("camera_info_topic"))]),
    ])
