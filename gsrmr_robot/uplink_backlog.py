"""The robot's view of its uplink queue (pure, no ROS): is an image still on its way, how fast does the link carry one.

DDS gives the robot one honest signal about the link: a reliable writer knows when every matched reader has
acknowledged what it published (``Publisher.wait_for_all_acked``). The robot node publishes each image and then
polls that every few milliseconds; :class:`UplinkBacklog` turns the publish and acknowledgement times into

* ``queued`` — an image (or part of one) is still unacknowledged: bits are queued somewhere between the
  robot's DDS writer and the server (the rate limit's queue, retransmissions after a loss, a link that is
  down). In a slot where the schedule asks for an image while one is queued, the robot *holds the image
  back* and sends the key only: on a link that carries less than one image per slot, images then go out as
  fast as the link delivers them instead of piling up and all arriving late (ledger ``held_back`` = 1);
* ``rate_bps`` — the link's throughput as the robot sees it: image bits / (acknowledgement − publish time),
  smoothed (an acknowledgement later than ``stale_after_s`` gives no sample: that was an outage, and the rate
  after it is what it was). The time includes up to one heartbeat period (50 ms with the uplink DDS profile,
  :mod:`gsrmr_robot.dds_profile`) and the round trip, so it is a lower bound of the rate limit.

A queued image that stays unacknowledged for ``stale_after_s`` no longer holds images back (its reader may
be gone, or acknowledgements may not be configured to come promptly): the robot then sends again, at most one
image per ``stale_after_s`` into a link that does not answer. Times are monotonic seconds.

DDS acknowledges *all* matched readers at once (``wait_for_all_acked`` has no per-reader form in rclpy), so a
reliable reader that never acknowledges — any participant can subscribe the image topic — would hold every image
back. The node therefore trusts the acknowledgements only while every matched reader is a known one (its
``image_readers``); with another reader matched (``acks_trusted`` false) an image counts as delivered after its
bits at the last trusted throughput estimate (``rate_bps``), none held back without an estimate.
"""

from __future__ import annotations

from dataclasses import dataclass
import math


@dataclass
class UplinkBacklog:
    """Publish/acknowledge bookkeeping of the image uploads (see the module docstring)."""

    stale_after_s: float = 1.0  # an image unacknowledged this long no longer holds the next one back
    smoothing: float = 0.3  # weight of a new throughput sample in rate_bps
    sent_s: float | None = None  # publish time of the oldest unacknowledged image (None: nothing queued)
    queued_bits: int = 0  # bits published and not yet acknowledged
    rate_bps: float = math.nan  # smoothed throughput of acknowledged images, bit/s
    last_ack_delay_s: float = math.nan
    acked_images: int = 0
    held_back: int = 0  # images the schedule asked for and the robot did not send (queued)
    acks_trusted: bool = True  # False while a reader that is not a known one is matched: acks then say nothing
    model_deliveries: int = 0  # images taken as delivered by the throughput model (acks not trusted)

    def __post_init__(self) -> None:
        if not self.stale_after_s > 0:
            raise ValueError("stale_after_s must be > 0")
        if not 0 < self.smoothing <= 1:
            raise ValueError("smoothing must be in (0, 1]")

    def sent(self, bits: int, now_s: float) -> None:
        """An image of ``bits`` was published at ``now_s``."""
        if self.sent_s is None:
            self.sent_s = now_s
        self.queued_bits += int(bits)

    def acked(self, now_s: float) -> None:
        """Everything published so far is acknowledged (``wait_for_all_acked`` said so at ``now_s``)."""
        if self.sent_s is None:
            return
        delay = max(now_s - self.sent_s, 1e-6)
        if delay < self.stale_after_s:  # longer: the link was down or the reader gone, not slow — no sample
            sample = self.queued_bits / delay
            self.rate_bps = sample if math.isnan(self.rate_bps) else \
                (1 - self.smoothing) * self.rate_bps + self.smoothing * sample
        self.last_ack_delay_s = delay
        self.acked_images += 1
        self.sent_s, self.queued_bits = None, 0

    @property
    def waiting(self) -> bool:
        """Something was published and is not yet acknowledged (the node polls while this is true)."""
        return self.sent_s is not None

    def queued(self, now_s: float) -> bool:
        """An unacknowledged image younger than ``stale_after_s`` is on its way: hold the next one back. Without
        trusted acknowledgements the image is on its way until its bits at ``rate_bps`` have passed (then it is
        taken as delivered: no throughput sample), and nothing is held back without a throughput estimate."""
        if self.sent_s is None:
            return False
        age = now_s - self.sent_s
        if not self.acks_trusted:
            expected = self.queued_bits / self.rate_bps if math.isfinite(self.rate_bps) and self.rate_bps > 0 \
                else 0.0
            if age >= min(expected, self.stale_after_s):
                self.sent_s, self.queued_bits = None, 0
                self.model_deliveries += 1
                return False
            return True
        return age < self.stale_after_s

    def queued_for_s(self, now_s: float) -> float:
        """How long the oldest unacknowledged image has waited (0 when nothing is queued)."""
        return 0.0 if self.sent_s is None else max(0.0, now_s - self.sent_s)
