"""The scheduler's pose-fix age (gsrmr_scheduler.planner.fix_age) and how the planner prices it: the ledger's
correction seq and the keys' distance make a fix stale, the in-slot rule then takes ever poorer fades, and an image
or a new correction ends it. Pure, no ROS."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from gsrmr_common.link_model import LinkBudget
from gsrmr_common.pose2d import Pose2D
from gsrmr_scheduler.loss_map import LossMap
from gsrmr_scheduler.planner import OnlinePlanner, PlannerConfig, RoutePredictor
from gsrmr_scheduler.planner.fix_age import FixAge

ROUTE = [(0.0, 0.0), (20.0, 0.0), (20.0, 20.0)]


def _drive(age: FixAge, first_slot: int, slots: int, start_m: float, step_m: float = 0.03, seq: int = 1) -> float:
    """Keys along x, ``step_m`` a slot, each with its key-only ledger row naming ``seq``; returns the last x."""
    x = start_m
    for k in range(slots):
        x = start_m + step_m * k
        age.key(first_slot + k, Pose2D(x, 0.0, 0.0))
        age.ledger(first_slot + k, 0, seq)
    return x


def _ahead(x0: float, n: int, step_m: float = 0.03) -> np.ndarray:
    return np.array([[x0 + step_m * (k + 1), 0.0, 0.0] for k in range(n)])


def test_a_fix_goes_stale_with_distance_and_an_image_or_a_new_correction_resets_it():
    age = FixAge(stale_fix_m=1.0, ramp_m=0.3)
    x = _drive(age, 0, 10, 0.0, seq=0)
    assert age.explore(_ahead(x, 100), Pose2D(x, 0, 0)) is None  # no correction seen yet: not ours to price
    x = _drive(age, 10, 21, x, seq=1)  # the correction changes at slot 10, then 0.6 m
    assert age.fix_slot == 10 and age.slots_since_fix(40) == 30
    assert age.driven_since_fix_m == pytest.approx(0.60)
    explore = age.explore(_ahead(x, 40), Pose2D(x, 0, 0))
    ahead_m = 0.03 * np.arange(1, 41)
    # stale once 0.6 + ahead > 1.0 (and the last image is further than 0.5 m back: none since the start, 0.9 m)
    want = 0.5 * np.clip((np.minimum(0.6 + ahead_m - 1.0, 0.9 + ahead_m - 0.5)) / 0.3, 0, 1)
    np.testing.assert_allclose(explore, want, atol=1e-12)
    assert explore[:13].max() == 0 and explore[14] > 0 and explore[-1] == 0.5 and age.stale_plans == 1
    age.ledger(31, 1, 1)  # an image left: its fix may come; half the distance again before asking
    explore = age.explore(_ahead(x, 40), Pose2D(x, 0, 0))
    np.testing.assert_allclose(explore, 0.5 * np.clip(np.minimum(0.6 + ahead_m - 1.0, ahead_m - 0.5) / 0.3, 0, 1),
                               atol=1e-12)
    x = _drive(age, 32, 5, x, seq=2)  # the fix came
    assert age.fix_slot == 32 and age.explore(_ahead(x, 20), Pose2D(x, 0, 0)) is None
    assert FixAge(0.0).explore(_ahead(0.0, 10), None) is None  # 0: never
    age.key(20, Pose2D(50.0, 0.0, 0.0))  # an older key, late: no distance from it
    assert age.driven_since_fix_m == pytest.approx(0.12)
    with pytest.raises(ValueError):
        FixAge(-1.0)


def test_the_planner_takes_poorer_fades_where_the_fix_is_stale():
    config = PlannerConfig(loss_threshold=0.03, horizon_slots=60, in_slot_decision=True, stale_fix_m=1.0)
    planners = {}
    for name, cfg in (("on", config), ("off", replace(config, stale_fix_m=0.0))):
        planner = OnlinePlanner(cfg, RoutePredictor(ROUTE, 0.3), LossMap(prior=0.001), LinkBudget())
        for k in range(30):  # 0.03 m a slot (the route's 0.3 m/s): 0.87 m since the fix of slot 0
            planner.record_action(k, 0, correction_seq=1)
            planner.record_pose(k, 0.03 * k, 0.0, 0.0)
        planners[name] = planner.plan(30, (0.87, 0.0, 0.0)).schedule.gain_threshold
    on, off = planners["on"], planners["off"]
    assert np.array_equal(on[:4], off[:4])  # the first slots are not stale yet (0.87 + 0.03 k ≤ 1 m)
    assert np.all(on[10:] < off[10:])  # past 1 m: any fade up to the median one buys the image
    with pytest.raises(ValueError, match="stale_fix_m"):
        PlannerConfig(loss_threshold=0.03, horizon_slots=10, stale_fix_m=-1.0)
