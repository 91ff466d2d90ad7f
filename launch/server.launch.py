"""On the workstation: MR composition server + online scheduler.

ros2 launch gsrmr server.launch.py model_path:=/path/to/sandbox.ply loss_threshold:=0.03 \
    loss_map_file:=/path/to/loss_map.json

The render intrinsics come from the robot's ``uplink/camera_info`` (latched); the camera's mount from
config/camera_mount.yaml (the robot loads the same file). Parameters: config/link.yaml (shared uplink
model), config/camera_mount.yaml, config/server.yaml, config/scheduler.yaml and the route file
(``route_file:=``, default config/routes/sandbox.yaml) — every file keyed ``/**``, so the launch
arguments below (passed after them) always win, also under ``namespace:=…``. ``loss_map_file:=`` seeds the
scheduler's loss map (its ``loss_map_file`` parameter): the JSON ``gsrmr-survey MODEL DATASET --out FILE`` writes
from the mapping round (docs/scheduling.md).
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue


def _arg(name: str, value_type: type) -> ParameterValue:
    return ParameterValue(LaunchConfiguration(name), value_type=value_type)


def generate_launch_description() -> LaunchDescription:
    config = os.path.join(get_package_share_directory("gsrmr"), "config")
    link, mount, server, scheduler = (os.path.join(config, n) for n in ("link.yaml", "camera_mount.yaml", "server.yaml",
                                                                       "scheduler.yaml"))
    sandbox_route = os.path.join(config, "routes", "sandbox.yaml")
    namespace = LaunchConfiguration("namespace")
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
        DeclareLaunchArgument("record_dir", default_value="", description="slots.csv + MCAP ('' = off)"),
        DeclareLaunchArgument("namespace", default_value="", description="ROS namespace of both nodes"),
        Node(package="gsrmr", executable="gsrmr-server", name="gsrmr_server", namespace=namespace, output="screen",
             parameters=[link, mount, server, {"model_path": _arg("model_path", str),
                                               "mr_content": _arg("mr_content", str),
                                        "record_dir": _arg("record_dir", str)}]),
        Node(package="gsrmr", executable="gsrmr-scheduler", name="gsrmr_scheduler", namespace=namespace,
             output="screen",
             parameters=[link, scheduler, LaunchConfiguration("route_file"),
                         {"method": _arg("method", str), "loss_threshold": _arg("loss_threshold", float),
                          "loss_map_file": _arg("loss_map_file", str)}]),
    ])
