"""On the LIMO: base driver + uplink node. The camera driver is yours: remap its topics here.

ros2 launch gsrmr robot.launch.py port:=/dev/ttyTHS1 camera_image_topic:=/camera/color/image_raw

Parameters: config/link.yaml, config/limo_base.yaml, config/camera_mount.yaml (also the server's) and
config/robot.yaml, keyed ``/**``, then the launch arguments (README.md's launch table), which win. Name the camera
and radio drivers in config/robot.yaml; known writers and ``keystore:=``: docs/security.md.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue


def _security(context, node_name: str) -> dict:
    """The Node arguments that run ``node_name`` enforced in its enclave when ``keystore:=`` names a keystore
    (as the SROS2 tutorials export them; Enforce: a node whose enclave is missing does not start), else none.
    The same rule as server.launch.py and gsrmr_sim/launch_nodes.py (test/system/test_security.py holds them to
    config/security/policy.xml)."""
    keystore = LaunchConfiguration("keystore").perform(context)
    if not keystore:
        return {}
    return {"ros_arguments": ["--enclave", "/gsrmr/" + node_name.removeprefix("gsrmr_")],
            "additional_env": {"ROS_SECURITY_KEYSTORE": os.path.abspath(os.path.expanduser(keystore)),
                               "ROS_SECURITY_ENABLE": "true", "ROS_SECURITY_STRATEGY": "Enforce"}}


def _nodes(context, config: str) -> list[Node]:
    link, base, mount, robot = (os.path.join(config, name)
                                for name in ("link.yaml", "limo_base.yaml", "camera_mount.yaml", "robot.yaml"))
    namespace = LaunchConfiguration("namespace")
    cmd_vel_source = LaunchConfiguration("cmd_vel_source").perform(context)
    return [
        Node(package="gsrmr", executable="gsrmr-limo-base", name="gsrmr_limo_base", namespace=namespace,
             output="screen",
             parameters=[base, {"port": ParameterValue(LaunchConfiguration("port"), value_type=str),
                                "cmd_vel_writers": [cmd_vel_source]}],
             **_security(context, "gsrmr_limo_base")),
        Node(package="gsrmr", executable="gsrmr-robot", name="gsrmr_robot", namespace=namespace, output="screen",
             parameters=[link, mount, robot, {"jpeg_quality": ParameterValue(LaunchConfiguration("jpeg_quality"),
                                                                      value_type=int),
                                              "odom_writers": ["gsrmr_limo_base"],
                                              "localization": ParameterValue(LaunchConfiguration("localization"),
                                                                             value_type=str)}],
             remappings=[("camera/image_raw", LaunchConfiguration("camera_image_topic")),
                         ("camera/camera_info", LaunchConfiguration("camera_info_topic")),
                         ("amcl_pose", LaunchConfiguration("localizer_pose_topic"))],
             **_security(context, "gsrmr_robot")),
    ]


def generate_launch_description() -> LaunchDescription:
    config = os.path.join(get_package_share_directory("gsrmr"), "config")
    return LaunchDescription([
        DeclareLaunchArgument("port", default_value="/dev/ttyTHS1", description="LIMO serial port"),
        DeclareLaunchArgument("camera_image_topic", default_value="/camera/color/image_raw",
                              description="sensor_msgs/Image of the robot camera"),
        DeclareLaunchArgument("camera_info_topic", default_value="/camera/color/camera_info",
                              description="sensor_msgs/CameraInfo of that camera"),
        DeclareLaunchArgument("jpeg_quality", default_value="80", description="JPEG quality of uploaded images"),
        DeclareLaunchArgument("namespace", default_value="", description="ROS namespace of both nodes"),
        DeclareLaunchArgument("keystore", default_value="",
                              description="SROS2 keystore: run enforced, each node in its enclave /gsrmr/<node> "
                                          "('' = off)"),
        DeclareLaunchArgument("cmd_vel_source", default_value="*",
                              description="the node the base takes cmd_vel from (a planner or twist_mux; * = any)"),
        DeclareLaunchArgument("localization", default_value="server", choices=["server", "pose", "tf", "off"],
                              description="map → odom: corrected by the server's localization (server), from "
                                          "another localizer's pose (pose: AMCL, slam_toolbox) or its /tf (tf), or "
                                          "map_from_odom alone (off)"),
        DeclareLaunchArgument("localizer_pose_topic", default_value="amcl_pose",
                              description="with localization:=pose, that localizer's PoseWithCovarianceStamped of "
                                          "base_link in map (slam_toolbox: pose)"),
        OpaqueFunction(function=_nodes, kwargs={"config": config}),
    ])
