"""The ``ros2 launch`` command itself, run as a user runs it in a terminal, stopped by Ctrl-C.

Each test starts ``ros2 launch gsrmr <file>`` in its own session and sends SIGINT to that session's
process group, as a terminal's Ctrl-C does (every process gets it, then launch forwards its own). The
exit code of every process is read from the launch log: all must be 0.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
import os
from pathlib import Path
import re
import shutil
import subprocess
import time
import xml.etree.ElementTree as ET

import pytest
from support.launch_support import (
    DOMAIN_NOTE,
    exit_codes_from_launch_log,
    isolate_this_process,
    require_ros_tooling,
    ros2,
    ros2_until,
    sim_process_names,
    start_ros2_launch,
)
from support.ros_domain import DOMAIN_MAX, DOMAIN_MIN

pytestmark = require_ros_tooling()

from support.stack_harness import make_point_model  # noqa: E402

from gsrmr_common.wire import JPEG_FORMAT  # noqa: E402

PACKAGE_ROOT = Path(__file__).resolve().parents[2]  # where a ROS user types `launch_test test/launch/<file>`
NUMPY_CORE_LIBRARY = "_multiarray_umath"  # numpy's core extension: mapped only once the start-up guard is in


@pytest.mark.ros
@pytest.mark.slow
def test_ros2_launch_sim_ctrl_c_every_process_exits_zero(tmp_path):
    isolate_this_process()
    model = make_point_model(tmp_path, n=2000)
    run = start_ros2_launch(tmp_path, "gsrmr", "sim.launch.py", f"model_path:={model}", "laps:=0",
                            f"serial_link:={tmp_path / 'limo'}")
    try:
        # every process up and in its loop: the robot set off, and the scorer (at nice 19, the last) is ready
        for line in ("robot moving: round clock started", "scorer: model"):
            assert run.wait_for(line, 120.0), run.output()[-4000:]
        time.sleep(3.0)  # a few slots of the running loop
        rc = run.ctrl_c()
    finally:
        if run.proc.poll() is None:
            run.kill()
    codes = exit_codes_from_launch_log(run.launch_log())
    assert len(codes) == len(sim_process_names()), codes
    assert all(code == 0 for code in codes.values()), f"exit codes after Ctrl-C: {codes}\n{run.output()[-3000:]}"
    assert rc == 0, f"ros2 launch exit code {rc}"
    assert ros2("node", "list", "--no-daemon").stdout.strip() == "", "nodes left running after Ctrl-C"


class UplinkProbe:
    """Counts what the robot node uploads (pose keys, JPEG images) in the test's ROS domain."""

    def __init__(self) -> None:
        from geometry_msgs.msg import Vector3Stamped
        import rclpy
        from sensor_msgs.msg import CompressedImage

        from gsrmr_robot.robot_node import UPLINK_QOS

        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("robot_launch_probe", context=self.context)
        self.keys = 0
        self.images: list[str] = []
        self.node.create_subscription(Vector3Stamped, "uplink/pose_key", self._on_key, UPLINK_QOS)
        self.node.create_subscription(CompressedImage, "uplink/image_raw/compressed",
                                      lambda m: self.images.append(m.format), UPLINK_QOS)
        self.executor = rclpy.executors.SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def _on_key(self, _msg) -> None:
        self.keys += 1

    def spin_until(self, done, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while not done() and time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.05)

    def close(self) -> None:
        self.executor.remove_node(self.node)
        self.node.destroy_node()
        self.context.try_shutdown()


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.parametrize("stop_after_s", [0.0, 5.0, 60.0], ids=["start-up", "linking", "running"])
def test_ros2_launch_robot_ctrl_c(ros_processes, tmp_path, stop_after_s):
    """robot.launch.py against the mock LIMO on a pty and a camera remapped by launch arguments.

    Start-up: Ctrl-C the moment both nodes are loading their modules (numpy's core mapped: it loads after the
    package's ``__init__`` installed the start-up guard, before rclpy). A Ctrl-C landing earlier, in the
    interpreter's own start-up (site, the console script's wrapper), ends any Python program by SIGINT before
    a line of it runs — exit code -2, as for every rclpy node; the clock of ``ros2 launch`` cannot tell the
    two apart on a loaded machine, so the test waits for the mapping instead of a fixed time.
    Running: Ctrl-C once the robot uploaded more than 50 pose keys and an image (at most ``stop_after_s``)."""
    link = tmp_path / "limo"
    ros_processes.start("gsrmr-mock-limo", "--link", str(link), "--no-ros")
    ros_processes.start("gsrmr-mock-camera", "--ros-args", "-r", "camera/image_raw:=/test_cam/image_raw",
                        "-r", "camera/camera_info:=/test_cam/camera_info")
    probe = None
    if stop_after_s >= 20.0:
        os.environ.update({k: ros_processes.env[k] for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")})
        probe = UplinkProbe()
    run = start_ros2_launch(tmp_path, "gsrmr", "robot.launch.py", f"port:={link}",
                            "camera_image_topic:=/test_cam/image_raw", "camera_info_topic:=/test_cam/camera_info",
                            env=ros_processes.env)
    try:
        if probe is not None:
            probe.spin_until(lambda: probe.keys > 50 and bool(probe.images), stop_after_s)
        elif stop_after_s == 0.0:
            assert run.wait_until_loading(2, NUMPY_CORE_LIBRARY, 120.0), run.output()[-3000:]
        else:
            time.sleep(stop_after_s)
        rc = run.ctrl_c()
    finally:
        if probe is not None:
            probe.close()
        if run.proc.poll() is None:
            run.kill()
    text = run.launch_log()
    codes = exit_codes_from_launch_log(text)
    assert all(code == 0 for code in codes.values()), \
        f"exit codes after Ctrl-C at {stop_after_s} s: {codes}\n{text}\n{run.output()[-6000:]}"
    assert rc == 0, f"ros2 launch exit code {rc}"
    if stop_after_s >= 20.0:
        assert len(codes) == 2, codes
        assert "LIMO link up on" in run.output(), run.output()[-3000:]
        assert probe.keys > 50, f"{probe.keys} pose keys uploaded in {stop_after_s} s"
        assert probe.images and set(probe.images) == {JPEG_FORMAT}, probe.images[:5]


@pytest.mark.ros
def test_launch_test_command_runs_the_link_check(tmp_path):
    """``launch_test test/launch/test_link_check_launch.py`` typed in the package root, as a ROS user runs a launch
    test: no pytest and no conftest, so the file must import its helpers by itself, and the helper picks a free ROS
    domain of its own and says which. Every test of the file (active and post-shutdown) must pass."""
    exe = shutil.which("launch_test")
    assert exe is not None, "launch_test is not on PATH (launch_testing installs it)"
    junit = tmp_path / "launch_test.xml"
    result = subprocess.run([exe, "test/launch/test_link_check_launch.py", "--junit-xml", str(junit)],
                            capture_output=True, text=True, timeout=180, cwd=PACKAGE_ROOT,
                            env=dict(os.environ, ROS_LOG_DIR=str(tmp_path / "log"), PYTHONUNBUFFERED="1"))
    said = result.stdout + result.stderr
    assert result.returncode == 0, said[-3000:]
    picked = re.search(re.escape(DOMAIN_NOTE) + r"(\d+) ", said)
    assert picked is not None and DOMAIN_MIN <= int(picked.group(1)) <= DOMAIN_MAX, said[-3000:]
    cases = ET.parse(junit).getroot().findall(".//testcase")
    assert {"test_probe_reports_every_ping_answered", "test_exit_codes"} <= {c.get("name") for c in cases}, said[-3000:]
    bad = [c.get("name") for c in cases if any(c.find(tag) is not None for tag in ("failure", "error", "skipped"))]
    assert bad == [], f"{bad}:\n{said[-3000:]}"


@pytest.mark.ros
@pytest.mark.slow
def test_ros2_launch_server_arguments_and_ctrl_c(tmp_path):
    """``ros2 launch gsrmr server.launch.py`` with the README's arguments; Ctrl-C ends both nodes with 0."""
    isolate_this_process()
    model = make_point_model(tmp_path, n=1000)
    run = start_ros2_launch(tmp_path, "gsrmr", "server.launch.py", f"model_path:={model}", "loss_threshold:=0.035",
                            "mr_content:=sandbox", "method:=exact", f"record_dir:={tmp_path / 'record'}",
                            "localization:=false")
    try:
        # four independent CLI calls at once (each mostly waits: interpreter start, discovery of its node)
        with ThreadPoolExecutor(max_workers=4) as pool:
            showing = pool.submit(ros2, "launch", "gsrmr", "server.launch.py", "--show-args")
            threshold = pool.submit(ros2_until, "param", "get", "--no-daemon", "/gsrmr_scheduler", "loss_threshold",
                                    ok="value is", attempts=20)
            model_path = pool.submit(ros2_until, "param", "get", "--no-daemon", "/gsrmr_server", "model_path",
                                     ok="value is", attempts=20)
            localization = pool.submit(ros2_until, "param", "get", "--no-daemon", "/gsrmr_server", "localization",
                                       ok="value is", attempts=20)
        shown = showing.result()
        for name in ("model_path", "mr_content", "route_file", "loss_threshold", "method", "record_dir", "namespace"):
            assert f"'{name}'" in shown.stdout, shown.stdout
        got = threshold.result()
        assert got.stdout.strip() == "Double value is: 0.035", got.stdout + got.stderr
        got = model_path.result()
        assert got.stdout.strip() == f"String value is: {model}", got.stdout + got.stderr
        got = localization.result()
        assert got.stdout.strip() == "Boolean value is: False", got.stdout + got.stderr
        rc = run.ctrl_c()
    finally:
        if run.proc.poll() is None:
            run.kill()
    codes = exit_codes_from_launch_log(run.launch_log())
    assert len(codes) == 2 and all(code == 0 for code in codes.values()), f"{codes}\n{run.output()[-3000:]}"
    assert rc == 0


def test_every_launch_file_shows_its_arguments():
    """``ros2 launch gsrmr <file> --show-args`` (README) lists each file's arguments."""
    expected = {"sim.launch.py": ("model_path", "scene", "record_dir", "loss_threshold", "method", "laps",
                                  "serial_link", "namespace"),
                "robot.launch.py": ("port", "camera_image_topic", "camera_info_topic", "jpeg_quality", "namespace",
                                    "localization"),
                "server.launch.py": ("model_path", "loss_map_file", "localization", "record_dir")}
    with ThreadPoolExecutor(max_workers=len(expected)) as pool:  # independent CLI calls: at once
        shows = dict(zip(expected, pool.map(lambda name: ros2("launch", "gsrmr", name, "--show-args"), expected),
                         strict=True))
    for name, args in expected.items():
        shown = shows[name]
        assert shown.returncode == 0, shown.stderr
        for arg in args:
            assert f"'{arg}'" in shown.stdout, (name, arg, shown.stdout)
