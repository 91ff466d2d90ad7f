"""A fleet on one machine: N simulated robots, each with its own server, scheduler and simulated world.

ros2 launch gsrmr fleet.launch.py robots:=3 model_path:=/path/to/sandbox.ply record_dir:=/tmp/gsrmr_fleet

Robot k runs in namespace /robot<k> (its MR stream on /robot<k>/mr/image). The process list is
gsrmr_sim.sim_stack.fleet_stack, the one ``gsrmr-demo --robots N`` runs (docs/world.md, "A fleet"); arguments:
README.md's launch table.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration

from gsrmr_sim.launch_nodes import launch_node
from gsrmr_sim.sim_stack import fleet_stack


def _nodes(context):
    arg = lambda name: LaunchConfiguration(name).perform(context)  # noqa: E731
    seed = arg("channel_seed")
    specs = fleet_stack(robots=int(arg("robots")), scene=arg("scene"), model_path=arg("model_path"),
                        record_dir=arg("record_dir"), loss_threshold=float(arg("loss_threshold")),
                        laps=int(arg("laps")), method=arg("method"), link_path=arg("serial_link"),
                        channel_seed=int(seed) if seed else None)
    return [launch_node(s) for s in specs]


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription([
        DeclareLaunchArgument("robots", default_value="2", description="number of robots N (/robot1 … /robotN)"),
        DeclareLaunchArgument("model_path", description="Gaussian-splatting model of the scene (.ply)"),
        DeclareLaunchArgument("scene", default_value="sandbox", description="scene name or YAML path"),
        DeclareLaunchArgument("record_dir", default_value="",
                              description="slots.csv + MCAP of robot k in record_dir/robot<k> ('' = off)"),
        DeclareLaunchArgument("loss_threshold", default_value="0.03", description="average MR-loss budget L_th"),
        DeclareLaunchArgument("method", default_value="exact", description="scheduling method"),
        DeclareLaunchArgument("laps", default_value="1", description="route laps of round 2 (0 = forever)"),
        DeclareLaunchArgument("serial_link", default_value="/tmp/gsrmr_limo",
                              description="pty symlink prefix of the mock LIMOs' serial ports (+ _robot<k>)"),
        DeclareLaunchArgument("channel_seed", default_value="",
                              description="channel seed of robot 1, robot k gets seed + k - 1 "
                                          "('' = config/link.yaml's)"),
        OpaqueFunction(function=_nodes),
    ])
