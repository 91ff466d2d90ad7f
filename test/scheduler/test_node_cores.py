"""The pure objects behind the robot and scheduler nodes, without ROS: what each admits, refuses and counts."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from gsrmr_common.link_model import LinkBudget
from gsrmr_common.plausibility import Implausible, ScheduleLimits
from gsrmr_common.wire import ChannelSample, LedgerRow, LossSample, MRSlotInfo, RealSource, ScheduleMsg
from gsrmr_robot.robot_inputs import GAINS_KEPT, REPEAT, ChannelGains, ScheduleInbox
from gsrmr_scheduler.intake import LOSS_WAIT_SLOTS, SLOT_INFO_SKEW_SLOTS, Refusal, SchedulerIntake
from gsrmr_scheduler.loss_map import LossMap
from gsrmr_scheduler.replan_log import ServiceGate, changed_slots
from gsrmr_scheduler.state_store import StateStore


def schedule(first_slot: int, x: list[int], seq: int = 1, slot_s: float = 0.1, power_w: float = 0.05) -> ScheduleMsg:
    return ScheduleMsg(first_slot, slot_s, seq, np.array(x, np.int8), np.full(len(x), power_w))


def row(slot: int, x: int, bits: int = 67_200) -> LedgerRow:
    return LedgerRow(slot, x, 0.05, bits if x else 192, 1e-6, 0.05, 0.01, 67_200, 0.02)


# ------------------------------------------------------------------------------------------------- the robot
def test_the_schedule_inbox_keeps_the_newest_and_the_one_before_and_refuses_lies():
    inbox = ScheduleInbox(0.1, ScheduleLimits(max_power_w=0.1), Implausible())
    assert inbox.offer(schedule(100, [1, 0, 1], seq=1), b"w", 100) is None
    assert inbox.offer(schedule(100, [1, 0, 1], seq=1), b"w", 100) == REPEAT  # latched, delivered again
    assert inbox.offer(schedule(103, [0, 0], seq=2), b"w", 101) is None
    assert inbox.covering(101).first_slot == 100 and inbox.covering(103).first_slot == 103  # the one before covers 101
    assert inbox.offer(schedule(103, [1], seq=1), b"w", 101) == "schedule_seq"  # a replay of that endpoint
    assert inbox.offer(schedule(103, [1], seq=9, slot_s=0.2), b"w", 101) == "schedule_slot_s"
    assert inbox.offer(schedule(103, [1], seq=9, power_w=5.0), b"w", 101) == "schedule_power"
    assert inbox.offer(schedule(103, [1], seq=1), b"restarted", 101) is None  # a new writer endpoint starts afresh
    assert dict(inbox.implausible) == {"schedule_seq": 1, "schedule_slot_s": 1, "schedule_power": 1}


def test_channel_gains_are_taken_inside_the_band_once_the_pose_is_known_and_kept_bounded():
    link = LinkBudget()
    gains = ChannelGains(link, Implausible())
    at = (2.0, 1.0)
    mean = link.mean_gain(at)
    assert gains.offer(ChannelSample(5, 3, mean * 1e3), at) == "gain_band"  # far beyond any fade
    assert gains.offer(ChannelSample(5, 3, mean), at) is None
    assert gains.offer(ChannelSample(6, 4, mean * 1e3), None) is None  # no pose yet: no band to apply
    assert gains.take(5) == (mean, 3) and gains.take(7) == (None, -1) and gains.unmeasured == 1
    for slot in range(100, 100 + 2 * GAINS_KEPT):
        gains.offer(ChannelSample(slot, slot, mean), at)
    assert gains.take(100)[0] is None and gains.take(100 + 2 * GAINS_KEPT - 1)[0] == mean


# --------------------------------------------------------------------------------------------- the scheduler
def test_a_loss_sample_is_taken_for_an_image_slot_at_its_key_and_refused_otherwise():
    intake = SchedulerIntake(max_speed_mps=1.0, slot_s=0.1)
    assert intake.key(10, (1.0, 2.0, 0.5)) and intake.key(11, (1.01, 2.0, 0.5))
    assert intake.ledger(row(10, 1), 10) == (1, None) and intake.ledger(row(11, 0), 11) == (0, None)
    assert intake.loss(LossSample(10, 1.0, 2.0, 0.5, 0.02)) is True
    assert intake.loss(LossSample(10, 1.0, 2.0, 0.5, 0.02)) is None  # the same sample again: redelivered, not used
    refused = intake.loss(LossSample(11, 1.01, 2.0, 0.5, 0.02))
    assert isinstance(refused, Refusal) and refused.reason == "loss_key_slot"
    assert intake.ledger(row(10, 1), 12) == (None, None)  # one row per slot
    assert not intake.key(13, (9.0, 2.0, 0.5))  # faster than the robot drives
    assert dict(intake.implausible) == {"loss_key_slot": 1, "ledger_repeat": 1, "pose_jump": 1}
    assert intake.counters()["loss_samples_redelivered"] == 1 and intake.problems()


def test_a_sample_before_its_ledger_row_waits_for_it_then_expires():
    intake = SchedulerIntake(max_speed_mps=1.0, slot_s=0.1)
    intake.ledger(row(5, 1), 5)
    early = LossSample(20, 0.0, 0.0, 0.0, 0.03)
    assert intake.loss(early) is None  # waits
    assert intake.ledger(row(20, 1), 20) == (1, early)  # handed back with its row
    late = LossSample(30, 0.0, 0.0, 0.0, 0.03)
    assert intake.loss(late) is None and intake.expire(30 + LOSS_WAIT_SLOTS) == []
    (refusal,) = intake.expire(31 + LOSS_WAIT_SLOTS)
    assert refusal.reason == "loss_unledgered" and intake.implausible["loss_unledgered"] == 1
    before_first = SchedulerIntake(max_speed_mps=1.0, slot_s=0.1)
    before_first.loss(LossSample(3, 0.0, 0.0, 0.0, 0.03))
    assert before_first.expire(100) == [] and before_first.loss_samples_unverified == 1  # not a lie: unverifiable


def test_slot_info_names_a_slot_near_now():
    intake = SchedulerIntake(max_speed_mps=1.0, slot_s=0.1)
    info = MRSlotInfo(100, RealSource.RENDER, 0.0, 0.0, 0.0, 0.0)
    assert intake.slot_info(info, 100 + SLOT_INFO_SKEW_SLOTS)
    assert not intake.slot_info(info, 101 + SLOT_INFO_SKEW_SLOTS) and intake.implausible["slot_info_slot"] == 1


def test_the_replan_service_is_rate_limited():
    gate = ServiceGate()
    assert gate.refusal(10.0, 1.0, 5.0) is None
    assert "rate-limited" in gate.refusal(10.5, 1.0, 5.0)
    assert gate.refusal(11.1, 1.0, 5.0) is None and gate.refused == 1 and gate.problems()


def test_changed_slots_counts_only_the_slots_both_schedules_cover():
    assert changed_slots(None, schedule(0, [1, 1])) == 0
    assert changed_slots(schedule(0, [1, 0, 1]), schedule(1, [1, 1, 0, 0])) == 1  # slot 1 changed; 3, 4 are new


def test_the_state_store_saves_and_resumes_the_schedule_and_refuses_a_broken_file(tmp_path):
    store = StateStore(str(tmp_path / "state"))
    assert store.load_schedule() is None and store.loss_map_path() is None
    loss_map = LossMap(prior=0.02)
    store.save(schedule(7, [1, 0]), loss_map, "exact", [0.001], [0.05])
    back = store.load_schedule()
    assert back.first_slot == 7 and list(back.x) == [1, 0]
    assert store.initial_loss_map("", 0.5)[1] == store.loss_map_path()  # the saved map wins over a prior
    assert json.loads((tmp_path / "state" / "plan_stats.json").read_text())["solve_time_s"] == [0.001]
    (tmp_path / "state" / "schedule.json").write_text("{not json")
    with pytest.raises(ValueError):
        store.load_schedule()
    empty, source = StateStore("").initial_loss_map("", 0.5)
    assert source is None and math.isclose(empty.prior, 0.5)
