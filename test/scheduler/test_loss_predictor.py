"""The live loop's L_t predictor, round budget, probing rule and the offline replay (pure, no ROS)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gsrmr_common.link_model import LinkBudget
from gsrmr_scheduler.loss_map import LossMap
from gsrmr_scheduler.loss_predictor import LossPredictor
from gsrmr_scheduler.planner import OnlinePlanner, PlannerConfig, RoutePredictor
from gsrmr_scheduler.slot_price import DEEP_FADE_FRACTION, gain_thresholds, rician_power_samples
from gsrmr_server.mr.blend import jpeg_mr_loss
from gsrmr_sim.replay import recorded_slots, replay

ROUTE = [(0.0, 0.0), (2.0, 0.0), (2.0, 2.0), (0.0, 2.0)]
POSE = (0.5, 0.0, 0.0)


def _flat_map(value: float = 0.02) -> LossMap:
    lm = LossMap(prior=value)
    return lm


def _planner(loss_map: LossMap | None = None, **kw) -> OnlinePlanner:
    """A planner with the in-slot rule and the burst model, no learned margin; ``kw``: PlannerConfig fields."""
    args = dict(slot_s=0.1, image_bits=67_200.0, pose_bits=192.0, loss_threshold=0.03, horizon_slots=30,
                in_slot_decision=True, margin_quantile=0.0)
    args.update(kw)
    return OnlinePlanner(PlannerConfig(**args), RoutePredictor(ROUTE, 0.3), loss_map or _flat_map(), LinkBudget())


# ---------------------------------------------------------------------------- predictor
def test_prediction_follows_a_measured_burst_and_fades_into_the_runs_average():
    lp = LossPredictor(_flat_map(0.02), burst_time_constant_slots=10.0)
    assert lp.predict(np.array([5]), np.array([POSE]))[0] == pytest.approx(0.02)  # nothing measured: the seed
    for k in range(0, 40, 4):  # a quiet stretch measured at 1.2× the seed
        lp.observe(k, POSE, 0.024)
    lp.observe(40, POSE, 0.08)  # a burst: 4× the seed
    assert math.exp(lp.level) == pytest.approx(1.2)
    ahead = lp.predict(np.arange(41, 200), np.repeat([POSE], 159, axis=0))
    assert ahead[0] == pytest.approx(0.08, rel=0.15)  # right after: the burst's level
    assert np.all(np.diff(ahead) <= 1e-12)  # fading …
    far = 0.02 * math.exp(lp.level) * lp.burst_factor
    assert ahead[-1] == pytest.approx(far, rel=1e-3) and lp.burst_factor > 1.0  # … to the average, bursts included


def test_past_key_slots_are_estimated_between_the_measurements_around_them():
    lp = LossPredictor(_flat_map(0.02))
    lp.observe(10, POSE, 0.02)
    lp.observe(20, POSE, 0.08)
    mid = lp.estimate(15, POSE)
    assert mid == pytest.approx(math.sqrt(0.02 * 0.08), rel=1e-9)  # linear in log-ratio: the geometric mean
    assert lp.estimate(10, POSE) == pytest.approx(0.02) and lp.estimate(20, POSE) == pytest.approx(0.08)
    lp.observe(15, POSE, 0.05)  # a late sample lands in order
    assert lp.estimate(15, POSE) == pytest.approx(0.05)



def test_a_change_the_robot_found_between_two_measurements_is_estimated_as_a_step_there():
    lp = LossPredictor(_flat_map(0.02))
    lp.observe(10, POSE, 0.10)  # a light on …
    lp.observe(20, POSE, 0.02)  # … and off again by the next image
    interpolated = [lp.estimate(k, POSE) for k in range(11, 20)]
    assert all(0.02 < v < 0.10 for v in interpolated)  # without a change slot: a gradual fade
    lp.note_change(16)  # the robot's change test fired on slot 16's frame: the light went off there
    lp.note_change(16)  # a repeated row changes nothing
    assert [lp.estimate(k, POSE) for k in range(11, 16)] == pytest.approx([0.10] * 5)  # still lit
    assert [lp.estimate(k, POSE) for k in range(16, 20)] == pytest.approx([0.02] * 4)  # dark from the change on
    assert lp.estimate(10, POSE) == pytest.approx(0.10) and lp.estimate(20, POSE) == pytest.approx(0.02)
    lp.observe(30, POSE, 0.04)
    lp.note_change(20)  # a change in the slot of a measurement: the gap after it is interpolated as before
    assert lp.estimate(25, POSE) == pytest.approx(math.sqrt(0.02 * 0.04), rel=1e-9)
    lp.note_change(24)
    lp.note_change(22)  # two changes in one gap (notified out of order): the step is at the first
    assert lp.estimate(21, POSE) == pytest.approx(0.02) and lp.estimate(22, POSE) == pytest.approx(0.04)
    assert lp.estimate(40, POSE) == pytest.approx(0.04)  # after the last measurement: its value, as before
    lp.note_change(35)
    assert lp.estimate(40, POSE) == pytest.approx(0.04)


def test_the_planner_charges_key_slots_by_the_change_slot_of_the_robot_s_ledger():
    """The ledger's ``scene_change`` reaches the burst model through record_action: the key slots booked between
    two images are charged as a step at the change, not as a fade."""
    planner = _planner(loss_map=_flat_map(0.02))
    for slot, x, change in [(10, 1, 0), *((k, 0, int(k == 13)) for k in range(11, 20)), (20, 1, 0)]:
        planner.record_action(slot, x, scene_change=change)
    planner.observe(10, *POSE, 0.02)
    planner.observe(20, *POSE, 0.08)
    charged = [planner.forecast.key_loss(k, POSE) for k in range(11, 20)]
    assert charged == pytest.approx([0.02, 0.02] + [0.08] * 7)
    unchanged = _planner(loss_map=_flat_map(0.02))
    for slot in (10, 20):
        unchanged.record_action(slot, 1)
    unchanged.observe(10, *POSE, 0.02)
    unchanged.observe(20, *POSE, 0.08)
    assert 0.02 < unchanged.forecast.key_loss(12, POSE) < unchanged.forecast.key_loss(13, POSE) < 0.08

def test_learned_margin_is_the_quantile_of_measured_over_predicted():
    lp = LossPredictor(_flat_map(0.02), margin_quantile=0.75)
    assert lp.margin == 1.0
    for k, ratio in enumerate([0.8, 1.0, 1.2, 1.4, 3.0]):
        lp.observe(k, POSE, 0.02 * ratio, predicted=0.02)
    assert lp.margin == pytest.approx(np.quantile([0.8, 1.0, 1.2, 1.4, 3.0], 0.75))
    lp.observe(9, POSE, float("nan"), predicted=0.02)  # ignored
    lp.observe(9, POSE, -1.0, predicted=0.02)
    assert lp.samples == 5
    assert LossPredictor(_flat_map(), margin_quantile=0.0).margin == 1.0
    with pytest.raises(ValueError):
        LossPredictor(_flat_map(), burst_time_constant_slots=0.0)


def test_predictions_stay_finite_at_the_extremes():
    lp = LossPredictor(_flat_map(0.02))
    for k, loss in enumerate([0.0, 1e-12, 1.0, 1e6, 0.02]):
        lp.observe(k, POSE, loss)
    out = lp.predict(np.arange(5, 2000), np.repeat([POSE], 1995, axis=0))
    assert np.all(np.isfinite(out)) and np.all(out >= 0)
    assert math.isfinite(lp.estimate(2, POSE))


# ---------------------------------------------------------------------------- planner
def test_image_slots_leave_their_jpeg_loss_in_the_budget():
    """J = 0.02, L_t = 0.05 everywhere, L_th = 0.0305: 10 keys fit (10·0.05 + 20·0.02 = 0.9 ≤ 0.915), 11 do not."""
    planner = _planner(loss_map=_flat_map(0.05), image_slot_loss=0.02, in_slot_decision=False, loss_threshold=0.0305)
    plan = planner.plan(1000, (0.0, 0.0, 0.0))
    assert int((plan.schedule.x == 0).sum()) == 10
    assert plan.mean_predicted_loss <= 0.0305 + 1e-12
    blind = _planner(loss_map=_flat_map(0.05), in_slot_decision=False, loss_threshold=0.0305)  # J = 0: 18 keys
    assert int((blind.plan(1000, (0.0, 0.0, 0.0)).schedule.x == 0).sum()) == 18


def test_the_round_budget_ends_with_the_round():
    """Overspent in the round: its last slots are all images; the slots after it get a fresh budget."""
    planner = _planner(loss_map=_flat_map(0.05), round_slots=40, horizon_slots=30)
    planner.plan(100, None)
    planner.record_pose(100, 0.0, 0.0, 0.0)  # standing
    planner.record_pose(101, 0.2, 0.0, 0.0)  # moving: the round starts here
    for k in range(102, 130):
        planner.record_pose(k, 0.2, 0.0, 0.0)
        planner.record_action(k, 0)
    plan = planner.plan(130, (0.2, 0.0, 0.0))  # 28 of 40 round slots booked at 0.05 > 40·0.03 budget
    assert planner.budget.round_remaining(130) == 11
    n, spent = planner.budget.round_booked()
    assert n == 29 and spent > 0.03 * 40
    thr = plan.schedule.gain_threshold
    floor = np.quantile(rician_power_samples(1.0), DEEP_FADE_FRACTION)
    poses = planner.route.predict((0.2, 0.0, 0.0), 30, 0.1)
    mean = np.array([planner.link.mean_gain(p[:2]) for p in poses])
    np.testing.assert_allclose(thr[:11], floor * mean[:11])  # nothing left: an image in all but the deepest fades
    assert np.all(thr[11:] > 0.0)  # the next round starts with its own budget
    continuous = _planner(loss_map=_flat_map(0.05), horizon_slots=30)
    assert continuous.budget.round_remaining(130) is None


def test_probe_gap_lowers_the_threshold_to_the_median_fade():
    fading = rician_power_samples(1.0)
    planner = _planner(loss_map=_flat_map(0.02), probe_gap_slots=10, explore_image_fraction=0.0, horizon_slots=30)
    for k in range(1, 4):  # calibrated: no start-up exploration
        planner.observe(k, 0.0, 0.0, 0.0, 0.02)
    planner.record_action(100, 1)
    plan = planner.plan(101, (0.0, 0.0, 0.0))
    poses = planner.route.predict((0.0, 0.0, 0.0), 30, 0.1)
    mean = np.array([planner.link.mean_gain(p[:2]) for p in poses])
    thr = plan.schedule.gain_threshold
    median = np.quantile(fading, 0.5) * mean
    assert np.all(thr[9:] <= median[9:] * (1 + 1e-9))  # ≥ 10 slots since the last image: a median fade suffices
    assert np.any(thr[:5] > median[:5])  # right after an image the price alone decides


def test_gain_thresholds_take_one_exploration_fraction_per_slot():
    s = rician_power_samples(1.0)
    m, L = np.ones(4), np.full(4, 0.05)
    thr, _, _ = gain_thresholds(m, L, 0.0, 1e-9, s, np.array([0.0, 0.1, 0.5, 1.0]))
    floor = np.quantile(s, DEEP_FADE_FRACTION)  # never an image in the deepest fades
    np.testing.assert_allclose(thr, floor)
    thr, lam, _ = gain_thresholds(m, L, 1.0, 1e-9, s, np.array([0.0, 0.1, 0.5, 1.0]))
    assert lam == 0.0 and math.isinf(thr[0]) and thr[2] == pytest.approx(np.quantile(s, 0.5))


# ---------------------------------------------------------------------------- image-slot loss and replay
def test_jpeg_mr_loss_grows_with_compression_and_vanishes_under_the_virtual_view():
    rng = np.random.default_rng(0)
    frame = (rng.uniform(0, 255, (48, 64, 3))).astype(np.uint8)
    virtual = np.zeros((48, 64, 3), np.float32)
    real = np.ones((48, 64), np.float32)
    assert jpeg_mr_loss(frame, virtual, real, 30) > jpeg_mr_loss(frame, virtual, real, 95) > 0
    assert jpeg_mr_loss(frame, virtual, np.zeros((48, 64), np.float32), 30) == pytest.approx(0.0, abs=1e-7)


def test_loss_map_carries_the_image_slot_loss_through_json():
    lm = LossMap(image_loss=0.0067)
    lm.add(0.0, 0.0, 0.0, 0.02)
    assert LossMap.from_json(lm.to_json()).image_loss == 0.0067
    assert LossMap.from_json(LossMap().to_json()).image_loss is None
    with pytest.raises(ValueError):
        LossMap(image_loss=float("nan"))


def test_loss_map_carries_the_sample_offset_through_json():
    lm = LossMap(sample_offset=0.0031)
    assert LossMap.from_json(lm.to_json()).sample_offset == 0.0031
    assert LossMap.from_json(LossMap().to_json()).sample_offset is None and "sample_offset" not in LossMap().to_json()
    for bad in (float("nan"), float("inf"), 1.5):
        with pytest.raises(ValueError, match="sample_offset"):
            LossMap(sample_offset=bad)


def _rows(n: int = 120, burst: slice = slice(40, 70), seed: int = 0) -> list[dict]:
    rng = np.random.default_rng(seed)
    link = LinkBudget()
    rows = []
    for i in range(n):
        a = 0.3 * 0.1 * i
        gain = link.mean_gain((a, 0.0)) * float(rng.exponential())
        gs = 0.09 if burst.start <= i < burst.stop else 0.02
        rows.append({"slot": 5000 + i, "pose_a_m": a, "pose_b_m": 0.0, "pose_theta_rad": 0.0, "channel_gain": gain,
                     "energy_image_j": 1e-6 / gain * 1e-6, "energy_key_j": 1e-9 / gain * 1e-6,
                     "image_truth_loss": 0.007, "gs_truth_loss": gs, "gs_loss": "", "scored": int(i >= 5)})
    return rows


def test_replay_plays_the_in_slot_rule_and_scores_like_the_demo():
    slots = recorded_slots(_rows())
    assert len(slots) == 120 and slots[0].measured_gs_loss == 0.02  # no live sample in the run: the truth
    seen = []
    planner = _planner(loss_map=_flat_map(0.02), horizon_slots=40, probe_gap_slots=8)
    result = replay(slots, planner, loss_threshold=0.03, replan_every=5,
                    on_plan=lambda i, plan: seen.append((i, plan.schedule)))
    assert result.replans >= 120 // 5 and seen[0][0] == 0
    for i, s in enumerate(slots):  # every decision is the schedule's rule at the slot's gain
        sched = [sc for j, sc in seen if j <= i][-1]
        assert result.x[i] == int(s.gain >= sched.threshold(s.slot))
    scored = np.array([s.scored for s in slots])
    losses = np.where(result.x == 1, 0.007, [s.gs_truth_loss for s in slots])[scored]
    assert result.mean_loss == pytest.approx(losses.mean())
    assert result.images == int(result.x[scored].sum()) and result.regret >= 1.0 - 1e-9
    assert result.x[45:70].sum() >= 3  # the burst is found (probing) and answered with images
    again = replay(recorded_slots(_rows()), _planner(loss_map=_flat_map(0.02), horizon_slots=40, probe_gap_slots=8),
                   loss_threshold=0.03, replan_every=5)
    np.testing.assert_array_equal(again.x, result.x)  # deterministic


def test_a_slot_without_a_live_sample_reads_the_run_s_additive_jpeg_bias():
    """The JPEG's error adds to every sample (docs/scheduling.md, item 7): a slot the run did not sample is replayed at
    its truth + the run's median sample − truth, at low and high L alike (a ratio would read low at low L)."""
    rows = _rows()
    for r in rows[::3]:
        r["gs_loss"] = r["gs_truth_loss"] + 0.003  # sampled live: 0.02 → 0.023 and 0.09 → 0.093
    slots = {s.slot: s for s in recorded_slots(rows)}
    assert slots[5001].measured_gs_loss == pytest.approx(0.023)  # L = 0.02, not sampled live
    assert slots[5041].measured_gs_loss == pytest.approx(0.093)  # L = 0.09 (the burst), not sampled live
    assert slots[5003].measured_gs_loss == pytest.approx(0.023)  # sampled live: as measured


