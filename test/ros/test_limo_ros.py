"""gsrmr-mock-limo and gsrmr-limo-base as real processes; cmd_vel from this process moves odom."""

from __future__ import annotations

import math
import time

import pytest

pytestmark = pytest.mark.ros


def test_cmd_vel_moves_odom_diagnostics_and_ground_truth_then_clean_sigint(ros_processes, tmp_path, monkeypatch):
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import Twist
    from nav_msgs.msg import Odometry
    from rcl_interfaces.srv import SetParameters
    import rclpy
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import Imu

    link = str(tmp_path / "limo")
    mock = ros_processes.start("gsrmr-mock-limo", "--link", link, "--cmd-timeout-s", "0.3")
    ros_processes.wait_for(mock, "mock LIMO ready", timeout_s=20)
    base = ros_processes.start("gsrmr-limo-base", "--ros-args", "-p", f"port:={link}", "-p",
                               "heading_source:=gyro_integration",
                               "-p", "live_parameter_changes:=true")  # issue 28: off unless started on
    ros_processes.wait_for(base, "link up", timeout_s=20)

    for key in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE"):
        monkeypatch.setenv(key, ros_processes.env[key])
    monkeypatch.delenv("ROS_LOCALHOST_ONLY", raising=False)
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        node = rclpy.create_node("test_limo_ros", context=ctx)
        got: dict[str, list] = {"odom": [], "diag": [], "truth": [], "imu": []}
        node.create_subscription(Odometry, "odom", got["odom"].append, 10)
        node.create_subscription(DiagnosticArray, "/diagnostics", got["diag"].append, 10)
        node.create_subscription(Odometry, "/sim/ground_truth/odom", got["truth"].append, 10)
        node.create_subscription(Imu, "imu", got["imu"].append, 10)
        pub = node.create_publisher(Twist, "cmd_vel", 10)
        executor = rclpy.executors.SingleThreadedExecutor(context=ctx)
        executor.add_node(node)

        def spin_for(seconds: float, cmd: Twist | None = None) -> None:
            end = time.monotonic() + seconds
            next_pub = 0.0
            while time.monotonic() < end:
                if cmd is not None and time.monotonic() >= next_pub:
                    pub.publish(cmd)
                    next_pub = time.monotonic() + 0.05
                executor.spin_once(timeout_sec=0.01)

        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and (pub.get_subscription_count() == 0 or not got["odom"]):
            spin_for(0.1)
        assert got["odom"], "no odom from gsrmr-limo-base"
        cmd = Twist()
        cmd.linear.x, cmd.angular.z = 0.3, 0.2
        spin_for(2.0, cmd)
        spin_for(1.5)  # cmd_vel stops → base stops after cmd_timeout_s
        odom, truth = got["odom"][-1], got["truth"][-1]
        assert odom.header.frame_id == "odom" and odom.child_frame_id == "base_link"
        assert truth.header.frame_id == "map" and truth.child_frame_id == "base_link"
        assert odom.pose.pose.position.x > 0.3
        assert odom.twist.twist.linear.x == 0.0  # stopped again
        assert odom.pose.covariance[0] > 0 and odom.pose.covariance[35] > 0 and odom.twist.covariance[0] > 0
        # odometry and the mock's true pose agree (both start at the origin)
        assert odom.pose.pose.position.x == pytest.approx(truth.pose.pose.position.x, abs=0.02)
        assert odom.pose.pose.position.y == pytest.approx(truth.pose.pose.position.y, abs=0.02)
        yaw = 2 * math.atan2(odom.pose.pose.orientation.z, odom.pose.pose.orientation.w)
        yaw_true = 2 * math.atan2(truth.pose.pose.orientation.z, truth.pose.pose.orientation.w)
        assert yaw == pytest.approx(yaw_true, abs=0.02) and yaw > 0.2
        assert got["imu"] and got["imu"][-1].header.frame_id == "imu_link"
        assert got["diag"], "no /diagnostics"
        values = {kv.key: kv.value for kv in got["diag"][-1].status[0].values}
        assert values["battery_voltage_v"] == "12.3"
        assert values["control_mode"] == "commanded" and values["motion_mode"] == "diff"
        assert values["link_connected"] == "True" and values["errors"] == "none"
        assert int(values["parser_frames_ok"]) > 100
        # string parameters are validated; read-only ones are refused
        client = node.create_client(SetParameters, "/gsrmr_limo_base/set_parameters")
        assert client.wait_for_service(timeout_sec=10.0)

        def set_param(name: str, value: str) -> bool:
            req = SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()])
            future = client.call_async(req)
            end = time.monotonic() + 10.0
            while not future.done() and time.monotonic() < end:
                executor.spin_once(timeout_sec=0.05)
            return future.result().results[0].successful

        assert not set_param("motion_mode", "tank")
        assert not set_param("heading_source", "compass")
        assert not set_param("port", "/dev/ttyUSB0")
        assert set_param("motion_mode", "diff")
        assert set_param("heading_source", "imu")
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)

    assert ros_processes.interrupt(base) < 10.0
    assert base.returncode == 0, ros_processes.output(base)
    assert ros_processes.interrupt(mock) < 10.0
    assert mock.returncode == 0, ros_processes.output(mock)
    assert "mock LIMO stopped" in ros_processes.output(mock)[0]
    for proc in (base, mock):
        assert "Traceback" not in "".join(ros_processes.output(proc))


