"""Everything on one machine: mock LIMO and camera, route follower, robot, server and scheduler.

ros2 launch gsrmr sim.launch.py model_path:=/path/to/sandbox.ply record_dir:=/tmp/gsrmr_run

The process list is gsrmr_sim.sim_stack's, the one ``make demo`` runs, each process a launch Node by
gsrmr_sim.launch_nodes. Arguments: README.md's launch table; writers, live parameters and ``keystore:=``:
docs/security.md.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration

from gsrmr_sim.launch_nodes import launch_node
from gsrmr_sim.sim_stack import sim_stack


def _nodes(context):
    arg = lambda name: LaunchConfiguration(name).perform(context)  # noqa: E731
    specs = sim_stack(scene=arg("scene"), model_path=arg("model_path"), record_dir=arg("record_dir"),
                      loss_threshold=float(arg("loss_threshold")), laps=int(arg("laps")), method=arg("method"),
                      link_path=arg("serial_link"),
                      # all processes start at once here: the robot sets off once the server composes
                      overrides={"gsrmr_route_follower": {"wait_for_server": True},
                                 # the one-machine playground: the operator may retune the plan live
                                 "gsrmr_scheduler": {"live_parameter_changes": True}})
    # without a keystore the call stays launch_node(spec, namespace): test_launch_files stands in for it so
    keystore = LaunchConfiguration("keystore", default="").perform(context)
    security = {"keystore": keystore} if keystore else {}
    return [launch_node(s, namespace=arg("namespace"), **security) for s in specs]


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription([
        DeclareLaunchArgument("model_path", description="Gaussian-splatting model of the scene (.ply)"),
        DeclareLaunchArgument("scene", default_value="sandbox", description="scene name or YAML path"),
        DeclareLaunchArgument("record_dir", default_value="", description="slots.csv + MCAP ('' = off)"),
        DeclareLaunchArgument("loss_threshold", default_value="0.03", description="average MR-loss budget L_th"),
        DeclareLaunchArgument("method", default_value="exact", description="scheduling method"),
        DeclareLaunchArgument("laps", default_value="1", description="route laps of round 2 (0 = forever)"),
        DeclareLaunchArgument("serial_link", default_value="/tmp/gsrmr_limo",
                              description="pty symlink of the mock LIMO's serial port"),
        DeclareLaunchArgument("namespace", default_value="", description="ROS namespace of every node"),
        DeclareLaunchArgument("keystore", default_value="",
                              description="SROS2 keystore: run enforced, each node in its enclave /gsrmr/<node> "
                                          "('' = off)"),
        OpaqueFunction(function=_nodes),
    ])
