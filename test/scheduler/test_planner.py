"""The online planner's parts (pure, no ROS): its configuration, the loss budget, the in-slot pricing, the L_t
forecast, the drift monitor, and the planner that composes them (live reconfiguration, resuming a schedule).
The link cap's tests are in test_uplink_backlog.py."""

from __future__ import annotations

from dataclasses import FrozenInstanceError, replace
import math

import numpy as np
import pytest

from gsrmr_common.link_model import LinkBudget
from gsrmr_common.wire import ScheduleMsg
from gsrmr_scheduler.loss_map import LossMap
from gsrmr_scheduler.planner import (
    DriftMonitor,
    InSlotPricing,
    LossBudget,
    LossForecast,
    OnlinePlanner,
    PlannerConfig,
    RoutePredictor,
)
from gsrmr_scheduler.planner.cadence import SampleAlignedCadence
from gsrmr_scheduler.slot_price import DEEP_FADE_FRACTION, gain_thresholds, rician_power_samples, saving_coefficient_j

ROUTE = [(0.0, 0.0), (2.0, 0.0), (2.0, 2.0), (0.0, 2.0)]
BASE = PlannerConfig(loss_threshold=0.03, horizon_slots=20)


def _schedule(first: int, x: list[int]) -> ScheduleMsg:
    return ScheduleMsg(first, 0.1, 1, np.array(x, np.int8), np.zeros(len(x)))


# ---------------------------------------------------------------------------- configuration
def test_config_is_frozen_and_validated():
    config = PlannerConfig(loss_threshold=0.03, horizon_slots=10, image_bits=64_000, solver_options={"a": 1})
    assert isinstance(config.image_bits, float) and config.image_bits == 64_000.0  # stored as the float it means
    with pytest.raises(FrozenInstanceError):
        config.loss_threshold = 0.5  # type: ignore[misc]
    with pytest.raises(TypeError):
        config.solver_options["a"] = 2  # type: ignore[index]
    options = {"time_limit_s": 0.05}
    held = PlannerConfig(loss_threshold=0.03, horizon_slots=10, solver_options=options)
    options["time_limit_s"] = 9.0  # the caller's dict changes later: the config does not
    assert held.solver_options == {"time_limit_s": 0.05}
    assert replace(config, loss_margin=0.5).loss_target == pytest.approx(0.015)


@pytest.mark.parametrize(("change", "reason"), [
    ({"horizon_slots": 0}, "horizon_slots must be >= 1"),
    ({"horizon_slots": 10.0}, "horizon_slots must be an integer"),
    ({"horizon_slots": True}, "horizon_slots must be an integer"),
    ({"loss_threshold": math.nan}, "loss_threshold must be a finite number"),
    ({"loss_threshold": -0.01}, "loss_threshold must be >= 0"),
    ({"image_bits": 192.0}, "image_bits must exceed pose_bits"),
    ({"method": "bogus"}, "method must be one of"),
    ({"loss_margin": 1.0}, "loss_margin must be in [0, 1)"),
    ({"explore_image_fraction": 1.5}, "explore_image_fraction must be in [0, 1]"),
    ({"margin_quantile": -0.1}, "margin_quantile must be in [0, 1]"),
    ({"drift_window_samples": 0}, "drift_window_samples must be >= 1"),
    ({"in_slot_decision": 1}, "in_slot_decision must be a bool"),
    ({"image_slot_loss": -1.0}, "image_slot_loss must be a loss >= 0"),
    ({"burst_time_constant_slots": 0.0}, "burst_time_constant_slots must be > 0"),
    ({"round_slots": -1}, "round_slots must be >= 0"),
])
def test_config_refuses_with_a_reason(change, reason):
    with pytest.raises(ValueError, match="planner config: ") as err:
        replace(BASE, **change)
    assert reason in str(err.value)


def test_only_live_fields_may_change_in_a_running_planner():
    assert BASE.live_change_problem(replace(BASE, loss_threshold=0.02, horizon_slots=50, method="ranking")) is None
    reason = BASE.live_change_problem(replace(BASE, round_slots=288, probe_gap_slots=4))
    assert reason is not None and "round_slots" in reason and "probe_gap_slots" in reason


