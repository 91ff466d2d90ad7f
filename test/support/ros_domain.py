"""ROS domains for test processes, without pytest: which domain a test's processes use, and clean-up.

Imported by ``conftest.py`` (a pytest session hands out :func:`next_domain_id`, one per test) and by
``launch_support.py``, which a launch test run by plain ``launch_test test/launch/<file>`` imports with no
conftest at all: then :func:`free_domain_id` picks a domain that no DDS participant on this host is
using. Fast DDS (and Cyclone DDS) bind their UDP ports of domain ``d`` in ``7400 + 250 d`` …
``7400 + 250 d + 249`` (RTPS port mapping: PB 7400, DG 250), so a bound port there means "in use".
"""

from __future__ import annotations

from collections.abc import Iterable
import itertools
import os
from pathlib import Path
import random
import signal
import time

DOMAIN_MIN, DOMAIN_MAX = 1, 101  # valid on Linux: the ports of a higher domain reach the ephemeral range
RTPS_PORT_BASE, RTPS_DOMAIN_GAIN = 7400, 250

USED_DOMAINS: set[int] = set()
_domains = itertools.count(random.Random(os.getpid() ^ time.time_ns()).randrange(DOMAIN_MIN, DOMAIN_MAX + 1))
_pytest_session = False


def next_domain_id() -> int:
    """A ROS domain id in 1..101, different for every call in this process (a sequence from a random start)."""
    domain = DOMAIN_MIN + next(_domains) % (DOMAIN_MAX - DOMAIN_MIN + 1)
    USED_DOMAINS.add(domain)
    return domain


def bound_udp_ports() -> set[int]:
    """The local ports of every UDP socket on this host (IPv4 and IPv6), from ``/proc/net/udp{,6}``."""
    ports: set[int] = set()
    for table in (Path("/proc/net/udp"), Path("/proc/net/udp6")):
        try:
            lines = table.read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            if len(fields) > 1 and ":" in fields[1]:
                ports.add(int(fields[1].rsplit(":", 1)[1], 16))
    return ports


def busy_domains(ports: Iterable[int] | None = None) -> set[int]:
    """Domains in 1..101 with a bound UDP port in their RTPS port block (a DDS participant, or a ros2 daemon)."""
    taken = bound_udp_ports() if ports is None else set(ports)
    low, high = RTPS_PORT_BASE + RTPS_DOMAIN_GAIN * DOMAIN_MIN, RTPS_PORT_BASE + RTPS_DOMAIN_GAIN * (DOMAIN_MAX + 1)
    return {(p - RTPS_PORT_BASE) // RTPS_DOMAIN_GAIN for p in taken if low <= p < high}


def free_domain_id(rng: random.Random | None = None) -> int:
    """A random domain in 1..101 that no process on this host uses now and this process has not used
    (free-ish: two runs starting in the same instant may still pick the same one); the next id of the
    sequence when every domain is busy."""
    busy = busy_domains() | USED_DOMAINS
    free = [d for d in range(DOMAIN_MIN, DOMAIN_MAX + 1) if d not in busy]
    if not free:
        return next_domain_id()
    domain = (rng or random.SystemRandom()).choice(free)
    USED_DOMAINS.add(domain)
    return domain


def mark_pytest_session() -> None:
    """Called by ``conftest.py``: a pytest session hands out the domains (:func:`next_domain_id`) and stops
    the ros2 daemons at its end."""
    global _pytest_session
    _pytest_session = True


def in_pytest_session() -> bool:
    """Whether ``conftest.py`` is loaded (pytest, ``colcon test``) rather than a plain ``launch_test``."""
    return _pytest_session


def stop_ros2_daemons(domains: Iterable[int]) -> list[int]:
    """SIGTERM the ros2 CLI daemons (``ros2 topic``/``ros2 node`` start one per domain) of ``domains``;
    the pids signalled."""
    wanted = set(domains)
    stopped: list[int] = []
    for proc in Path("/proc").glob("[0-9]*"):
        try:
            argv = (proc / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if not any(b"ros2cli.daemon.daemonize" in a for a in argv) or b"--ros-domain-id" not in argv:
            continue
        try:
            if int(argv[argv.index(b"--ros-domain-id") + 1]) in wanted:
                os.kill(int(proc.name), signal.SIGTERM)
                stopped.append(int(proc.name))
        except (ValueError, IndexError, OSError):
            continue
    return stopped
