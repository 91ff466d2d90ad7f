"""The channel of the live loop: the simulator owns the truth (reproducible per seed and round slot), the
robot books the radio's measured gain, the scheduler plans with statistics unless told to use the oracle."""

from __future__ import annotations

from dataclasses import replace
import itertools
import math

import numpy as np
import pytest

from gsrmr_common.link_model import LinkBudget
from gsrmr_common.ros_wire import channel_sample_from_msg, channel_sample_to_msg
from gsrmr_common.wire import ChannelSample, ScheduleMsg
from gsrmr_robot.uplink_core import SlotInputs, UplinkCore, covering_schedule
from gsrmr_scheduler.loss_map import LossMap
from gsrmr_scheduler.planner import OnlinePlanner, PlannerConfig, RoutePredictor
from gsrmr_scheduler.slot_price import DEEP_FADE_FRACTION, gain_thresholds, rician_power_samples, saving_coefficient_j
from gsrmr_sim.hindsight import hindsight_optimum, regret_split
from gsrmr_sim.world.true_channel import TrueChannel


def drive(truth: TrueChannel, first_slot: int, moving_from: int, n: int) -> list[ChannelSample]:
    """Sample n slots; the robot rests until slot ``moving_from``, then moves 2 cm per slot along +x."""
    out = []
    for i in range(n):
        slot = first_slot + i
        x = 0.02 * max(0, slot - moving_from + 1)
        truth.observe_pose((x, 0.0, 0.0))
        out.append(truth.sample(slot))
    return out


def test_same_seed_same_channel_whatever_the_wall_clock():
    link = LinkBudget(channel_seed=11)
    a = drive(TrueChannel(link), 17_000_000_000, 17_000_000_005, 60)
    b = drive(TrueChannel(link), 17_000_123_456, 17_000_123_470, 60)  # another time, a longer warm-up
    ra = [s for s in a if s.round_slot >= 0]
    rb = [s for s in b if s.round_slot >= 0]
    assert [s.round_slot for s in ra[:40]] == list(range(40)) == [s.round_slot for s in rb[:40]]
    assert ra[0].slot == 17_000_000_005 and all(s.round_slot == -1 for s in a[:5])
    np.testing.assert_allclose([s.gain for s in ra[:40]], [s.gain for s in rb[:40]], rtol=1e-12)
    other = drive(TrueChannel(LinkBudget(channel_seed=12)), 17_000_000_000, 17_000_000_005, 60)
    assert not np.allclose([s.gain for s in ra[:40]], [s.gain for s in other[5:45]])
    # the Rician fading averages to the path loss (E|h|² = 1)
    gains = np.array([TrueChannel(link).link.gain(k, (0.0, 0.0)) for k in range(4000)])
    assert gains.mean() / link.mean_gain((0.0, 0.0)) == pytest.approx(1.0, abs=0.06)


def test_channel_sample_wire_round_trip_and_refusals():
    s = ChannelSample(123, 4, 2.5e-6)
    assert channel_sample_from_msg(channel_sample_to_msg(s)) == s
    for bad in ([1.0, 2.0], [1.0, 0.0, 0.0], [1.0, 0.0, float("nan")]):
        with pytest.raises(ValueError, match="channel sample"):
            ChannelSample.from_data(bad)


def test_robot_books_the_measured_gain_or_the_expected_one():
    link = LinkBudget()
    core = UplinkCore(link, 0.1)
    frame = np.random.default_rng(0).integers(0, 255, (24, 32, 3), np.uint8)
    pose = (1.0, 2.0, 0.0)
    measured = core.run_slot(SlotInputs(10, frame, 1_000_000_000, pose, (1, 0.0), 3.2e-7))
    assert measured.row.gain == 3.2e-7
    unmeasured = core.run_slot(SlotInputs(11, frame, 1_100_000_000, pose, (1, 0.0), None))
    assert unmeasured.row.gain == pytest.approx(link.mean_gain(pose[:2]))
    # a deep fade costs more energy for the same bits
    fade = core.run_slot(SlotInputs(12, frame, 1_200_000_000, pose, (1, 0.0), 3.2e-9))
    assert fade.row.energy_j > 10 * measured.row.energy_j
    # the in-slot rule decides at the measured gain, and at the expected one when the radio said nothing
    mean = link.mean_gain(pose[:2])
    assert core.run_slot(SlotInputs(13, frame, 1_300_000_000, pose, (0, 0.0), None, 0.5 * mean)).x == 1
    assert core.run_slot(SlotInputs(14, frame, 1_400_000_000, pose, (1, 0.0), None, 2.0 * mean)).x == 0
    assert core.run_slot(SlotInputs(15, frame, 1_500_000_000, pose, (0, 0.0), 4.0 * mean, 2.0 * mean)).x == 1
    assert core.run_slot(SlotInputs(16, frame, 1_600_000_000, pose, (1, 0.0), None, None)).x == 1  # no rule: plan