# ---------------------------------------------------------------------------- loss budget
def test_budget_books_what_the_robot_did_at_the_pose_it_reported():
    seen: list[tuple[int, tuple | None]] = []

    def key_loss(slot, pose):
        seen.append((slot, pose))
        return 0.05 if pose is not None else 0.02

    budget = LossBudget(key_loss, image_slot_loss=0.007)
    sched = _schedule(10, [0, 0, 1, 1, 0])
    budget.record_action(11, 1)  # the robot sent an image where the plan said key
    budget.record_action(13, 0)  # … and a key where it said image
    budget.record_pose(10, (1.0, 0.0, 0.0))
    budget.account_until(15, sched)
    assert budget.slots_done == 5
    # slot 10: key at its pose (0.05); 11: image (J); 12: the plan's image (J); 13: key, no pose (0.02); 14 too
    assert budget.loss_spent == pytest.approx(0.05 + 0.007 + 0.007 + 0.02 + 0.02)
    assert (10, (1.0, 0.0, 0.0)) in seen and (13, None) in seen
    budget.account_until(15, sched)  # nothing new: nothing booked twice
    assert budget.slots_done == 5
    target, h = 0.03, 20
    (part, cap), = budget.caps(15, h, target)
    assert part == slice(0, h) and cap == pytest.approx(target * (5 + h) - budget.loss_spent)  # running mean
    assert budget.round_remaining(15) is None


def test_a_ledger_row_or_pose_key_that_comes_after_its_slot_was_booked_rebooks_it():
    """A plan books every slot before its first one: with the plan's x and at no pose where the robot's ledger row
    and pose key have not come (delayed on the way). When they come, they correct the booking (they were dropped
    before: an image booked as a key for good)."""
    budget = LossBudget(lambda _slot, pose: 0.05 if pose is not None else 0.02, image_slot_loss=0.007)
    budget.account_until(3, _schedule(0, [0, 0, 0, 0]))  # slots 0–2 booked as the plan's keys, no pose
    budget.planned_from(2)
    assert budget.loss_spent == pytest.approx(3 * 0.02)
    budget.record_action(2, 1)  # slot 2 was an image in fact (the robot's in-slot rule)
    budget.record_pose(1, (1.0, 0.0, 0.0))  # slot 1 was a key at this pose
    assert budget.slots_done == 3
    assert budget.loss_spent == pytest.approx(0.02 + 0.05 + 0.007)
    budget.record_action(3, 1)  # not booked yet: kept for its booking, as before
    budget.account_until(4, _schedule(0, [0, 0, 0, 0]))
    assert budget.slots_done == 4 and budget.loss_spent == pytest.approx(0.02 + 0.05 + 0.007 + 0.007)


def test_a_slot_is_charged_as_the_server_composed_it_not_as_the_robot_sent_it():
    """An image that did not reach the server in time left the render's loss (its key came) or the fallback's
    (neither came), not the JPEG's: the server's mr/slot_info says which, booked or not yet."""
    from gsrmr_scheduler.planner.budget import FALLBACK_LOSS_FACTOR

    key = 0.04
    budget = LossBudget(lambda _slot, _pose: key, image_slot_loss=0.005)
    for slot in range(5):
        budget.record_action(slot, 1)  # the robot sent an image in every slot
    budget.record_composed(1, "render")  # … its key came in time, the image did not
    budget.record_composed(2, "image")
    budget.account_until(5, _schedule(0, [1] * 5))
    assert budget.loss_spent == pytest.approx(4 * 0.005 + key)
    budget.record_composed(3, "fallback")  # after the booking: still charged by it (neither upload in time)
    budget.record_composed(4, "none")  # no pose at all: the fallback's charge too
    assert budget.loss_spent == pytest.approx(2 * 0.005 + key + 2 * FALLBACK_LOSS_FACTOR * key)
    keys = LossBudget(lambda _slot, _pose: key, image_slot_loss=0.005)
    keys.record_composed(0, "render")  # a key slot composed from its key: charged as before
    keys.record_composed(1, "fallback")  # a key slot whose key came too late
    keys.account_until(2, _schedule(0, [0, 0]))
    assert keys.loss_spent == pytest.approx(key + FALLBACK_LOSS_FACTOR * key)
    assert FALLBACK_LOSS_FACTOR > 1.0


