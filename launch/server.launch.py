"""On the workstation: MR composition server + online scheduler.

ros2 launch gsrmr server.launch.py model_path:=/path/to/sandbox.ply loss_map_file:=/path/to/loss_map.json

Parameters: config/link.yaml, config/camera_mount.yaml (also the robot's), config/server.yaml,
config/scheduler.yaml and the route file, keyed ``/**``, then the launch arguments (README.md's launch table),
which win. The render intrinsics come from the robot's latched ``uplink/camera_info``; the seed loss map is
``gsrmr-survey``'s (docs/hardware.md); ``keystore:=``: docs/security.md.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue


def _arg(name: str, value_type: type) -> ParameterValue:
    return ParameterValue(LaunchConfiguration(name), value_type=value_type)


def _security(context, node_name: str) -> dict:
    """The Node arguments that run ``node_name`` enforced in its enclave when ``keystore:=`` names a keystore
    (as the SROS2 tutorials export them; Enforce: a node whose enclave is missing does not start), else none.
    The same rule as robot.launch.py and gsrmr_sim/launch_nodes.py (test/system/test_security.py holds them to
    config/security/policy.xml)."""
    keystore = LaunchConfiguration("keystore").perform(context)
    if not keystore:
        return {}
    return {"ros_arguments": ["--enclave", "/gsrmr/" + node_name.removeprefix("gsrmr_")],
            "additional_env": {"ROS_SECURITY_KEYSTORE": os.path.abspath(os.path.expanduser(keystore)),
                               "ROS_SECURITY_ENABLE": "true", "ROS_SECURITY_STRATEGY": "Enforce"}}


def _nodes(context, config: str) -> list[Node]:
    link, mount, server, scheduler = (os.path.join(config, n) for n in ("link.yaml", "camera_mount.yaml", "server.yaml",
                                                                       "scheduler.yaml"))
    namespace = LaunchConfiguration("namespace")
    return [
        Node(package="gsrmr", executable="gsrmr-server", name="gsrmr_server", namespace=namespace, output="screen",
             parameters=[link, mount, server, {"model_path": _arg("model_path", str),
                                               "mr_content": _arg("mr_content", str),
                                               "record_dir": _arg("record_dir", str),
                                               "localization": _arg("localization", bool)}],
             **_security(context, "gsrmr_server")),
        Node(package="gsrmr", executable="gsrmr-scheduler", name="gsrmr_scheduler", namespace=namespace,
             output="screen",
             parameters=[link, scheduler, LaunchConfiguration("route_file"),
                         {"method": _arg("method", str), "loss_threshold": _arg("loss_threshold", float),
                          "loss_map_file": _arg("loss_map_file", str)}],
             **_security(context, "gsrmr_scheduler")),
    ]


def generate_launch_description() -> LaunchDescription:
    config = os.path.join(get_package_share_directory("gsrmr"), "config")
    sandbox_route = os.path.join(config, "routes", "sandbox.yaml")
    return LaunchDescription([
        DeclareLaunchArgument("model_path", description="Gaussian-splatting model (.ply, 3DGS layout)"),
        DeclareLaunchArgument("mr_content", default_value="sandbox",
                              description="MR content: virtual agents (config/mr/<name>.yaml or a path)"),
        DeclareLaunchArgument("route_file", default_value=sandbox_route,
                              description="the robot's route as scheduler parameters (config/routes/*.yaml)"),
        DeclareLaunchArgument("loss_threshold", default_value="0.03", description="average MR-loss budget L_th"),
        DeclareLaunchArgument("method", default_value="exact", description="scheduling method"),
        DeclareLaunchArgument("loss_map_file", default_value="",
                              description="the scheduler's seed loss map: gsrmr-survey's JSON ('' = none)"),
        DeclareLaunchArgument("localization", default_value="true", choices=["true", "false"],
                              description="localize the robot from its images and publish gsrmr/map_correction"),
        DeclareLaunchArgument("record_dir", default_value="", description="slots.csv + MCAP ('' = off)"),
        DeclareLaunchArgument("namespace", default_value="", description="ROS namespace of both nodes"),
        DeclareLaunchArgument("keystore", default_value="",
                              description="SROS2 keystore: run enforced, each node in its enclave /gsrmr/<node> "
                                          "('' = off)"),
        OpaqueFunction(function=_nodes, kwargs={"config": config}),
    ])
