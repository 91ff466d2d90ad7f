"""launch_testing: the installed ``sim.launch.py`` runs the whole loop; the ros2 CLI drives it.

The launch file is included from the ament index (as ``ros2 launch gsrmr sim.launch.py`` finds it),
against the loopback mock camera and mock serial base. While the round runs, the test checks what a
ROS user would: the server composes every slot of the round (its recording, asked for by the
``record_dir`` launch argument, has a row for each), every topic a gsrmr node publishes carries messages, and MR
images reach a subscriber of ``mr/image``
all through the round (no 2 s without one: a subscriber may miss some of a reliable keep-last-5
topic of 0.9 MB images when its own process is starved, as on a loaded CI machine), ``ros2 service call
/gsrmr/replan std_srvs/srv/Trigger`` answering ``success: true`` with what changed, ``ros2 param set``
of an out-of-range value refused with its reason, every node alive at the end of the round, and every
process's exit code 0 when launch stops them with SIGINT.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
import itertools
from pathlib import Path
import sys
import tempfile
import threading
import time
import unittest

# `launch_test test/launch/<file>` loads this file by its path, with no conftest and test/ not on sys.path: put it
# there for the helpers below, test/support/ (under pytest, whose pythonpath is test/, it already is).
if str(Path(__file__).resolve().parents[1]) not in sys.path:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import pytest
from support.launch_support import isolate_this_process, launch_file, require_ros_tooling, ros2_until, sim_process_names

needs_ros_tooling = require_ros_tooling()

import launch  # noqa: E402
from launch.launch_description_sources import PythonLaunchDescriptionSource  # noqa: E402
import launch_testing.actions  # noqa: E402
import launch_testing.asserts  # noqa: E402
from support.stack_harness import make_point_model  # noqa: E402

from gsrmr_server.recording.slots_csv import read_slots_csv  # noqa: E402

SLOT_S = 0.1
# Every topic a gsrmr node publishes in this stack, with its type (README "Use it from ROS 2": `ros2 topic echo`).
GSRMR_TOPICS = {"/uplink/pose_key": "geometry_msgs/msg/Vector3Stamped",
                "/uplink/image_raw/compressed": "sensor_msgs/msg/CompressedImage",
                "/uplink/camera_info": "sensor_msgs/msg/CameraInfo", "/gsrmr/ledger": "std_msgs/msg/Float64MultiArray",
                "/gsrmr/schedule": "std_msgs/msg/Float64MultiArray",
                "/gsrmr/loss_sample": "std_msgs/msg/Float64MultiArray", "/mr/image": "sensor_msgs/msg/Image",
                "/mr/image/compressed": "sensor_msgs/msg/CompressedImage", "/odom": "nav_msgs/msg/Odometry",
                "/imu": "sensor_msgs/msg/Imu", "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
                "/camera/image_raw": "sensor_msgs/msg/Image", "/camera/camera_info": "sensor_msgs/msg/CameraInfo",
                "/cmd_vel": "geometry_msgs/msg/Twist", "/sim/ground_truth/odom": "nav_msgs/msg/Odometry"}
CLI_ECHO_TOPICS = ("/uplink/pose_key", "/gsrmr/schedule", "/mr/image/compressed", "/odom")
ROUND_TIMEOUT_S = 150.0
#: How long after the lap ends the server may take to compose the round's last slot [s].
COMPOSE_GRACE_S = 10.0
MAX_MR_GAP_SLOTS = 20  # the longest run of round slots without an MR image at the probe (2 s)


@needs_ros_tooling
@pytest.mark.launch_test
def generate_test_description():
    isolate_this_process()
    folder = Path(tempfile.mkdtemp(prefix="gsrmr-sim-launch-"))
    model = make_point_model(folder, n=3000)
    sim = launch.actions.IncludeLaunchDescription(
        PythonLaunchDescriptionSource(launch_file("sim.launch.py")),
        launch_arguments={"model_path": str(model), "laps": "1", "record_dir": str(folder / "run"),
                          "serial_link": str(folder / "limo")}.items())
    return launch.LaunchDescription([sim, launch_testing.actions.ReadyToTest()]), {"folder": folder}


class RoundProbe:
    """Subscribes to what the round produces: MR images, the route follower's laps, the true pose."""

    def __init__(self) -> None:
        from nav_msgs.msg import Odometry
        import rclpy
        from rclpy.qos import qos_profile_sensor_data
        from rosidl_runtime_py.utilities import get_message
        from sensor_msgs.msg import Image
        from std_msgs.msg import Int32

        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("sim_launch_probe", context=self.context)
        self.mr_slots: set[int] = set()
        self.heard: set[str] = set()  # GSRMR_TOPICS with a message at the probe
        self.moved_at_s: float | None = None
        self.lap_done_at_s: float | None = None
        self._start_xy: tuple[float, float] | None = None
        self.node.create_subscription(Image, "mr/image", self._on_mr, 50)
        self.node.create_subscription(Int32, "sim/route/lap", self._on_lap, 10)
        self.node.create_subscription(Odometry, "/sim/ground_truth/odom", self._on_truth, qos_profile_sensor_data)
        # best effort and volatile: compatible with every publisher's QoS (reliable, transient local or not)
        for topic, type_name in GSRMR_TOPICS.items():
            if topic == "/mr/image":  # heard by _on_mr
                continue
            self.node.create_subscription(get_message(type_name), topic, lambda _msg, t=topic: self.heard.add(t),
                                          qos_profile_sensor_data)

    def _on_mr(self, msg) -> None:
        stamp_s = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        self.mr_slots.add(round(stamp_s / SLOT_S))
        self.heard.add("/mr/image")

    def _on_lap(self, msg) -> None:
        if msg.data >= 1 and self.lap_done_at_s is None:
            self.lap_done_at_s = time.time()

    def _on_truth(self, msg) -> None:
        xy = (msg.pose.pose.position.x, msg.pose.pose.position.y)
        if self._start_xy is None:
            self._start_xy = xy
        elif self.moved_at_s is None and abs(xy[0] - self._start_xy[0]) + abs(xy[1] - self._start_xy[1]) > 0.01:
            self.moved_at_s = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9

    def spin_until(self, done, timeout_s: float) -> None:
        import rclpy

        executor = rclpy.executors.SingleThreadedExecutor(context=self.context)
        executor.add_node(self.node)
        deadline = time.monotonic() + timeout_s
        while not done() and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.1)
        executor.remove_node(self.node)

    def close(self) -> None:
        self.node.destroy_node()
        self.context.try_shutdown()


