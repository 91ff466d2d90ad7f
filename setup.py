"""ament_python setup for the gsrmr ROS 2 package (also `pip install -e .` outside ROS)."""

from glob import glob
import os

from setuptools import find_packages, setup

PACKAGE = "gsrmr"


def config_files() -> list[tuple[str, list[str]]]:
    """config/**/*.yaml and *.xml (the SROS2 policy), installed under share/gsrmr/config keeping the sub-folders."""
    groups: dict[str, list[str]] = {}
    for path in sorted(glob("config/**/*.yaml", recursive=True) + glob("config/**/*.xml", recursive=True)):
        groups.setdefault(os.path.dirname(path), []).append(path)
    return [(os.path.join("share", PACKAGE, folder), files) for folder, files in groups.items()]


# Every node and CLI: `ros2 run gsrmr <name>` (colcon build / a ROS install), `.venv/bin/<name>` here. Each points
# at its module's main; a node's main is decorated with gsrmr_common.interrupts.console_main (exit code 0 on Ctrl-C
# in any phase, also while the module loads: docs/architecture.md "Console scripts").
CONSOLE_SCRIPTS = [
    # foundation: DDS link check between the robot and the workstation
    "gsrmr-link-echo = gsrmr_common.link_check:echo_main",
    "gsrmr-link-probe = gsrmr_common.link_check:probe_main",
    # scheduler (GSCLO): library CLI
    "gsrmr-schedule = gsrmr_scheduler.cli:main",
    # Gaussian-splatting engine
    "gsrmr-train = gsrmr_splat.train_cli:train_main",
    "gsrmr-render = gsrmr_splat.cli:render_main",
    "gsrmr-compact = gsrmr_splat.train_cli:compact_main",
    "gsrmr-align = gsrmr_splat.align_cli:main",
    # a robot's recorded bag → a nerfstudio dataset in map (deployment tool, no ROS runtime)
    "gsrmr-dataset = gsrmr_offline.dataset_tool:main",
    # LIMO base: driver node and byte-exact mock base
    "gsrmr-limo-base = gsrmr_robot.limo.node:main",
    "gsrmr-mock-limo = gsrmr_sim.limo.mock_ros:main",
    # simulated world: headless recorder, mock camera node, route follower node
    "gsrmr-sim = gsrmr_sim.world.cli:main",
    "gsrmr-mock-camera = gsrmr_sim.world.camera_node:main",
    "gsrmr-route-follower = gsrmr_sim.world.route_follower:main",
    "gsrmr-sim-channel = gsrmr_sim.world.channel_node:main",
    "gsrmr-sim-scorer = gsrmr_sim.world.scorer_node:main",
    # node suite, experiments and the main job
    "gsrmr-robot = gsrmr_robot.robot_node:main",
    "gsrmr-server = gsrmr_server.server_node:main",
    "gsrmr-scheduler = gsrmr_scheduler.scheduler_node:main",
    "gsrmr-survey = gsrmr_offline.survey_cli:main",
    "gsrmr-update = gsrmr_offline.update_cli:main",
    "gsrmr-localize = gsrmr_offline.localize_cli:main",
    "gsrmr-experiments = gsrmr_sim.experiments.cli:main",
    "gsrmr-demo = gsrmr_sim.demo:main",
    "gsrmr-uplink-relay = gsrmr_sim.fault_relay_node:main",
    # after a run: tables from recorded gsrmr-demo reports (README "Reading recorded runs")
    "gsrmr-regret-split = gsrmr_sim.analysis.regret_split:main",
    "gsrmr-key-estimates = gsrmr_sim.analysis.key_estimates:main",
    "gsrmr-planner-replay = gsrmr_sim.analysis.planner_replay:main",
    "gsrmr-planner-tail = gsrmr_sim.analysis.planner_tail:main",
    "gsrmr-plausibility-replay = gsrmr_sim.analysis.plausibility_replay:main",
]


def data_files() -> list[tuple[str, list[str]]]:
    """What `colcon build` / `pip install` put under share/: index marker, package.xml, launch, config."""
    return [
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/launch", sorted(glob("launch/*.launch.py"))),
        *config_files(),
    ]


if __name__ == "__main__":
    os.chdir(os.path.dirname(os.path.abspath(__file__)))
    setup(
        name=PACKAGE,
        version="0.1.0",
        packages=find_packages(exclude=["test", "test.*", "bench", "bench.*"]),
        package_data={"": ["*.yaml", "*.json"]},
        data_files=data_files(),
        install_requires=["setuptools"],
        extras_require={"test": ["pytest"]},  # colcon test runs pytest when "test" names it
        zip_safe=True,
        maintainer="gsrmr developers",
        maintainer_email="gsrmr@example.com",
        description="Green robotic mixed reality with Gaussian splatting (ROS 2)",
        license="Apache-2.0",
        entry_points={"console_scripts": CONSOLE_SCRIPTS},
    )
