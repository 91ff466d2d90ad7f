"""The ROS domain helpers of the tests (``ros_domain``): which domains are in use on this host, and a free one.

A launch test run by plain ``launch_test`` (no conftest) isolates itself in :func:`ros_domain.free_domain_id`;
these check that a UDP socket bound in a domain's RTPS port block marks that domain busy and that the free
domain is never a busy one.
"""

from __future__ import annotations

from collections.abc import Iterator
import contextlib
import random
import socket

import pytest
from support.ros_domain import (
    DOMAIN_MAX,
    DOMAIN_MIN,
    RTPS_DOMAIN_GAIN,
    RTPS_PORT_BASE,
    USED_DOMAINS,
    busy_domains,
    free_domain_id,
)

LAST_PORT_OFFSET = RTPS_DOMAIN_GAIN - 1  # the block's last port: a DDS participant would need id 119 to want it


def block_port(domain: int, offset: int = LAST_PORT_OFFSET) -> int:
    """A UDP port in ``domain``'s RTPS port block."""
    return RTPS_PORT_BASE + RTPS_DOMAIN_GAIN * domain + offset


@contextlib.contextmanager
def udp_sockets(ports: list[int]) -> Iterator[list[int]]:
    """Bind a UDP socket on each port that is free (others are skipped); yield the ports bound."""
    socks, bound = [], []
    try:
        for port in ports:
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            try:
                sock.bind(("127.0.0.1", port))
            except OSError:
                sock.close()
                continue
            socks.append(sock)
            bound.append(port)
        yield bound
    finally:
        for sock in socks:
            sock.close()


def test_ports_map_to_their_domain() -> None:
    ports = [block_port(5, 0), block_port(5, 12), block_port(DOMAIN_MAX, LAST_PORT_OFFSET), block_port(0, 10),
             RTPS_PORT_BASE + RTPS_DOMAIN_GAIN * (DOMAIN_MAX + 1), 53, 40_000]
    assert busy_domains(ports) == {5, DOMAIN_MAX}


def test_a_bound_port_makes_its_domain_busy() -> None:
    candidates = sorted(set(range(DOMAIN_MIN, DOMAIN_MAX)) - busy_domains())
    if not candidates:
        pytest.fail("every ROS domain of this host is in use")
    domain = random.choice(candidates)
    with udp_sockets([block_port(domain)]) as bound:
        assert bound == [block_port(domain)]
        assert domain in busy_domains()


def test_the_free_domain_is_the_only_one_nothing_uses() -> None:
    busy = busy_domains() | USED_DOMAINS
    candidates = [d for d in range(DOMAIN_MIN, DOMAIN_MAX + 1) if d not in busy]
    if not candidates:
        pytest.fail("every ROS domain of this host is in use")
    keep = random.choice(candidates)
    others = [block_port(d) for d in range(DOMAIN_MIN, DOMAIN_MAX + 1) if d != keep and d not in busy]
    with udp_sockets(others):
        # a port another process took meanwhile makes its domain busy too: either way only `keep` is free
        assert free_domain_id(random.Random(0)) == keep
