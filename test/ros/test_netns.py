"""Two simulated hosts (gsrmr_sim.netns): DDS across a rate-limited veth pair, and nothing left behind.

Runs only as root with iproute2 (the namespaces, veth pair and tbf are real); skipped otherwise.
"""

from __future__ import annotations

from pathlib import Path
import subprocess
import sys
import time

import pytest

from gsrmr_sim.netns import TwoHosts, namespaces, unavailable_reason

pytestmark = [pytest.mark.ros, pytest.mark.slow,
              pytest.mark.skipif(unavailable_reason() is not None, reason=str(unavailable_reason()))]

PUB = """
import sys, time, rclpy
from std_msgs.msg import UInt8MultiArray
rclpy.init(); n = rclpy.create_node('netns_pub'); pub = n.create_publisher(UInt8MultiArray, 'blob', 10)
msg = UInt8MultiArray(data=bytes(8000))
end = time.monotonic() + float(sys.argv[1])
while time.monotonic() < end:
    pub.publish(msg); rclpy.spin_once(n, timeout_sec=0.1)
"""

SUB = """
import sys, rclpy
from std_msgs.msg import UInt8MultiArray
rclpy.init(); n = rclpy.create_node('netns_sub'); got = [0]
def cb(m):
    got[0] += 1
    open(sys.argv[1], 'w').write(str(got[0]))
n.create_subscription(UInt8MultiArray, 'blob', cb, 10)
rclpy.spin(n)
"""


def _received(path: Path) -> int:
    try:
        return int(path.read_text() or 0)
    except (OSError, ValueError):
        return 0


def test_dds_crosses_the_rate_limited_link_and_everything_is_removed(tmp_path):
    from conftest import next_domain_id

    before = set(namespaces())
    hosts = TwoHosts(uplink_mbit=2.0, domain_id=next_domain_id())
    with hosts:
        assert {hosts.robot_ns, hosts.server_ns} <= set(namespaces())
        # the server's route to the robot is the veth (each namespace has only its loopback and its veth end)
        assert hosts.server_if in hosts.ns_run(hosts.server_ns, "ip", "route", "get", hosts.robot_ip).stdout
        count = tmp_path / "count"
        start = hosts.link_bytes()
        hosts.popen("server", [sys.executable, "-c", SUB, str(count)], log=tmp_path / "sub.log")
        time.sleep(1.0)
        pub = hosts.popen("robot", [sys.executable, "-c", PUB, "8"], log=tmp_path / "pub.log")
        pub.wait(timeout=60)
        time.sleep(1.0)
        got = _received(count)
        moved = hosts.link_bytes()
        # 8 kB at 10 Hz for 8 s (discovery takes the first second or two): most of the 80 arrive, and the
        # bytes crossed the veth (not /dev/shm): at least what the delivered messages weigh
        assert got >= 40, (tmp_path / "sub.log").read_text()
        assert moved["uplink"] - start["uplink"] >= got * 8000
        hosts.set_link(False)
        assert "state DOWN" in hosts.ns_run(hosts.robot_ns, "ip", "link", "show", hosts.robot_if).stdout
        hosts.set_link(True)
        hosts.set_rate(1.0)
        assert "rate 1Mbit" in hosts.ns_run(hosts.robot_ns, "tc", "qdisc", "show", "dev", hosts.robot_if).stdout
    assert set(namespaces()) == before  # namespaces (and their veth ends) removed
    assert hosts.robot_if not in subprocess.run(["ip", "link"], capture_output=True, text=True).stdout
    assert not any(p.poll() is None for p in hosts._procs)


def test_a_failed_setup_removes_what_it_made():
    before = set(namespaces())
    hosts = TwoHosts(uplink_mbit=2.0)
    hosts.server_if = "x" * 20  # an interface name the kernel refuses (> 15 characters): veth creation fails
    with pytest.raises(subprocess.CalledProcessError):
        hosts.open()
    assert set(namespaces()) == before
