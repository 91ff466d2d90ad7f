"""Pure tests of the node suite's cores: energy ledger, MR composer, online planner (no ROS graph)."""

import math

import numpy as np
import pytest

from gsrmr_common.camera import CameraMount, Intrinsics
from gsrmr_common.jpeg import decode_jpeg, encode_jpeg
from gsrmr_common.link_model import LinkBudget, required_power_w
from gsrmr_common.pose2d import Pose2D
from gsrmr_common.wire import LEDGER_FIELDS, POSE_KEY_BITS, LedgerRow, MRSlotInfo, PoseKey, RealSource, UplinkFault
from gsrmr_robot.ledger import EnergyLedger
from gsrmr_robot.uplink_core import PoseHistory, SlotInputs, UplinkCore
from gsrmr_scheduler.loss_map import LossMap
from gsrmr_scheduler.planner import OnlinePlanner, PlannerConfig, RoutePredictor
from gsrmr_server.compose import MRComposer
from gsrmr_server.slot_core import ServerCore
from gsrmr_server.uplink import SlotUploads
from gsrmr_sim.demo import first_moving_slot
from gsrmr_sim.world.scene import load_scene
from gsrmr_sim.world.virtual import virtual_view
from gsrmr_splat.model import GaussianModel


def test_ledger_prices_actual_bits_and_upload_all_reference():
    led = EnergyLedger(required_power_w, 0.1, 1e6, 1e-9)
    g = 1e-6
    key = led.record(1, 0, 1e-6, None, g, 8000)
    img = led.record(2, 1, 0.1, 8000, g, 8000)
    assert key.bits_sent == POSE_KEY_BITS and img.bits_sent == POSE_KEY_BITS + 64000
    assert key.energy_j == pytest.approx(0.1 * required_power_w(POSE_KEY_BITS, g, 0.1, 1e6, 1e-9))
    assert img.energy_j == pytest.approx(0.1 * required_power_w(64192, g, 0.1, 1e6, 1e-9))
    totals = led.totals()
    assert totals["images_sent"] == 1 and totals["keys_only"] == 1
    assert totals["energy_upload_all_j"] == pytest.approx(2 * 0.1 * required_power_w(64000, g, 0.1, 1e6, 1e-9))
    assert totals["energy_ratio_vs_upload_all"] > 1
    dead = led.record(3, 1, 0.0, 8000, 0.0, 8000)  # a slot that cannot carry anything: inf, not NaN
    assert math.isinf(dead.energy_j) and led.totals()["undeliverable"] == 1
    assert math.isfinite(led.totals()["energy_j"])
    assert len(LEDGER_FIELDS) == len(EnergyLedger.row_dict(dead))


@pytest.fixture(scope="module")
def composer():
    scene = load_scene("sandbox")
    k = Intrinsics.from_fov(48, 36, math.radians(70))
    pts = np.array([[x, y, z] for x in (1.0, 1.5) for y in (-0.5, 0.0, 0.5) for z in (0.1, 0.3)], float)
    model = GaussianModel.from_points(pts, np.full((len(pts), 3), 0.7), scales_m=0.2, opacities=0.9)
    return MRComposer(model, virtual_view(scene), k, CameraMount(), (0.2, 0.2, 0.2))


def test_composer_sources_and_faults(composer):
    k = composer.intrinsics
    frame = np.full((k.height, k.width, 3), 200, np.uint8)
    key = PoseKey(7, -1.0, 0.0, 0.0)
    img = composer.compose(SlotUploads(7, key=key, jpeg=encode_jpeg(frame, 90)), None, 0.0)
    assert img.source == "image" and img.gs_loss is not None and img.gs_loss > 0
    assert img.mr.shape == (k.height, k.width, 3) and np.all(np.isfinite(img.mr))
    rnd = composer.compose(SlotUploads(8, key=key), None, 0.0)
    assert rnd.source == "render" and rnd.gs_loss is None
    bad = composer.compose(SlotUploads(9, key=key, jpeg=b"\xff\xd8garbage"), None, 0.0)
    assert bad.source == "fallback" and "corrupt_image" in bad.faults
    small = encode_jpeg(np.zeros((10, 10, 3), np.uint8), 90)
    wrong = composer.compose(SlotUploads(10, key=key, jpeg=small), None, 0.0)
    assert wrong.source == "fallback" and wrong.faults
    lost = composer.compose(SlotUploads(11), key, 0.0)  # no upload at all: render at the best estimate
    assert lost.source == "fallback" and lost.pose == key
    blind = composer.compose(SlotUploads(12), None, 0.0)  # never had a pose: background, still an image
    assert blind.source == "none" and blind.mr.shape == (k.height, k.width, 3)


