"""Everything on one machine: mock LIMO and camera, route follower, robot, server and scheduler.

ros2 launch gsrmr sim.launch.py model_path:=/path/to/sandbox.ply record_dir:=/tmp/gsrmr_run
The process list comes from gsrmr_server.sim_stack, the same definition `make demo` runs.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from gsrmr_server.sim_stack import nice_prefix, sim_stack


def _nodes(context):
    arg = lambda name: LaunchConfiguration(name).perform(context)  # noqa: E731
    specs = sim_stack(scene=arg("scene"), model_path=arg("model_path"), record_dir=arg("record_dir"),
                      loss_threshold=float(arg("loss_threshold")), laps=int(arg("laps")))
    return [Node(package="gsrmr", executable=s.executable, name=s.name, output="screen",
                 arguments=s.arguments, parameters=[*s.param_files, s.params] if s.params else s.param_files,
                 remappings=s.remappings, prefix=" ".join(nice_prefix(s)) or None)
            for s in specs]


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription([
        DeclareLaunchArgument("model_path", description="Gaussian-splatting model of the scene (.ply)"),
        DeclareLaunchArgument("scene", default_value="sandbox"),
        DeclareLaunchArgument("record_dir", default_value=""),
        DeclareLaunchArgument("loss_threshold", default_value="0.03"),
        DeclareLaunchArgument("laps", default_value="1"),
        OpaqueFunction(function=_nodes),
    ])