def test_a_key_slot_composed_below_full_size_is_charged_its_level_and_the_plan_buys_images_for_it():
    """The server's mr/slot_info says the level: a render at half or a quarter of the size costs the measured extra
    loss in the budget, an image slot (r̂ the JPEG) does not; the recent levels raise the forecast of key slots."""
    key, extra = 0.02, (0.0, 0.01, 0.04)
    budget = LossBudget(lambda _slot, _pose: key, image_slot_loss=0.005, level_extra_loss=extra, level_window_slots=4)
    for slot, (x, source, level) in enumerate([(0, "render", 0), (0, "render", 1), (0, "render", 2),
                                                (1, "image", 2), (0, "fallback", 1), (1, "render", 2)]):
        budget.record_action(slot, x)
        budget.record_composed(slot, source, level)
    budget.account_until(6, _schedule(0, [0, 0, 0, 1, 0, 1]))
    from gsrmr_scheduler.planner.budget import FALLBACK_LOSS_FACTOR

    assert budget.loss_spent == pytest.approx(key + (key + 0.01) + (key + 0.04) + 0.005
                                              + (FALLBACK_LOSS_FACTOR * key + 0.01) + (key + 0.04))
    assert budget.level_loss_now(6) == pytest.approx((0.04 + 0.04 + 0.01 + 0.04) / 4)  # slots 2–5
    assert budget.level_loss_now(100) == 0.0 and LossBudget(lambda *_: key).level_loss_now(6) == 0.0
    budget.record_composed(7, "render", 9)  # a level past the table: the cheapest's charge
    assert budget.slot_loss(7, 0, None) == pytest.approx(key + 0.04)
    with pytest.raises(ValueError):
        LossBudget(lambda *_: key, level_extra_loss=(0.0, -0.1, 0.0))
    config = replace(BASE, half_level_extra_loss=0.01, quarter_level_extra_loss=0.04)
    calm, starved = _planner(config), _planner(config)
    for slot in range(80, 100):
        starved.record_composed(slot, "render", 2)
    calm_plan, starved_plan = calm.plan(100, (0.0, 0.0, 0.0)), starved.plan(100, (0.0, 0.0, 0.0))
    assert starved_plan.predicted_loss == pytest.approx(calm_plan.predicted_loss + 0.04)
    assert starved_plan.images > calm_plan.images
    with pytest.raises(ValueError, match="level_extra_loss"):
        replace(BASE, quarter_level_extra_loss=2.0)


def test_budget_refines_recent_estimates_and_freezes_old_ones():
    estimate = {k: 0.02 for k in range(100)}
    budget = LossBudget(lambda slot, _pose: estimate[slot], refine_slots=2)
    budget.account_until(5, _schedule(0, [0] * 10))
    assert budget.loss_spent == pytest.approx(5 * 0.02)
    for k in range(5):  # new measurements change every estimate: only the 2 newest slots still follow them
        estimate[k] = 0.08
    assert budget.loss_spent == pytest.approx(3 * 0.02 + 2 * 0.08)