def test_port_removed_and_restored_during_motion_node_keeps_driving(ros_processes, tmp_path, monkeypatch):
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import Twist
    from nav_msgs.msg import Odometry
    import rclpy

    link = str(tmp_path / "limo")
    # the mock closes its port (the link path disappears) 4 s after start, for 0.5 s, every 4 s
    mock = ros_processes.start("gsrmr-mock-limo", "--link", link, "--reopen-every-s", "4.0", "--reopen-gap-s", "0.5")
    ros_processes.wait_for(mock, "mock LIMO ready", timeout_s=20)
    base = ros_processes.start("gsrmr-limo-base", "--ros-args", "-p", f"port:={link}", "-p",
                               "diagnostics_period_s:=0.2")
    for key in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE"):
        monkeypatch.setenv(key, ros_processes.env[key])
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        node = rclpy.create_node("test_limo_reconnect", context=ctx)
        diag: list = []
        truth: list = []
        node.create_subscription(DiagnosticArray, "/diagnostics", diag.append, 10)
        node.create_subscription(Odometry, "/sim/ground_truth/odom", truth.append, 10)
        pub = node.create_publisher(Twist, "cmd_vel", 10)
        executor = rclpy.executors.SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        cmd = Twist()
        cmd.linear.x = 0.2

        def drive(seconds: float, until=None) -> None:
            end = time.monotonic() + seconds
            next_pub = 0.0
            while time.monotonic() < end and not (until and until()):
                if time.monotonic() >= next_pub:
                    pub.publish(cmd)
                    next_pub = time.monotonic() + 0.05
                executor.spin_once(timeout_sec=0.01)

        def values() -> dict[str, str]:
            return {kv.key: kv.value for kv in diag[-1].status[0].values} if diag else {}

        def count(key: str) -> int:
            return int(values().get(key, "0"))

        drive(20.0, until=lambda: count("disconnects") >= 1 and truth)
        assert count("disconnects") >= 1, "the node never saw the port disappear"
        drive(10.0, until=lambda: count("connects") >= 2 and values().get("link_connected") == "True")
        assert count("connects") >= 2
        x_back = truth[-1].pose.pose.position.x
        drive(1.0)
        assert truth[-1].pose.pose.position.x > x_back + 0.1  # driving resumed, same node process
        assert base.poll() is None
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)
    out, err = ros_processes.output(base)
    assert "link lost" in err + out and "connection #2" in err + out
    assert ros_processes.interrupt(base) < 10.0 and base.returncode == 0
    assert ros_processes.interrupt(mock) < 10.0 and mock.returncode == 0
