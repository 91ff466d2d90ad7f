"""Two simulated hosts on one machine: network namespaces joined by a veth pair with a rate-limited uplink.

What :class:`TwoHosts` creates, the DDS settings inside and why: docs/two_hosts.md, "What runs where". Everything
it creates is removed by :meth:`TwoHosts.close` (also when creation fails half-way; a context manager). The kernel
here has no ``netem``: rate limits and link up/down only, no delay or loss. Needs root and iproute2
(:func:`unavailable_reason`).
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
import os
from pathlib import Path
import random
import re
import shutil
import signal
import subprocess
import time

from gsrmr_sim.supervisor import OWN_PROCESS_GROUP

NETNS_PREFIX = "gsrmr"


def unavailable_reason() -> str | None:
    """Why namespaces cannot be made here (not root, no ``ip`` or ``tc``), or None."""
    if os.geteuid() != 0:
        return "needs root (network namespaces and veth pairs)"
    for tool in ("ip", "tc"):
        if shutil.which(tool) is None:
            return f"needs iproute2's `{tool}`"
    return None


def _run(*argv: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(list(argv), capture_output=True, text=True, check=check, timeout=20)


def namespaces() -> list[str]:
    """Names of the network namespaces that exist now."""
    out = _run("ip", "netns", "list", check=False).stdout
    return [line.split()[0] for line in out.splitlines() if line.strip()]


@dataclass
class TwoHosts:
    """A robot and a server namespace joined by a rate-limited veth pair (see the module docstring)."""

    uplink_mbit: float = 5.0  # robot → server rate limit (tbf), Mbit/s
    domain_id: int = 0  # ROS_DOMAIN_ID of the processes started here
    tag: str = field(default_factory=lambda: f"{os.getpid() % 100000}{random.randrange(100)}")
    robot_ns: str = field(init=False)
    server_ns: str = field(init=False)
    robot_if: str = field(init=False)
    server_if: str = field(init=False)
    robot_ip: str = field(init=False)
    server_ip: str = field(init=False)
    _procs: list[subprocess.Popen] = field(default_factory=list, init=False, repr=False)
    _made: list[str] = field(default_factory=list, init=False, repr=False)

    def __post_init__(self) -> None:
        if not self.uplink_mbit > 0:
            raise ValueError("uplink_mbit must be > 0")
        self.robot_ns, self.server_ns = f"{NETNS_PREFIX}{self.tag}r", f"{NETNS_PREFIX}{self.tag}s"
        self.robot_if, self.server_if = f"gr{self.tag}"[:15], f"gs{self.tag}"[:15]
        block = random.Random(self.tag).randrange(0, 16384)  # a /30 of 10.231.0.0/16
        base = 4 * block
        self.robot_ip = f"10.231.{base // 256}.{base % 256 + 1}"
        self.server_ip = f"10.231.{base // 256}.{base % 256 + 2}"

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> TwoHosts:
        """Create the namespaces, the link and its limit; on any failure remove what was made and raise."""
        reason = unavailable_reason()
        if reason:
            raise RuntimeError(reason)
        try:
            for ns in (self.robot_ns, self.server_ns):
                _run("ip", "netns", "add", ns)
                self._made.append(ns)
            _run("ip", "link", "add", self.robot_if, "netns", self.robot_ns, "type", "veth", "peer", "name",
                 self.server_if, "netns", self.server_ns)
            for ns, ifname, ip in ((self.robot_ns, self.robot_if, self.robot_ip),
                                   (self.server_ns, self.server_if, self.server_ip)):
                self.ns_run(ns, "ip", "link", "set", "lo", "up")
                self.ns_run(ns, "ip", "addr", "add", f"{ip}/30", "dev", ifname)
                self.ns_run(ns, "ip", "link", "set", ifname, "up")
                self.ns_run(ns, "ip", "route", "add", "224.0.0.0/4", "dev", ifname)
            self.set_rate(self.uplink_mbit)
        except BaseException:
            self.close()
            raise
        return self

    def close(self) -> None:
        """Stop the processes started here (SIGINT, then SIGKILL) and delete the namespaces (their veth
        ends go with them). Safe to call twice."""
        for p in self._procs:
            if p.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGINT)
        deadline = time.monotonic() + 5.0
        for p in self._procs:
            try:
                p.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGKILL)
                p.wait(timeout=5)
        self._procs.clear()
        for ns in reversed(self._made):
            _run("ip", "netns", "delete", ns, check=False)
        self._made.clear()

    def __enter__(self) -> TwoHosts:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ use
    def ns_run(self, ns: str, *argv: str, check: bool = True) -> subprocess.CompletedProcess:
        """Run a short command inside namespace ``ns``."""
        return _run("ip", "netns", "exec", ns, *argv, check=check)

    def environment(self, base: dict[str, str] | None = None) -> dict[str, str]:
        """The environment of a ROS process in one of the hosts: DDS over UDPv4 across the link."""
        env = dict(os.environ if base is None else base)
        env.update(ROS_DOMAIN_ID=str(self.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET",
                   FASTDDS_BUILTIN_TRANSPORTS="UDPv4", RMW_IMPLEMENTATION="rmw_fastrtps_cpp")
        env.pop("ROS_STATIC_PEERS", None)
        return env

    def popen(self, host: str, argv: list[str], *, log: Path | None = None,
              env: dict[str, str] | None = None) -> subprocess.Popen:
        """Start ``argv`` in the ``robot`` or ``server`` host (own process group; stopped by :meth:`close`)."""
        ns = {"robot": self.robot_ns, "server": self.server_ns}[host]
        out = open(log, "w") if log is not None else subprocess.DEVNULL  # noqa: SIM115 - owned by the process
        p = subprocess.Popen(["ip", "netns", "exec", ns, *argv], env=self.environment(env), stdout=out,
                             stderr=subprocess.STDOUT, **OWN_PROCESS_GROUP)
        self._procs.append(p)
        return p

    def link_bytes(self) -> dict[str, float]:
        """Bytes the link carried so far: ``uplink`` (robot → server) and ``downlink``, from the veth counters,
        ``uplink_dropped`` (packets the rate limiter dropped) and ``wall_s``, when they were read (seconds since
        the epoch)."""
        def read(ns: str, ifname: str, what: str) -> int:
            return int(self.ns_run(ns, "cat", f"/sys/class/net/{ifname}/statistics/{what}").stdout.strip())

        return {"uplink": read(self.robot_ns, self.robot_if, "tx_bytes"),
                "downlink": read(self.server_ns, self.server_if, "tx_bytes"),
                "uplink_dropped": self.queue_stats()["dropped"], "wall_s": time.time()}

    def queue_stats(self) -> dict[str, int]:
        """The uplink's rate limiter (tbf on the robot's veth end), cumulative since the link was made:
        ``sent_bytes``, ``dropped`` packets (its queue overflowed: more than 400 ms of traffic waiting) and
        ``backlog_bytes`` queued right now."""
        text = self.ns_run(self.robot_ns, "tc", "-s", "qdisc", "show", "dev", self.robot_if).stdout
        sent = re.search(r"Sent (\d+) bytes", text)
        dropped = re.search(r"dropped (\d+)", text)
        backlog = re.search(r"backlog (\d+)([KM]?)b", text)
        scale = {"": 1, "K": 1000, "M": 1_000_000}
        return {"sent_bytes": int(sent.group(1)) if sent else 0, "dropped": int(dropped.group(1)) if dropped else 0,
                "backlog_bytes": int(backlog.group(1)) * scale[backlog.group(2)] if backlog else 0}

    def set_rate(self, mbit: float) -> None:
        """Limit the robot → server direction to ``mbit`` Mbit/s (tbf: 32 kbit burst, 400 ms queue)."""
        if not mbit > 0:
            raise ValueError("mbit must be > 0")
        self.ns_run(self.robot_ns, "tc", "qdisc", "replace", "dev", self.robot_if, "root", "tbf", "rate",
                    f"{mbit:g}mbit", "burst", "32kbit", "latency", "400ms")
        self.uplink_mbit = float(mbit)

    def set_link(self, up: bool) -> None:
        """Take the link down (both ends) or bring it back up."""
        state = "up" if up else "down"
        self.ns_run(self.robot_ns, "ip", "link", "set", self.robot_if, state)
        self.ns_run(self.server_ns, "ip", "link", "set", self.server_if, state)
        if up:  # routes through a downed device are dropped: restore the multicast route
            for ns, ifname in ((self.robot_ns, self.robot_if), (self.server_ns, self.server_if)):
                self.ns_run(ns, "ip", "route", "replace", "224.0.0.0/4", "dev", ifname)