def test_a_new_seed_map_leaves_the_loss_the_old_model_left_as_it_was_estimated():
    """A model swap re-seeds the forecast mid-round: the slots the old model served keep their estimate, in the
    running total and in the round's (re-estimating them with the new map once made the planner send an image in
    77–100 % of the slots left)."""
    estimate = {k: 0.02 for k in range(100)}
    budget = LossBudget(lambda slot, _pose: estimate[slot], round_slots=50, refine_slots=300)
    sched = _schedule(0, [0] * 40)
    budget.record_pose(0, (0.0, 0.0, 0.0))
    for k in range(1, 8):
        budget.record_pose(k, (0.1 * k, 0.0, 0.0))  # the round starts in slot 1
    budget.account_until(8, sched)
    assert budget.loss_spent == pytest.approx(8 * 0.02) and budget.round_booked() == (7, pytest.approx(7 * 0.02))
    budget.freeze_all()
    for k in range(100):  # the new map, not measured yet, says something else about every slot
        estimate[k] = 0.09
    assert budget.loss_spent == pytest.approx(8 * 0.02) and budget.round_booked() == (7, pytest.approx(7 * 0.02))
    budget.account_until(10, sched)  # slots served by the new model follow the new estimate
    assert budget.loss_spent == pytest.approx(8 * 0.02 + 2 * 0.09)
    assert budget.round_booked() == (9, pytest.approx(7 * 0.02 + 2 * 0.09))


def test_round_starts_on_motion_and_its_budget_ends_with_it():
    budget = LossBudget(lambda _slot, _pose: 0.05, round_slots=10, round_start_m=0.05)
    sched = _schedule(0, [0] * 40)
    budget.record_pose(0, (0.0, 0.0, 0.0))  # where it stands
    budget.record_pose(1, (0.03, 0.0, 0.0))  # within round_start_m: not moving yet
    assert budget.round_remaining(2) is None
    budget.record_pose(2, (0.1, 0.0, 0.0))  # moving: the round starts in slot 2
    for k in range(3, 6):
        budget.record_pose(k, (0.1 * k, 0.0, 0.0))
    budget.account_until(6, sched)
    assert budget.round_remaining(6) == 6 and budget.round_booked() == (4, pytest.approx(4 * 0.05))
    blocks = budget.caps(6, 20, 0.03)  # the round ends inside the horizon: its rest, then a fresh budget
    assert [b[0] for b in blocks] == [slice(0, 6), slice(6, 20)]
    assert blocks[0][1] == pytest.approx(0.03 * (4 + 6) - 4 * 0.05) and blocks[1][1] == pytest.approx(0.03 * 14)
    long = budget.caps(6, 4, 0.03)  # a horizon inside the round: the round's budget alone
    assert long == [(slice(0, 4), pytest.approx(0.03 * (4 + 4) - 4 * 0.05))]
    budget.record_pose(12, (2.0, 0.0, 0.0))  # the round is over: the next starts on motion from here
    assert budget.round_remaining(13) is None
    budget.record_pose(13, (2.2, 0.0, 0.0))
    assert budget.round_remaining(14) == 9


def test_budget_refuses_nonsense():
    with pytest.raises(ValueError):
        LossBudget(lambda *_: 0.0, image_slot_loss=math.nan)
    with pytest.raises(ValueError):
        LossBudget(lambda *_: 0.0, round_slots=-1)


# ---------------------------------------------------------------------------- in-slot pricing
def test_exploration_at_start_up_and_the_probe_ramp():
    pricing = InSlotPricing(1.0, explore_image_fraction=0.05, probe_gap_slots=10, startup_explore_samples=3)
    slots = np.arange(101, 121)
    # no image yet: the ramp counts from the slot before the horizon; start-up: the better half of the fades
    np.testing.assert_allclose(pricing.explore(slots, samples_held=0), 0.5)
    after = pricing.explore(slots, samples_held=3)
    np.testing.assert_allclose(after, np.maximum(0.05, 0.5 * np.minimum(1.0, np.arange(1, 21) / 10)))
    pricing.record_image(110)
    pricing.record_image(105)  # an older ledger row does not move the probe clock back
    assert pricing.last_image_slot == 110
    ramp = pricing.explore(slots, samples_held=3)
    np.testing.assert_allclose(ramp, np.maximum(0.05, 0.5 * np.minimum(1.0, np.maximum(slots - 110, 0) / 10)))
    plain = InSlotPricing(1.0)
    np.testing.assert_array_equal(plain.explore(slots, 0), np.zeros(20))
    with pytest.raises(ValueError):
        InSlotPricing(1.0, explore_image_fraction=2.0)