def test_replay_hindsight_studies_know_the_past_or_every_slot():
    """``observe_keys``: the forecast also learns the key slots' L (the planner's link and drift see only images);
    ``TruthLossPredictor(as_sampled=True)``: the L the server's samples read, not the L against the true frame."""
    from gsrmr_sim.replay import TruthLossPredictor

    rows = _rows()
    for r in rows:
        r["gs_loss"] = r["gs_truth_loss"] + 0.003  # every slot sampled live, 0.003 above the truth
    slots = recorded_slots(rows)
    planner = _planner(loss_map=_flat_map(0.02), horizon_slots=40, probe_gap_slots=8, loss_sample_offset=0.003)
    result = replay(slots, planner, loss_threshold=0.03, replan_every=5, observe_keys=True)
    assert planner.forecast.samples == len(slots) - 1  # every slot but the last (its sample arrives after the run)
    assert planner.forecast.key_loss(5045, (0.0, 0.0, 0.0)) == pytest.approx(0.09)  # corrected: against the frame
    assert 0 < result.images < len(slots)
    assert TruthLossPredictor(slots, as_sampled=True).estimate(5045, POSE) == pytest.approx(0.093)
    assert TruthLossPredictor(slots).estimate(5045, POSE) == 0.09


def test_replay_adds_the_robot_s_scene_change_images_at_the_recorded_gains():
    """A slot the run's robot found a change in: its change probe sends an image at the first fair fade of the
    wait, where the schedule's rule alone sent a key; without ``scene_changes`` nothing is added."""
    from gsrmr_robot.scene_change import ChangeProbe

    def run(changes=(), probe=None):
        planner = _planner(loss_map=_flat_map(0.02), horizon_slots=40, probe_gap_slots=8)
        return replay(recorded_slots(_rows()), planner, loss_threshold=0.03, replan_every=5, scene_changes=changes,
                      change_probe=probe, mean_gain=lambda pose: planner.link.mean_gain(pose[:2]))

    slots = recorded_slots(_rows())
    plain = run()
    keys = [i for i in range(20, len(slots) - 6) if not plain.x[i:i + 5].any()]
    assert keys, "the rule must leave a run of 5 key slots to test on"
    i = keys[0]
    wait = 5
    fades = ChangeProbe(LinkBudget().rician_k, wait).fades
    fair = [k for k in range(wait) if slots[i + k].gain >= LinkBudget().mean_gain(slots[i + k].pose[:2]) * fades[k]]
    assert fair, "the recorded gains must hold a fair fade in the wait"
    changed = run((slots[i].slot,), ChangeProbe(LinkBudget().rician_k, wait))
    np.testing.assert_array_equal(changed.x[:i], plain.x[:i])  # nothing changes before the change
    assert changed.x[i + fair[0]] == 1 and not changed.x[i:i + fair[0]].any()
    with pytest.raises(ValueError, match="change_probe"):
        replay(slots, _planner(loss_map=_flat_map(0.02)), loss_threshold=0.03, scene_changes=(slots[i].slot,))