def test_planner_uses_statistics_unless_it_is_the_oracle():
    link = LinkBudget(channel_seed=3)
    route = [(0.0, 0.0), (2.0, 0.0), (2.0, 2.0), (0.0, 2.0)]
    config = PlannerConfig(loss_threshold=0.03, horizon_slots=20, slot_s=0.1, image_bits=67_200.0, pose_bits=192.0)
    honest = OnlinePlanner(config, RoutePredictor(route, 0.3), LossMap(prior=0.05), link)
    poses = honest.route.predict((0.0, 0.0, 0.0), 20, 0.1)
    np.testing.assert_allclose(honest.gains(1000, poses), [link.mean_gain(p[:2]) for p in poses])
    oracle = OnlinePlanner(replace(config, oracle_channel=True), RoutePredictor(route, 0.3), LossMap(prior=0.05), link)
    np.testing.assert_allclose(oracle.gains(1000, poses), honest.gains(1000, poses))  # round start not yet learnt
    oracle.learn_round_start(990)
    assert oracle.round_start_slot == 990
    np.testing.assert_allclose(oracle.gains(1000, poses), [link.gain(10 + i, p[:2]) for i, p in enumerate(poses)])


def test_hindsight_optimum_is_the_brute_force_optimum():
    rng = np.random.default_rng(5)
    for trial in range(20):
        n = 10
        g = rng.uniform(2e-7, 5e-6, n)
        e_key = 0.1 * 1e-9 / g * (2 ** (192 / 1e5) - 1)
        e_img = 0.1 * 1e-9 / g * (2 ** (rng.uniform(5e4, 9e4, n) / 1e5) - 1)
        l_img = rng.uniform(0.0, 0.01, n)
        l_gs = rng.uniform(0.0, 0.08, n)
        lth = rng.uniform(0.01, 0.05)
        h = hindsight_optimum(e_img, e_key, l_img, l_gs, lth)
        best = math.inf
        for bits in itertools.product((0, 1), repeat=n):
            x = np.array(bits)
            if np.mean(np.where(x == 1, l_img, l_gs)) <= lth + 1e-12:
                best = min(best, float(np.sum(np.where(x == 1, e_img, e_key))))
        if math.isfinite(best):
            assert h.feasible and h.energy_j == pytest.approx(best, rel=1e-9), trial
            assert h.mean_loss <= lth + 1e-12
        else:
            assert not h.feasible


def test_gain_thresholds_spend_the_loss_budget_in_expectation():
    samples = rician_power_samples(1.0)
    assert samples.mean() == pytest.approx(1.0) and np.all(np.diff(samples) >= 0)
    c = saving_coefficient_j(67_200, 192, 0.1, 1e6, 1e-9)
    rng = np.random.default_rng(2)
    m = rng.uniform(5e-7, 2e-6, 100)
    L = rng.uniform(0.0, 0.08, 100)
    thr, lam, exp_loss = gain_thresholds(m, L, 0.03 * 100, c, samples)
    assert exp_loss == pytest.approx(3.0, rel=1e-3) and lam > 0
    # the rule keys the slots where an image is dear per unit of loss: lower L or lower mean gain → key more
    p_key = np.searchsorted(samples, thr / m) / samples.size
    assert np.corrcoef(p_key, L)[0, 1] < 0
    # Monte Carlo with fresh fading draws: the realised loss of the rule averages to the budget
    draws = rng.choice(samples, (2000, 100)) * m
    realised = np.where(draws >= thr, 0.0, L).sum(axis=1)
    assert realised.mean() == pytest.approx(3.0, rel=0.02)
    assert np.all(gain_thresholds(m, L, 1e9, c, samples)[0] == np.inf)  # everything fits: all keys
    floor = np.quantile(samples, DEEP_FADE_FRACTION) * m  # nothing fits: images in all but the deepest fades
    np.testing.assert_allclose(gain_thresholds(m, L, 0.0, c, samples)[0], floor)