def test_thresholds_are_the_priced_rule_and_the_link_cap_raises_the_price():
    pricing = InSlotPricing(1.0)
    rng = np.random.default_rng(3)
    mean_gain, key_cost = rng.uniform(5e-7, 2e-6, 40), rng.uniform(0.01, 0.08, 40)
    coeff = saving_coefficient_j(67_200, 192, 0.1, 1e6, 1e-9)
    explore = np.full(40, 0.05)
    thr, price = pricing.thresholds(mean_gain, key_cost, 0.6, explore, coeff)
    want, want_price, _ = gain_thresholds(mean_gain, key_cost, 0.6, coeff, rician_power_samples(1.0), explore)
    np.testing.assert_array_equal(thr, want)
    assert price == want_price > 0

    def expected_images(t: np.ndarray) -> float:
        return float(np.sum(1 - np.searchsorted(pricing.fading, t / mean_gain) / pricing.fading.size))

    assert expected_images(thr) > 10
    capped, capped_price = pricing.thresholds(mean_gain, key_cost, 0.6, explore, coeff, max_images=10.0)
    assert expected_images(capped) <= 10.0 + 1e-6 and capped_price > price


# ---------------------------------------------------------------------------- L_t forecast and drift
def test_trusted_map_forecast_plans_on_the_map_as_it_learns():
    lm = LossMap(prior=0.02)
    forecast = LossForecast(lm, trust_loss_map=True)
    poses = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    raw, margined = forecast.predict(np.array([5, 6]), poses)
    np.testing.assert_array_equal(raw, [0.02, 0.02])
    np.testing.assert_array_equal(margined, raw)  # no margin
    forecast.remember(5, raw, 4)
    assert forecast.observe(5, (0.0, 0.0, 0.0), 0.09) == 0.02  # what the plan had predicted
    assert forecast.observe(7, (0.0, 0.0, 0.0), math.nan) is None
    assert forecast.samples == 1 and forecast.model is None
    assert forecast.key_loss(9, (0.0, 0.0, 0.0)) == pytest.approx(0.09)  # the map learnt the sample
    assert forecast.key_loss(6, None) == 0.02 and forecast.key_loss(99, None) == 0.02  # plan, else prior
    with pytest.raises(ValueError):
        LossForecast(lm, trust_loss_map=True, model=forecast.model or object())  # type: ignore[arg-type]


def test_burst_forecast_corrects_a_frozen_seed_and_the_live_map_keeps_learning():
    lm = LossMap(prior=0.02)
    forecast = LossForecast(lm, margin_quantile=0.75)
    pose = (0.0, 0.0, 0.0)
    forecast.remember(10, np.full(5, 0.02), 9)
    for k in range(10, 14):
        forecast.observe(k, pose, 0.04)  # twice the seed, measured 4 times
    assert forecast.model is not None and forecast.samples == 4 and forecast.model.margin > 1.5
    raw, margined = forecast.predict(np.array([15]), np.array([pose]))
    assert raw[0] == pytest.approx(0.04) and margined[0] == pytest.approx(raw[0] * forecast.model.margin)
    assert forecast.model.seed_map.predict(*pose) == 0.02  # the model's seed stays the mapping round's
    assert lm.predict(*pose) == pytest.approx(0.04)  # the live map (saved for later runs) learnt
    forecast.remember(1500, np.array([0.5]), 2000)  # far later: predictions > 1000 slots old are forgotten
    assert forecast.predicted(10) is None and forecast.predicted(1500) == 0.5