def _in_background(*args: str, ok: str) -> tuple[threading.Thread, dict]:
    """Run ``ros2 <args>`` (until its output has ``ok``) in a thread: the probe keeps spinning meanwhile."""
    box: dict = {}

    def run() -> None:
        box["result"] = ros2_until(*args, ok=ok, attempts=8)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread, box


def longest_gap(received: list[int], first: int, last: int) -> int:
    """The longest run of slots in ``first..last`` (inclusive) missing from the sorted ``received``."""
    edges = [first - 1, *received, last + 1]
    return max(b - a - 1 for a, b in itertools.pairwise(edges))


def _composed_through(slots_csv: Path, last: int, grace_s: float) -> set[int]:
    """The slots the server's ``slots.csv`` has, once it reached ``last`` or after ``grace_s``: the server composes
    a slot after its end (at the key's or image's arrival, or at its deadline), so the round's last slot may land
    after the probe saw the lap end (clean-clone run 38: the last of 291 round slots was not in the file yet)."""
    deadline = time.monotonic() + grace_s
    while True:
        composed = {row["slot"] for row in read_slots_csv(slots_csv)} if slots_csv.exists() else set()
        if (composed and max(composed) >= last) or time.monotonic() > deadline:
            return composed
        time.sleep(0.2)


class TestSimLaunch(unittest.TestCase):
    def test_round_with_cli(self, proc_info, folder):
        probe = RoundProbe()
        try:
            probe.spin_until(lambda: len(probe.mr_slots) > 0, 90.0)
            self.assertTrue(probe.mr_slots, "no MR image on mr/image within 90 s of launch")
            replan, replan_box = _in_background("service", "call", "/gsrmr/replan", "std_srvs/srv/Trigger",
                                                  ok="response:")
            refuse, refuse_box = _in_background("param", "set", "--no-daemon", "/gsrmr_scheduler", "loss_threshold",
                                                "-1.0", ok="Setting parameter")
            probe.spin_until(lambda: probe.lap_done_at_s is not None, ROUND_TIMEOUT_S)
            probe.spin_until(lambda: probe.heard >= set(GSRMR_TOPICS), 10.0)
            replan.join(60)
            refuse.join(60)
            # every process still running at the end of the round (none died, not even with code 0)
            exited = {name: proc_info[name].returncode for name in proc_info.process_names()
                      if getattr(proc_info[name], "returncode", None) is not None}
            self.assertEqual(exited, {}, "processes that ended during the round")
            self.assertEqual(len(proc_info.process_names()), len(sim_process_names()))
        finally:
            probe.close()
        self.assertIsNotNone(probe.moved_at_s, "the robot never moved")
        self.assertEqual(sorted(set(GSRMR_TOPICS) - probe.heard), [], "topics with no message during the round")
        self.assertIsNotNone(probe.lap_done_at_s, f"the route lap did not complete within {ROUND_TIMEOUT_S} s")
        first = int(probe.moved_at_s / SLOT_S) + 1
        last = int(probe.lap_done_at_s / SLOT_S) - 1
        round_slots = set(range(first, last + 1))
        got = len(round_slots & probe.mr_slots)
        composed = _composed_through(folder / "run" / "slots.csv", last, COMPOSE_GRACE_S)
        gap = longest_gap(sorted(round_slots & probe.mr_slots), first, last)
        print(f"sim.launch.py round: {len(round_slots)} round slots, {len(round_slots & composed)} composed "
              f"(server's slots.csv), MR images for {got} at the probe "
              f"({100.0 * got / max(1, len(round_slots)):.1f} %), longest gap {gap} slots", flush=True)
        self.assertGreater(len(round_slots), 200, "round implausibly short")
        self.assertEqual(sorted(round_slots - composed), [], "round slots the server did not compose")
        self.assertLessEqual(gap, MAX_MR_GAP_SLOTS, f"MR images for {got} of {len(round_slots)} round slots")
        reply = replan_box["result"]
        self.assertIn("success=True", reply.stdout, reply.stdout + reply.stderr)
        self.assertRegex(reply.stdout, r"message='method=exact .*changed_slots=\d+; .*(switched|no slot changed)",
                         reply.stdout)
        refused = refuse_box["result"]
        said = refused.stdout + refused.stderr
        self.assertIn("Setting parameter failed", said)
        self.assertRegex(said, r"loss_threshold out of range Min: 0\.0, Max: 1\.0, value: -1\.0", said)
        # the recording the launch argument asked for exists and covers the round
        self.assertTrue((folder / "run" / "slots.csv").is_file())




