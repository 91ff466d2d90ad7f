"""The robot node's inputs from the workstation and the radio, after their plausibility rules: the schedules and
the channel gains per slot (pure, no ROS; the rules: :mod:`gsrmr_common.plausibility`,
:mod:`gsrmr_common.channel_band`)."""

from __future__ import annotations

from gsrmr_common.channel_band import GainBand
from gsrmr_common.link_model import LinkBudget
from gsrmr_common.plausibility import Implausible, ScheduleLimits, schedule_problem
from gsrmr_common.wire import ChannelSample, ScheduleMsg
from gsrmr_common.writer_admission import SeqTracker
from gsrmr_robot.uplink_core import covering_schedule

#: Channel gains kept: the newest slots (pruned to half when more arrive).
GAINS_KEPT = 64
#: What :meth:`ScheduleInbox.offer` returns for a schedule delivered again (a latched one): nothing new, no lie.
REPEAT = "repeat"


class ScheduleInbox:
    """The newest plausible schedule and the one before it (for the slots the newest starts after)."""

    def __init__(self, slot_s: float, limits: ScheduleLimits, implausible: Implausible) -> None:
        self.slot_s = slot_s
        self.limits = limits
        self.implausible = implausible
        self.newest: ScheduleMsg | None = None
        self.before: ScheduleMsg | None = None
        self._seq = SeqTracker()

    def offer(self, sched: ScheduleMsg, writer_gid: bytes, now_slot: int) -> str | None:
        """A parsed schedule from an admitted writer endpoint. Returns:
            None when it is taken; :data:`REPEAT` for the same ``seq`` again from that endpoint; else why it is
            refused (counted): ``schedule_slot_s`` (another τ), a :func:`schedule_problem` reason (T, slots,
            powers) or ``schedule_seq`` (not newer than the endpoint's last).
        """
        if abs(sched.slot_s - self.slot_s) > 1e-9:
            reason: str | None = "schedule_slot_s"
        else:
            reason = schedule_problem(sched, now_slot, self.limits)
        if reason is None:
            seq = self._seq.check(writer_gid, sched.seq)
            if seq == REPEAT:
                return REPEAT
            reason = "schedule_seq" if seq == "older" else None
        if reason:
            self.implausible[reason] += 1
            return reason
        self.newest, self.before = sched, self.newest
        return None

    def covering(self, slot: int) -> ScheduleMsg | None:
        """The schedule that decides ``slot`` (:func:`~gsrmr_robot.uplink_core.covering_schedule`)."""
        return covering_schedule(slot, self.newest, self.before)


class ChannelGains:
    """The radio's measured gain per slot, each inside the Rician band around the path-loss prediction at the robot's
    position (:class:`~gsrmr_common.channel_band.GainBand`)."""

    def __init__(self, link: LinkBudget, implausible: Implausible) -> None:
        self.link = link
        self.band = GainBand(link.rician_k, link.pathloss_exponent)
        self.implausible = implausible
        self._gains: dict[int, tuple[float, int]] = {}  # slot → (gain, round slot)
        self.unmeasured = 0  # slots decided without a gain

    def offer(self, sample: ChannelSample, position_m: tuple[float, float] | None) -> str | None:
        """A channel sample; ``position_m`` the robot's (x, y) in map (None: not known yet, the band is not applied).
        Returns why it is refused (counted: the slot stays unmeasured), or None."""
        if position_m is not None:
            reason = self.band.problem(sample.gain, self.link.mean_gain(position_m),
                                       self.link.distance_m(position_m))
            if reason:
                self.implausible[reason] += 1
                return reason
        self._gains[sample.slot] = (sample.gain, sample.round_slot)
        if len(self._gains) > GAINS_KEPT:
            for old in sorted(self._gains)[:-GAINS_KEPT // 2]:
                del self._gains[old]
        return None

    def take(self, slot: int) -> tuple[float | None, int]:
        """The gain measured for ``slot`` and its round slot; (None, -1) when unmeasured (counted)."""
        gain, round_slot = self._gains.get(slot, (None, -1))
        self.unmeasured += int(gain is None)
        return gain, round_slot