def test_loss_samples_are_corrected_by_the_sample_offset_before_anything_learns_from_them():
    """A server's sample reads its JPEG's error above the loss against the frame: the planner subtracts
    ``loss_sample_offset`` (floored at 0) before the burst model, the live map, the margin and the drift test."""
    pose = (0.0, 0.0, 0.0)
    forecast = LossForecast(LossMap(prior=0.02), sample_offset=0.003)
    assert forecast.corrected(0.013) == pytest.approx(0.010) and forecast.corrected(0.001) == 0.0
    assert math.isnan(forecast.corrected(math.nan))
    plain = OnlinePlanner(replace(BASE, drift_window_samples=1, drift_threshold=0.0025), RoutePredictor(ROUTE, 0.3),
                          LossMap(prior=0.02), LinkBudget())
    offset = OnlinePlanner(replace(BASE, drift_window_samples=1, drift_threshold=0.0025, loss_sample_offset=0.003),
                           RoutePredictor(ROUTE, 0.3), LossMap(prior=0.02), LinkBudget())
    for planner in (plain, offset):
        planner.forecast.remember(5, np.array([0.02]), 4)
    assert plain.observe(5, *pose, 0.023) is True  # |0.023 − 0.02| > 0.0025: a drift alarm
    assert offset.observe(5, *pose, 0.023) is False  # 0.020 against the frame: as predicted
    assert plain.loss_map.predict(*pose) == pytest.approx(0.023)
    assert offset.loss_map.predict(*pose) == pytest.approx(0.020)  # the live map holds losses against the frame
    assert offset.forecast.key_loss(6, pose) == pytest.approx(0.020)  # a key slot there is charged so


def test_drift_needs_a_full_window_and_follows_a_live_window_change():
    drift = DriftMonitor(0.02, 3)
    assert drift.add(0.1) is False and drift.add(0.1) is False and drift.add(0.0) is True  # mean 0.067 > 0.02
    drift.reconfigure(0.02, 2)  # the newest 2 errors stay: mean 0.05
    assert drift.add(0.0) is False  # mean of (0.0, 0.0)
    drift.reconfigure(0.02, 4)
    assert drift.add(0.2) is False and drift.add(0.2) is True  # 4 errors needed now
    drift.clear()
    assert drift.add(0.5) is False
    with pytest.raises(ValueError):
        DriftMonitor(0.02, 0)


# ---------------------------------------------------------------------------- the planner
def _planner(config: PlannerConfig, prior: float = 0.02) -> OnlinePlanner:
    return OnlinePlanner(config, RoutePredictor(ROUTE, 0.3), LossMap(prior=prior), LinkBudget())


def test_reconfigure_takes_live_fields_into_the_next_plan_and_refuses_the_others():
    planner = _planner(BASE, prior=0.05)
    first = planner.plan(100, (0.0, 0.0, 0.0))
    assert first.budget == pytest.approx(0.03) and len(first.schedule.x) == 20
    tighter = replace(BASE, loss_threshold=0.02, horizon_slots=30, method="ranking", drift_window_samples=2)
    planner.reconfigure(tighter)
    assert planner.config is tighter and planner.drift.window_samples == 2
    second = planner.plan(120, (0.0, 0.0, 0.0))
    assert len(second.schedule.x) == 30 and second.method == "ranking"
    spent = planner.budget.loss_spent  # 20 booked slots
    assert second.budget == pytest.approx((0.02 * (20 + 30) - spent) / 30)
    with pytest.raises(ValueError, match="round_slots cannot change"):
        planner.reconfigure(replace(tighter, round_slots=288))
    assert planner.config is tighter


def test_resume_continues_a_saved_schedule():
    planner = _planner(BASE)
    saved = ScheduleMsg(500, 0.1, 41, np.array([1, 0, 0, 1, 0], np.int8), np.zeros(5))
    planner.resume(saved)
    assert planner.active is saved and planner.seq == 41
    result = planner.plan(503, (0.0, 0.0, 0.0))  # the saved schedule's slots 500–502 were booked
    assert result.schedule.seq == 42 and result.schedule.first_slot == 503
    assert planner.budget.slots_done == 3
    assert planner.budget.loss_spent == pytest.approx(0.0 + 2 * 0.02)  # image, key, key (the map's prior)


def test_the_oracle_plans_without_thresholds_and_the_in_slot_rule_with_them():
    priced = _planner(replace(BASE, in_slot_decision=True))
    plan = priced.plan(0, (0.0, 0.0, 0.0))
    assert plan.schedule.gain_threshold is not None and priced.last_price is not None
    oracle = _planner(replace(BASE, in_slot_decision=True, oracle_channel=True, trust_loss_map=True))
    assert oracle.plan(0, (0.0, 0.0, 0.0)).schedule.gain_threshold is None and oracle.last_price is None


