"""Changes of the two-host link during a round (``gsrmr-demo --hosts 2 --link-events``, docs/two_hosts.md).

A :class:`LinkEvent` takes the link down or up or changes its uplink rate once the round has composed ``at_slot``
slots (the runner, :mod:`gsrmr_sim.stack_runner`, applies it); :func:`parse_link_events` reads ``ACTION@SLOT``.
"""

from __future__ import annotations

from dataclasses import dataclass

from gsrmr_sim.netns import TwoHosts

LINK_ACTIONS = ("down", "up", "rate")


@dataclass(frozen=True)
class LinkEvent:
    """A change of the two-host link once the round has composed ``at_slot`` slots: ``down`` (link down),
    ``up`` (link back up) or ``rate`` (``mbit`` Mbit/s on the uplink)."""

    at_slot: int
    action: str
    mbit: float = 0.0

    def apply(self, net: TwoHosts) -> None:
        """Apply to the two hosts' link."""
        if self.action in ("down", "up"):
            net.set_link(self.action == "up")
        elif self.action == "rate":
            net.set_rate(self.mbit)
        else:
            raise ValueError(f"unknown link action {self.action!r}")

    def describe(self) -> str:
        """``link down``, ``link up`` or ``rate 1.5 Mbit/s`` (the runner's log)."""
        return f"rate {self.mbit:g} Mbit/s" if self.action == "rate" else f"link {self.action}"

    def as_dict(self) -> dict:
        """The event as the report's ``link_events`` list has it."""
        rate = {"mbit": self.mbit} if self.action == "rate" else {}
        return {"at_slot": self.at_slot, "action": self.action, **rate}


def parse_link_events(text: str) -> list[LinkEvent]:
    """``"down@100,up@120,rate=1.5@150"`` → link events at round slots 100, 120 and 150."""
    events = []
    for item in filter(None, (t.strip() for t in text.split(","))):
        what, _, at = item.partition("@")
        if not at.isdigit():
            raise ValueError(f"link event {item!r}: expected ACTION@SLOT")
        action, _, mbit = what.partition("=")
        if action not in LINK_ACTIONS or (action == "rate") != bool(mbit):
            raise ValueError(f"link event {item!r}: ACTION is down, up or rate=MBIT")
        events.append(LinkEvent(int(at), action, float(mbit) if mbit else 0.0))
    return events