class TestSimLaunchCli(unittest.TestCase):
    """After the round (the stack keeps running): the CLI commands of the README, as typed there."""

    def test_ros2_cli_after_the_round(self, proc_info):
        # The commands up to the `param set` below are independent of each other: each is a CLI process that mostly
        # waits (interpreter start, discovery, a message), so they run 3 at once (one after the other: 15-20 s).
        calls = {"executables": (("pkg", "executables", "gsrmr"), {"ok": "gsrmr-server"}),
                 "nodes": (("node", "list", "--no-daemon"), {"ok": "gsrmr_scheduler"})}
        # The round's probe heard every topic; `ros2 topic echo` (README "Use it from ROS 2") on one topic of each
        # side, before a higher L_th (below) lets the scheduler plan no image at all once the robot stands. (Each
        # echo is a new CLI process: all 15 topics took 25-45 s of the suite.)
        calls.update({topic: (("topic", "echo", "--once", "--no-arr", topic), {"ok": "---", "attempts": 3,
                                                                               "timeout_s": 25.0})
                      for topic in CLI_ECHO_TOPICS})
        with ThreadPoolExecutor(max_workers=3) as pool:  # 3 at once: the stack keeps composing on the same 2 cores
            futures = {key: pool.submit(ros2_until, *args, **kwargs) for key, (args, kwargs) in calls.items()}
            done = {key: future.result() for key, future in futures.items()}
        executables = done["executables"].stdout
        for exe in ("gsrmr-robot", "gsrmr-server", "gsrmr-scheduler", "gsrmr-limo-base", "gsrmr-demo"):
            self.assertIn(f"gsrmr {exe}", executables)
        nodes = done["nodes"].stdout
        self.assertIn("/gsrmr_scheduler", nodes)
        for topic in CLI_ECHO_TOPICS:
            echo = done[topic]
            self.assertIn("---", echo.stdout, f"ros2 topic echo --once {topic}: {echo.stdout[-500:]}{echo.stderr}")
        # `1` is an INTEGER to the CLI: the DOUBLE parameter takes it as 1.0 (gsrmr_common.ros_node.declare), where
        # rclpy alone answers "Wrong parameter type"
        set_ok = ros2_until("param", "set", "--no-daemon", "/gsrmr_scheduler", "loss_threshold", "1",
                            ok="Set parameter successful")
        self.assertIn("Set parameter successful", set_ok.stdout, set_ok.stdout + set_ok.stderr)
        got = ros2_until("param", "get", "--no-daemon", "/gsrmr_scheduler", "loss_threshold", ok="value is")
        self.assertEqual(got.stdout.strip(), "Double value is: 1.0")
        exited = [n for n in proc_info.process_names() if getattr(proc_info[n], "returncode", None) is not None]
        self.assertEqual(exited, [], "a node died")


@launch_testing.post_shutdown_test()
class TestSimLaunchExit(unittest.TestCase):
    def test_every_process_exits_zero_on_sigint(self, proc_info):
        launch_testing.asserts.assertExitCodes(proc_info)
        self.assertGreaterEqual(len(proc_info.process_names()), len(sim_process_names()))
