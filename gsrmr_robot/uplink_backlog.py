"""The robot's view of its uplink queue (pure, no ROS): is an image still on its way, how fast does the link carry one.

:class:`UplinkBacklog` turns image publish times, DDS acknowledgements (``Publisher.wait_for_all_acked``) and slot
starts into ``queued`` (hold the next image back) and ``rate_bps`` (the image throughput the link sustains). Why:
``docs/two_hosts.md``, "How the robot and the scheduler notice a slow link"; a reader that is not a known one:
``docs/security.md``, "Services, parameters, readers". Times are monotonic seconds.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
import math


@dataclass
class _Episode:
    """Images published while none was acknowledged, up to the acknowledgement of them all."""

    start_s: float  # publication of the first of them
    end_s: float  # their acknowledgement, or the end of a slot that started with them queued (the later)
    ack_s: float
    bits: int


def busy_s(intervals: list[tuple[float, float]]) -> float:
    """Length (s) of the union of ``(start, end)`` intervals."""
    total, cur_start, cur_end = 0.0, None, None
    for start, end in sorted(intervals):
        if cur_end is None or start > cur_end:
            if cur_end is not None:
                total += cur_end - cur_start
            cur_start, cur_end = start, end
        else:
            cur_end = max(cur_end, end)
    return total if cur_end is None else total + cur_end - cur_start


@dataclass
class UplinkBacklog:
    """Publish/acknowledge bookkeeping of the image uploads.

    ``rate_bps`` is the image bits acknowledged in the last ``window_s`` over the *busy* time: the union of the
    intervals from an image's publication to its acknowledgement and of every slot that started with an image still
    queued, to the next slot start. Images queued back to back, or held back, so measure the share of the link the
    other traffic leaves them; sparse images on a fast link still read fast, and slots the plan gives no image do not
    lower it (a cap taken from it does not ratchet itself down). It does not time each image alone: one image can
    cross at the rate limit's whole rate between the other packets. The times include up to one heartbeat period
    (:mod:`gsrmr_robot.dds_profile`) and the round trip, so ``rate_bps`` is a lower bound of what the link carries.
    An image unacknowledged for ``stale_after_s`` stops holding the next one back and gives no sample (an outage).
    DDS acknowledges all matched readers at once, so with ``acks_trusted`` false (a reader that is not a known one is
    matched) an image counts as delivered after its bits at the last trusted estimate (:meth:`queued`).
    """

    stale_after_s: float = 1.0  # an image unacknowledged this long no longer holds the next one back
    window_s: float = 5.0  # acknowledgements rate_bps is judged on: those of the last window_s
    sent_s: float | None = None  # publish time of the oldest unacknowledged image (None: nothing queued)
    hold_from_s: float | None = None  # publish time of the image the hold-back waits for (sent after a stale one)
    queued_bits: int = 0  # bits published and not yet acknowledged
    last_ack_delay_s: float = math.nan
    acked_images: int = 0
    held_back: int = 0  # images the schedule asked for and the robot did not send (queued)
    acks_trusted: bool = True  # False while a reader that is not a known one is matched: acks then say nothing
    model_deliveries: int = 0  # images taken as delivered by the throughput model (acks not trusted)
    now_s: float = field(default=-math.inf, init=False)  # time of the latest call (sent, acked, queued): rate_bps's now
    _episodes: deque[_Episode] = field(default_factory=deque, init=False, repr=False)  # acknowledged, newest last
    # start of the last slot that began with an image queued (busy until the next slot starts)
    _held_slot_s: float | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        if not self.stale_after_s > 0:
            raise ValueError("stale_after_s must be > 0")
        if not self.window_s > 0:
            raise ValueError("window_s must be > 0")

    def _tell(self, now_s: float) -> None:
        self.now_s = now_s

    def sent(self, bits: int, now_s: float) -> None:
        """An image of ``bits`` was published at ``now_s``."""
        self._tell(now_s)
        if self.sent_s is None:
            self.sent_s = self.hold_from_s = now_s
        elif self.hold_from_s is None or now_s - self.hold_from_s >= self.stale_after_s:
            self.hold_from_s = now_s  # sent past a stale image: this one holds the next back
        self.queued_bits += int(bits)

    def acked(self, now_s: float) -> None:
        """Everything published so far is acknowledged (``wait_for_all_acked`` said so at ``now_s``)."""
        self._tell(now_s)
        if self.sent_s is None:
            return
        delay = max(now_s - self.sent_s, 1e-6)
        if delay < self.stale_after_s:  # longer: the link was down or the reader gone, not slow — no sample
            self._episodes.append(_Episode(self.sent_s, self.sent_s + delay, now_s, self.queued_bits))
            while self._episodes and self._episodes[0].ack_s < now_s - self.window_s:
                self._episodes.popleft()
        self.last_ack_delay_s = delay
        self.acked_images += 1
        self.sent_s, self.hold_from_s, self.queued_bits = None, None, 0

    def _window(self, ref_s: float) -> tuple[int, list[tuple[float, float]]]:
        """Bits and busy intervals of the images acknowledged in the ``window_s`` before ``ref_s``."""
        recent = [e for e in self._episodes if ref_s - self.window_s <= e.ack_s <= ref_s]
        return sum(e.bits for e in recent), [(e.start_s, e.end_s) for e in recent]

    def rate_at(self, now_s: float) -> float:
        """The sustained image throughput (bit/s) at ``now_s``, NaN before any acknowledgement gave a sample: the
        bits acknowledged in the ``window_s`` before the last acknowledgement over their busy time, and, while an
        image has been waiting (trusted acknowledgements), no more than the bits of the last ``window_s`` and the
        waiting ones over their busy time and the wait (the rate were they acknowledged at ``now_s``)."""
        rate = math.nan
        if self._episodes:
            bits, intervals = self._window(self._episodes[-1].ack_s)
            rate = bits / max(busy_s(intervals), 1e-6)
        if self.acks_trusted and self.sent_s is not None and now_s > self.sent_s:
            bits, intervals = self._window(now_s)
            bound = (bits + self.queued_bits) / busy_s([*intervals, (self.sent_s, now_s)])
            if not bound >= rate:  # also when there is no estimate yet (NaN)
                rate = bound
        return rate

    @property
    def rate_bps(self) -> float:
        """:meth:`rate_at` the latest time this was told of (the node asks at a slot's start, after :meth:`queued`)."""
        return self.rate_at(self.now_s)

    @property
    def waiting(self) -> bool:
        """Something was published and is not yet acknowledged (the node polls while this is true)."""
        return self.sent_s is not None

    def queued(self, now_s: float) -> bool:
        """An unacknowledged image younger than ``stale_after_s`` is on its way: hold the next one back (the node
        asks at the start of every slot: a slot that starts so is busy time for ``rate_bps`` until the next asks).
        Without trusted acknowledgements the image is on its way until its bits at ``rate_bps`` have passed (then
        it is taken as delivered: no throughput sample), and nothing is held back without a throughput estimate."""
        self._tell(now_s)
        if self._held_slot_s is not None:  # the last slot started with an image queued: busy to this one's start
            last = self._episodes[-1] if self._episodes else None
            if last is not None and last.ack_s >= self._held_slot_s and now_s - self._held_slot_s <= self.stale_after_s:
                last.end_s = max(last.end_s, now_s)
            self._held_slot_s = None
        if self.sent_s is None:
            return False
        if not self.acks_trusted:
            rate = self.rate_bps
            expected = self.queued_bits / rate if math.isfinite(rate) and rate > 0 else 0.0
            if now_s - self.sent_s >= min(expected, self.stale_after_s):
                self.sent_s, self.hold_from_s, self.queued_bits = None, None, 0
                self.model_deliveries += 1
                return False
            return True
        hold_from = self.sent_s if self.hold_from_s is None else self.hold_from_s
        if now_s - hold_from < self.stale_after_s:
            self._held_slot_s = now_s
            return True
        return False

    def queued_for_s(self, now_s: float) -> float:
        """How long the oldest unacknowledged image has waited (0 when nothing is queued)."""
        return 0.0 if self.sent_s is None else max(0.0, now_s - self.sent_s)
