"""Foundation test: two node processes, started from their console scripts, talk over DDS.

A topic round trip (ping → pong) and a service call (link/stats) cross process boundaries over
Fast DDS, then both processes exit cleanly on SIGINT within a bounded time.
"""

import json

import pytest

pytestmark = pytest.mark.ros


def test_topic_and_service_between_processes_then_clean_sigint(ros_processes):
    echo = ros_processes.start("gsrmr-link-echo")
    probe = ros_processes.start("gsrmr-link-probe", "--ros-args", "-p", "rate_hz:=50.0")
    # The probe logs the echo's counters once its first service call returns.
    ros_processes.wait_for(probe, "echo stats:", timeout_s=30)
    assert ros_processes.interrupt(probe) < 10.0
    assert probe.returncode == 0
    assert ros_processes.interrupt(echo) < 10.0
    assert echo.returncode == 0
    report = json.loads(ros_processes.output(probe)[0].strip().splitlines()[-1])
    assert report["received"] > 0, report
    assert report["rtt_ms_p50"] is not None and report["rtt_ms_p50"] > 0
    assert report["echo"]["pings_received"] > 0
    assert report["echo"]["pongs_sent"] == report["echo"]["pings_received"]


def test_probe_with_count_reports_and_exits_by_itself(ros_processes):
    echo = ros_processes.start("gsrmr-link-echo")
    probe = ros_processes.start("gsrmr-link-probe", "--ros-args", "-p", "count:=40", "-p", "rate_hz:=100.0",
                                "-p", "settle_s:=0.5")
    probe.wait(timeout=60)
    out, err = ros_processes.output(probe)
    assert probe.returncode == 0, err
    report = json.loads(out.strip().splitlines()[-1])
    assert report["sent"] == 40
    assert report["received"] + report["lost"] == 40
    assert report["received"] >= 38, report  # reliable QoS on loopback
    assert report["echo"]["pings_received"] >= report["received"]
    ros_processes.interrupt(echo)
    assert echo.returncode == 0
