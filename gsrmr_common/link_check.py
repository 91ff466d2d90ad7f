"""DDS link check between the robot and the workstation: round-trip latency, loss and a service call.

Run ``gsrmr-link-echo`` on the server and ``gsrmr-link-probe`` on the robot: the first thing to run when ROS 2
discovery between a LIMO and a workstation misbehaves. Topics, service and parameters: :data:`ECHO_INTERFACE`,
:data:`PROBE_INTERFACE` (what ``--help`` prints); a ping's ``frame_id`` is its sequence number as decimal text.
"""

from __future__ import annotations

from dataclasses import dataclass
import json
import sys
import time

import numpy as np
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import Header
from std_srvs.srv import Trigger

from gsrmr_common.interrupts import console_main
from gsrmr_common.node_help import Endpoint, NodeInterface, ParameterGroup
from gsrmr_common.node_params import NodeParameters, ros_parameter
from gsrmr_common.ros_node import declare_parameters, run_node

LINK_QOS = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)


@dataclass(frozen=True)
class LinkProbeParameters(NodeParameters):
    """The probe's parameters."""

    rate_hz: float = ros_parameter(20.0, "Ping rate [Hz]", min_value=0.1, max_value=1000.0)
    count: int = ros_parameter(0, "Pings to send before reporting and exiting (0 = run until Ctrl-C)", min_value=0,
                               max_value=10_000_000)
    settle_s: float = ros_parameter(1.0, "Wait after the last ping for late pongs [s]", min_value=0.0,
                                    max_value=60.0)


_PING = Endpoint("link/ping", "std_msgs/msg/Header", "stamp = send time, frame_id = sequence number")
_PONG = Endpoint("link/pong", "std_msgs/msg/Header", "the ping returned unchanged")
_STATS = Endpoint("link/stats", "std_srvs/srv/Trigger", 'JSON {"node", "pings_received", "pongs_sent"}')
#: What ``gsrmr-link-echo --help`` prints.
ECHO_INTERFACE = NodeInterface(
    executable="gsrmr-link-echo", node="gsrmr_link_echo",
    summary="The DDS link check's echo (run it on the workstation): returns every ping.",
    subscribes=(_PING,), publishes=(_PONG,), services=(_STATS,))
#: What ``gsrmr-link-probe --help`` prints.
PROBE_INTERFACE = NodeInterface(
    executable="gsrmr-link-probe", node="gsrmr_link_probe",
    summary="The DDS link check's probe (run it on the robot): sends numbered pings to gsrmr-link-echo and prints "
            "one JSON report of round-trip times, lost pings and the echo's counters.",
    subscribes=(_PONG,), publishes=(_PING,), parameters=(ParameterGroup(LinkProbeParameters),))


class LinkEcho(Node):
    """Returns every ping on ``link/pong`` and reports its counters on ``link/stats``."""

    def __init__(self) -> None:
        super().__init__("gsrmr_link_echo")
        self.pings_received = 0
        self.pongs_sent = 0
        self._pub = self.create_publisher(Header, "link/pong", LINK_QOS)
        self.create_subscription(Header, "link/ping", self._on_ping, LINK_QOS)
        self.create_service(Trigger, "link/stats", self._on_stats)
        self.get_logger().info("echoing link/ping on link/pong; stats on link/stats")

    def _on_ping(self, msg: Header) -> None:
        self.pings_received += 1
        self._pub.publish(msg)
        self.pongs_sent += 1

    def _on_stats(self, _request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success = True
        response.message = json.dumps({"node": self.get_fully_qualified_name(),
                                       "pings_received": self.pings_received,
                                       "pongs_sent": self.pongs_sent})
        return response


class LinkProbe(Node):
    """Sends pings at ``rate_hz``; after ``count`` pings (0 = until Ctrl-C) prints one JSON report."""

    def __init__(self) -> None:
        super().__init__("gsrmr_link_probe")
        params = declare_parameters(self, LinkProbeParameters)
        self.rate_hz, self.count, self.settle_s = params.rate_hz, params.count, params.settle_s
        self._sent: dict[int, float] = {}
        self.rtt_s: list[float] = []
        self.echo_stats: dict | None = None
        self._seq = 0
        self._done_at: float | None = None
        self._stats_future = None
        self._pub = self.create_publisher(Header, "link/ping", LINK_QOS)
        self.create_subscription(Header, "link/pong", self._on_pong, LINK_QOS)
        self._client = self.create_client(Trigger, "link/stats")
        self._timer = self.create_timer(1.0 / self.rate_hz, self._tick)

    def _tick(self) -> None:
        if self.count and self._seq >= self.count:
            self._finish_when_settled()
            return
        if self._pub.get_subscription_count() == 0:
            return  # no echo discovered yet: do not count pings that nobody can hear
        now = time.monotonic()
        msg = Header(frame_id=str(self._seq))
        msg.stamp = self.get_clock().now().to_msg()
        self._sent[self._seq] = now
        self._pub.publish(msg)
        self._seq += 1
        if self._seq % max(1, int(self.rate_hz)) == 0 and self._client.service_is_ready():
            self._request_stats()

    def _on_pong(self, msg: Header) -> None:
        try:
            seq = int(msg.frame_id)
        except ValueError:
            return
        sent = self._sent.pop(seq, None)
        if sent is not None:
            self.rtt_s.append(time.monotonic() - sent)

    def _request_stats(self) -> None:
        if self._stats_future is not None and not self._stats_future.done():
            return
        self._stats_future = self._client.call_async(Trigger.Request())
        self._stats_future.add_done_callback(self._on_stats)

    def _on_stats(self, future) -> None:
        result = future.result()
        if result is not None and result.success:
            if self.echo_stats is None:
                self.get_logger().info(f"echo stats: {result.message}")
            self.echo_stats = json.loads(result.message)

    def _finish_when_settled(self) -> None:
        now = time.monotonic()
        if self._done_at is None:
            self._done_at = now
            self._request_stats()
        if now - self._done_at >= self.settle_s and self.echo_stats is not None:
            print(json.dumps(self.report()), flush=True)
            self._timer.cancel()
            raise SystemExit(0)

    def report(self) -> dict:
        """Round-trip statistics so far (milliseconds) and the echo's counters."""
        rtt_ms = np.asarray(self.rtt_s) * 1e3
        pct = (lambda q: round(float(np.percentile(rtt_ms, q)), 3)) if rtt_ms.size else (lambda q: None)
        return {"sent": self._seq, "received": len(self.rtt_s), "lost": self._seq - len(self.rtt_s),
                "rtt_ms_p50": pct(50), "rtt_ms_p95": pct(95), "rtt_ms_max": pct(100),
                "echo": self.echo_stats}

    def on_shutdown(self) -> None:
        if not (self.count and self._done_at is not None):
            print(json.dumps(self.report()), flush=True)


@console_main
def echo_main(args: list[str] | None = None) -> int:
    """Console script ``gsrmr-link-echo``."""
    return run_node(LinkEcho, args, interface=ECHO_INTERFACE)


@console_main
def probe_main(args: list[str] | None = None) -> int:
    """Console script ``gsrmr-link-probe``."""
    try:
        return run_node(LinkProbe, args, interface=PROBE_INTERFACE)
    except SystemExit as done:
        return int(done.code or 0)


if __name__ == "__main__":
    sys.exit(probe_main())