def test_server_core_turns_a_slot_into_its_images_row_loss_sample_and_slot_info(composer):
    """The server's slot core: one uint8 image and one JPEG per slot, the ledger's numbers in the row, a loss
    sample only for an image slot with a key, the slot's MR slot info, and no score (that is the scorer's)."""
    k = composer.intrinsics
    core = ServerCore(composer, jpeg_quality=90)
    frame = np.full((k.height, k.width, 3), 200, np.uint8)
    key = PoseKey(7, -1.0, 0.0, 0.0)
    led = LedgerRow(7, 1, 0.02, 8 * 1000 + POSE_KEY_BITS, 1e-6, 0.03, 0.003, 8000, 0.0029, 12.5)
    out = core.process(SlotUploads(7, key=key, jpeg=encode_jpeg(frame, 90)), None, time_s=0.4, stamp_s=0.7,
                       ledger=led)
    assert out.mr_u8.dtype == np.uint8 and out.mr_u8.shape == (k.height, k.width, 3)
    assert out.jpeg is out.jpeg and decode_jpeg(out.jpeg).shape == out.mr_u8.shape  # encoded once
    r = out.row
    assert (r.slot, r.stamp_s, r.x, r.power_w, r.bytes_sent, r.energy_j, r.energy_upload_all_j) == \
        (7, 0.7, 1, 0.03, (8000 + POSE_KEY_BITS) // 8, 0.003, 0.0029)
    assert r.source == RealSource.IMAGE and r.pose_a_m == -1.0 and r.loss is None and r.gs_truth_loss is None
    assert out.loss_sample is not None and out.loss_sample.slot == 7 and out.loss_sample.loss == r.gs_loss > 0
    assert out.info == MRSlotInfo(7, RealSource.IMAGE, -1.0, 0.0, 0.0, 0.4)  # the pose and content time used
    lost = core.process(SlotUploads(8, faults=[UplinkFault.MISSING_KEY]), key, time_s=0.5, stamp_s=0.8,
                        scheduled_x=0)
    assert lost.row.x == 0 and lost.row.bytes_sent is None and lost.row.source == RealSource.FALLBACK
    assert lost.loss_sample is None and lost.row.faults == (UplinkFault.MISSING_KEY,)
    assert lost.info.source == RealSource.FALLBACK and lost.info.pose == PoseKey(8, -1.0, 0.0, 0.0)
    blind = core.process(SlotUploads(9), None, time_s=0.6, stamp_s=0.9)
    assert blind.info.source == RealSource.NONE and blind.info.pose is None


def test_uplink_core_decides_each_slot_and_books_it():
    """The robot's slot core: image only when x = 1 and a frame is fresh, a key whenever there is a pose,
    the schedule's default when none covers the slot, every slot in the ledger."""
    core = UplinkCore(LinkBudget(), 0.1, jpeg_quality=80, default_upload_image=True)
    frame = np.random.default_rng(0).integers(0, 255, (24, 32, 3), np.uint8)
    pose = (1.0, 2.0, 0.5)
    img = core.run_slot(SlotInputs(10, frame, 5_000_000_000, pose, (1, 0.02)))
    assert img.jpeg is not None and img.key == PoseKey(10, *pose) and img.scheduled and img.publish_row
    assert img.row.bits_sent == POSE_KEY_BITS + 8 * len(img.jpeg) and img.row.frame_stamp_s == 5.0
    key = core.run_slot(SlotInputs(11, frame, 5_100_000_000, pose, (0, 1e-6)))
    assert key.jpeg is None and key.row.bits_sent == POSE_KEY_BITS and key.row.upload_all_bits > 0
    default = core.run_slot(SlotInputs(12, frame, 5_200_000_000, pose, None))
    assert default.jpeg is not None and not default.scheduled and math.isnan(default.row.scheduled_power_w)
    blind = core.run_slot(SlotInputs(13, None, None, None, (1, 0.02)))
    assert blind.jpeg is None and blind.key is None and not blind.publish_row
    # an image asked for without a fresh frame: the key goes alone, and the row says key (x = 0), not image
    no_frame = core.run_slot(SlotInputs(14, None, None, pose, (1, 0.02)))
    assert no_frame.jpeg is None and no_frame.key == PoseKey(14, *pose) and no_frame.publish_row
    assert no_frame.x == 0 and no_frame.row.x == 0 and no_frame.row.held_back == 0
    assert no_frame.row.bits_sent == POSE_KEY_BITS
    unscheduled = core.run_slot(SlotInputs(15, None, None, pose, None))  # the default is an image: no frame, a key
    assert unscheduled.x == 0 and unscheduled.row.x == 0 and unscheduled.jpeg is None
    assert core.ledger.slots == 6 and core.ledger.images == 2

    history = PoseHistory()
    assert history.at(5) is None and not history.add(1, (math.nan, 0.0, 0.0))
    history.add(100, (0.0, 0.0, 0.0))
    history.add(200, (1.0, 0.0, 0.0))
    assert history.at(140) == (0.0, 0.0, 0.0) and history.at(160) == (1.0, 0.0, 0.0) and history.at(None)[0] == 1.0
    a, b, t = Pose2D(1.0, 2.0, math.pi / 2).compose((1.0, 0.0, math.pi))
    assert (a, b) == pytest.approx((1.0, 3.0)) and t == pytest.approx(-math.pi / 2)


def _keys_across_a_stall(max_age_ns: int | None, queued_first_ms: int = 0) -> list[tuple[int, tuple[float, float,
                                                                                                 float] | None]]:
    """The robot's no-frame keys (slot, pose) with odometry at 50 Hz, 0.3 m/s along x, and the node stalled from
    2.0 s to 4.0 s: its executor then runs the slot timer first, the queued odometry after it — after the oldest
    ``queued_first_ms`` of it (taken before the timer: they arrive now, stamped at the stall's start)."""
    history, keys, ms = PoseHistory(), [], 1_000_000
    for t_ms in range(0, 6000, 20):
        stalled = 2000 <= t_ms < 4000
        if not stalled:
            if t_ms == 4000:  # back: the timer's slot runs before the odometry queued meanwhile is taken
                for queued_ms in range(2000, 2000 + queued_first_ms, 20):
                    history.add(queued_ms * ms, (0.3 * queued_ms / 1000, 0.0, 0.0), 4000 * ms)
                keys.append((40, history.at(None, 4000 * ms, max_age_ns)))
                for queued_ms in range(2000 + queued_first_ms, 4000, 20):
                    history.add(queued_ms * ms, (0.3 * queued_ms / 1000, 0.0, 0.0), 4000 * ms)
            history.add(t_ms * ms, (0.3 * t_ms / 1000, 0.0, 0.0), t_ms * ms)
            if t_ms % 100 == 0 and t_ms != 4000:
                keys.append((t_ms // 100, history.at(None, t_ms * ms, max_age_ns)))
    return keys


def test_a_stalled_robot_sends_no_key_from_before_the_stall():
    """After a 2 s stall the newest pose is 2 s old: keyed with it, the slot puts the robot 0.6 m behind, and the next
    fresh key jumps 0.6 m in one slot — the server's pose-continuity rule (1.5 m/s top speed: 0.45 m) refuses it.
    With ``max_pose_age_s`` the stale slot has no key (the server renders at its extrapolation) and no key jumps."""
    from gsrmr_common.plausibility import PoseTrack

    def refused(keys) -> list[int]:
        track = PoseTrack(max_speed_mps=1.5, slot_s=0.1)
        return [slot for slot, pose in keys if pose is not None and not track.offer(slot, pose[0], pose[1])]

    stale = _keys_across_a_stall(None)
    assert dict(stale)[40] == pytest.approx((0.3 * 1.98, 0.0, 0.0))  # the pose from before the stall
    assert refused(stale)[:1] == [41]  # and the next one or two, until the reach grows past the gap
    fresh = _keys_across_a_stall(500_000_000)
    assert dict(fresh)[40] is None and dict(fresh)[41] == pytest.approx((0.3 * 4.1, 0.0, 0.0))
    assert refused(fresh) == []
    assert PoseHistory().at(None, 0, 1) is None
    # the oldest queued odometry taken before the timer: fresh by arrival, 1.9 s old by its stamp — no key either
    first_in_queue = _keys_across_a_stall(500_000_000, queued_first_ms=100)
    assert dict(first_in_queue)[40] is None and refused(first_in_queue) == []
    # a driver stamping on another clock (more than a minute off the node's) is judged by arrival alone
    other_clock = PoseHistory()
    other_clock.add(5, (1.0, 2.0, 0.0), 1000 * 1_000_000_000)
    assert other_clock.at(None, 1000_100_000_000, 500_000_000) == (1.0, 2.0, 0.0)
    assert other_clock.at(None, 1000_600_000_000, 500_000_000) is None


def test_route_predictor_follows_the_loop():
    scene = load_scene("sandbox")
    pred = RoutePredictor(scene.route.waypoints, scene.route.speed_mps)
    start = scene.route.waypoints[0]
    poses = pred.predict((start[0], start[1], 0.0), 50, 0.1)
    assert poses.shape == (50, 3)
    steps = np.hypot(*np.diff(poses[:, :2], axis=0).T)
    assert np.allclose(steps[steps > 0.005], scene.route.speed_mps * 0.1, atol=0.02)
    lap = pred.predict(None, int(round(pred.path.length_m / (scene.route.speed_mps * 0.1))), 0.1)
    assert np.hypot(*(lap[-1, :2] - np.asarray(start))) < 0.05  # one lap comes back to the start


def test_planner_meets_budget_carries_it_over_and_detects_drift():
    scene = load_scene("sandbox")
    lm = LossMap(prior=0.02)
    config = PlannerConfig(loss_threshold=0.03, horizon_slots=40, slot_s=0.1, image_bits=67200, pose_bits=192,
                           drift_threshold=0.05, drift_window_samples=2, trust_loss_map=True)
    planner = OnlinePlanner(config, RoutePredictor(scene.route.waypoints, scene.route.speed_mps), lm, LinkBudget())
    first = planner.plan(1001, None)  # the schedule from slot 1001 on
    assert first.feasible and first.images == 0  # prior 0.02 < L_th: every slot can be a key
    assert first.mean_predicted_loss <= 0.03 + 1e-12
    # Losses turn out much higher than predicted: drift is detected after drift_window samples.
    p = RoutePredictor(scene.route.waypoints, scene.route.speed_mps).predict(None, 3, 0.1)
    assert planner.observe(1001, *p[0], 0.3) is False
    assert planner.observe(1002, *p[1], 0.3) is True
    # 40 key slots at predicted 0.02 were spent: the next budget still lets the run's mean meet L_th.
    second = planner.plan(1041, None)
    assert second.budget == pytest.approx((0.03 * 80 - 40 * 0.02) / 40)
    assert second.schedule.first_slot == 1041 and len(second.schedule.x) == 40
    assert np.all(np.isfinite(second.schedule.power_w)) and np.all(second.schedule.power_w >= 0)


def test_planner_charges_key_slots_at_the_reported_pose_and_backs_off_by_the_margin():
    scene = load_scene("sandbox")
    lm = LossMap(prior=0.02)
    lm.add(0.0, 0.0, 0.0, 0.09)  # one costly place the plan's predicted poses do not visit
    config = PlannerConfig(loss_threshold=0.03, horizon_slots=40, slot_s=0.1, image_bits=67200, pose_bits=192,
                           loss_margin=0.2, trust_loss_map=True)
    planner = OnlinePlanner(config, RoutePredictor(scene.route.waypoints, scene.route.speed_mps), lm, LinkBudget())
    first = planner.plan(1001, None)  # the schedule from slot 1001 on
    assert first.budget == pytest.approx(0.024)  # L_th·(1 − margin)
    x = first.schedule.x
    reported = [k for k in range(1001, 1041) if x[k - 1001] == 0][:10]
    for k in reported:  # the robot was elsewhere than planned in 10 key slots: charged at its real pose
        planner.record_pose(k, 0.0, 0.0, 0.0)
    keys = int((x == 0).sum())
    planned = [planner.forecast.predicted(k) for k in range(1001, 1041) if x[k - 1001] == 0 and k not in reported]
    second = planner.plan(1041, None)
    spent = 10 * lm.predict(0.0, 0.0, 0.0) + sum(planned)
    assert keys == 40 and lm.predict(0.0, 0.0, 0.0) > 0.05
    assert second.budget == pytest.approx((0.024 * 80 - spent) / 40)


def test_demo_round_starts_at_the_first_slot_whose_pose_key_moved():
    def row(source, pose):
        a, b, t = pose if pose else (None, None, None)
        return {"source": source, "pose_a_m": a, "pose_b_m": b, "pose_theta_rad": t}

    rest = (-1.0, -1.1, 0.0)
    rows = [row("fallback", None), row("image", None), row("render", rest), row("image", rest),
            row("fallback", (5.0, 5.0, 0.0)),  # an extrapolated fallback pose is not motion
            row("render", (-1.0, -1.1, 0.005)), row("render", (-0.98, -1.1, 0.0))]
    assert first_moving_slot(rows) == 6
    assert first_moving_slot(rows[:6]) is None
    assert first_moving_slot([row("render", rest), row("render", (-1.0, -1.1, 0.02))]) == 1  # a turn in place