def test_robot_decides_in_the_slot_and_the_planner_sends_thresholds():
    link = LinkBudget()
    core = UplinkCore(link, 0.1)
    frame = np.random.default_rng(0).integers(0, 255, (24, 32, 3), np.uint8)
    pose = (1.0, 2.0, 0.0)
    good = core.run_slot(SlotInputs(10, frame, 1, pose, (0, 0.0), 2e-6, 1e-6))  # plan said key; channel good
    bad = core.run_slot(SlotInputs(11, frame, 2, pose, (1, 0.0), 5e-7, 1e-6))  # plan said image; deep fade
    blind = core.run_slot(SlotInputs(12, frame, 3, pose, (1, 0.0), None, 1e-6))  # no measurement: the plan
    assert (good.x, bad.x, blind.x) == (1, 0, 1) and good.jpeg is not None and bad.jpeg is None

    route = [(0.0, 0.0), (2.0, 0.0), (2.0, 2.0), (0.0, 2.0)]
    config = PlannerConfig(loss_threshold=0.03, horizon_slots=30, slot_s=0.1, image_bits=67_200.0, pose_bits=192.0,
                           in_slot_decision=True)
    lm = LossMap(prior=0.05)
    planner = OnlinePlanner(config, RoutePredictor(route, 0.3), lm, link)
    plan = planner.plan(101, (0.0, 0.0, 0.0))  # the schedule from slot 101 on
    thr = plan.schedule.gain_threshold
    assert thr is not None and thr.shape == (30,) and np.all(thr > 0) and planner.last_price > 0
    # every slot has the prior loss: one price → one threshold per mean gain, higher where the gain is lower
    assert plan.schedule.threshold(101) == thr[0]
    # key slots are charged by what the robot did: an image it chose in the slot costs no loss
    for k in range(101, 111):
        planner.record_action(k, 1)
    planner.budget.account_until(111, planner.active)
    assert planner.budget.loss_spent == 0.0 and planner.budget.slots_done == 10
    oracle = OnlinePlanner(replace(config, oracle_channel=True), RoutePredictor(route, 0.3), lm, link)
    assert oracle.plan(100, (0.0, 0.0, 0.0)).schedule.gain_threshold is None


def test_a_newer_schedule_that_starts_after_the_slot_leaves_it_to_the_plan_before():
    """The robot keeps the previous schedule's entry for a slot the newest one does not cover (it would otherwise
    upload the image there by default, in whatever fade: issue 28's regret tail)."""
    def sched(first: int, x: int, seq: int) -> ScheduleMsg:
        return ScheduleMsg(first, 0.1, seq, np.full(10, x, np.int8), np.full(10, 0.01))

    before, newest = sched(100, 0, 1), sched(105, 1, 2)
    assert covering_schedule(104, newest, before) is before  # 104: only the one before covers it
    assert covering_schedule(105, newest, before) is newest  # from 105 on the newest decides
    assert covering_schedule(99, newest, before) is newest  # neither covers it: the default upload (lookup None)
    assert covering_schedule(104, newest, None) is newest
    assert covering_schedule(104, None, before) is None


def test_regret_split_separates_image_placement_from_the_budget_left_unspent():
    rng = np.random.default_rng(11)
    n = 40
    g = rng.uniform(2e-7, 5e-6, n)
    e_key = 0.1 * 1e-9 / g * (2 ** (192 / 1e5) - 1)
    e_img = 0.1 * 1e-9 / g * (2 ** (rng.uniform(5e4, 9e4, n) / 1e5) - 1)
    l_img, l_gs = rng.uniform(0.0, 0.01, n), rng.uniform(0.0, 0.08, n)
    lth = 0.03

    def split(x):
        return regret_split(x, np.where(x == 1, e_img, e_key), e_img, e_key, l_img, l_gs, lth)

    best = hindsight_optimum(e_img, e_key, l_img, l_gs, lth)
    at_best = split(best.x)  # the optimum itself: nothing to split
    assert at_best.regret == pytest.approx(1.0) and at_best.placement == pytest.approx(1.0)
    assert at_best.unspent == pytest.approx(1.0)
    careful = split(hindsight_optimum(e_img, e_key, l_img, l_gs, 0.8 * lth).x)  # optimal, but for a tighter budget
    assert careful.placement == pytest.approx(1.0) and careful.unspent > 1.0
    assert careful.regret == pytest.approx(careful.unspent) and careful.mean_loss <= 0.8 * lth + 1e-12
    wasteful = split(np.ones(n, np.int8))  # every slot an image: the loss is the images', placed at any cost
    assert wasteful.placement > 1.0 and wasteful.images == n
    for s in (at_best, careful, wasteful):
        assert s.regret == pytest.approx(s.placement * s.unspent, rel=1e-12)
        assert s.images_at_own_loss <= n