def _robot_decides(schedule: ScheduleMsg | None, slot: int, gain: float) -> int:
    """The robot's rule (``gsrmr_robot.uplink_core``): an image iff the slot's gain reaches its threshold; a slot its
    schedule has no entry for uploads the image (``default_upload_image``), whatever the fade."""
    entry = schedule.lookup(slot) if schedule is not None else None
    if entry is None:
        return 1
    threshold = schedule.threshold(slot)
    return entry[0] if threshold is None else int(gain >= threshold)


def test_a_deficit_is_not_repaid_in_a_deep_fade_when_a_plan_is_published_before_its_slot():
    """Issue 28's regret tail. The node plans from the slot after the one in which the plan is expected to be done;
    a timer that fires just before a slot boundary publishes plan(k) — its horizon from k + 1 — before slot k
    starts, and the robot decides slot k with it. Here every replan is so, the run starts 20 key slots in deficit
    (L = 0.05 against L_th = 0.03) and slot 105 is a deep fade (1 % of the mean gain, below the in-slot rule's
    floor): the robot keys it — the new schedule carries the previous one's entry — and the run still meets L_th.
    Before, slot 105 had no entry and the robot uploaded its image there: 100× a typical image's energy."""
    config = replace(BASE, horizon_slots=40, in_slot_decision=True, trust_loss_map=True, image_slot_loss=0.007,
                     round_slots=140, loss_margin=0.1)  # the rule meets its budget in expectation: a back-off
    planner = _planner(config, prior=0.05)  # L_t = 0.05 wherever the robot is
    planner.record_pose(79, 0.0, 0.0, 0.0)
    pose = (0.1, 0.0, 0.0)  # moved: the round of 140 slots starts in slot 80
    mean = planner.link.mean_gain(pose[:2])
    planner.plan(79, pose)  # the first schedule: slots 80–119
    loss = {}
    for k in range(80, 100):  # keys: 0.4 of loss budget overspent when the loop below starts
        planner.record_pose(k, *pose)
        planner.record_action(k, 0)
        loss[k] = 0.05
    fades, uncovered = {}, []
    floor = np.quantile(rician_power_samples(1.0), DEEP_FADE_FRACTION)
    for k in range(100, 220):
        if k % 5 == 0:
            planner.plan(k, pose)  # published before slot k started
            if planner.active.lookup(k) is None:
                uncovered.append(k)
        fades[k] = 0.01 if k == 105 else planner.link.gain(k, pose[:2]) / mean
        x = _robot_decides(planner.active, k, fades[k] * mean)
        planner.record_pose(k, *pose)
        planner.record_action(k, x)
        if x:
            planner.observe(k, *pose, 0.05)
        loss[k] = 0.007 if x else 0.05
        assert not (x and fades[k] < floor), f"an image in slot {k}, a fade of {fades[k]:.3f} of the mean gain"
    assert uncovered == []  # every schedule covers the slot it may arrive before
    assert planner.budget.round_remaining(219) == 1
    assert math.fsum(loss.values()) / len(loss) <= config.loss_threshold  # the deficit repaid within the round


def test_the_periodic_replan_waits_for_the_next_loss_sample_and_at_most_a_period():
    cadence = SampleAlignedCadence()
    assert not cadence.sample_taken()  # a sample before the period is over: no replan of its own
    assert not cadence.timer_fired()  # the period is over: wait for the next sample
    assert cadence.waiting
    assert cadence.sample_taken() and not cadence.waiting  # ... and replan right after it
    assert not cadence.sample_taken()  # once per period
    assert not cadence.timer_fired()
    assert cadence.timer_fired() and cadence.waited_out == 1  # no sample for a whole period: replan at the timer
    assert not cadence.timer_fired()
    cadence.replanned()  # a drift or service replan satisfies the period
    assert not cadence.waiting and not cadence.sample_taken()
    unaligned = SampleAlignedCadence(aligned=False)  # the timer's phase, as before
    assert unaligned.timer_fired() and unaligned.timer_fired() and not unaligned.sample_taken()
