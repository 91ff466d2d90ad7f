"""Nothing on the graph is trusted blindly — the pure cores (no rclpy): known writers by GID, plausibility rules, the
Rician gain band, robust aggregation, the robot's hold-back without trusted acknowledgements, the private DDS profile.

The ROS half (subscriptions, the graph, whole stacks lied to by a rogue participant) is test_hostile_graph.py.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
import stat

import numpy as np
import pytest

from gsrmr_common.channel import ChannelModel
from gsrmr_common.channel_band import (
    GainBand,
    median_alarm_probability,
    rician_power_cdf,
    rician_power_quantile,
)
from gsrmr_common.metrics import mr_loss
from gsrmr_common.plausibility import (
    MR_LOSS_MAX,
    REDELIVERED,
    LossSampleCheck,
    PoseTrack,
    ScheduleLimits,
    ledger_image_sent,
    ledger_problem,
    schedule_problem,
)
from gsrmr_common.wire import POSE_KEY_BITS, LedgerRow, LossSample, ScheduleMsg
from gsrmr_common.writer_admission import (
    Endpoint,
    FloodBreaker,
    RateLimit,
    SeqTracker,
    Verdict,
    WriterGate,
    join_node_name,
    resolve_writer_name,
    writer_list_problem,
)
from gsrmr_robot.robot_params import RobotParameters
from gsrmr_robot.uplink_backlog import UplinkBacklog
from gsrmr_scheduler.loss_map import LossMap
from gsrmr_scheduler.loss_predictor import MAX_LOG_DEVIATION, LossPredictor
from gsrmr_scheduler.scheduler_params import SchedulerParameters
from gsrmr_server.server_params import ServerParameters

ROBOT, SERVER, ROGUE, RELAY = b"\x01" * 16, b"\x02" * 16, b"\x03" * 16, b"\x04" * 16
TOPIC = "uplink/pose_key"


# ------------------------------------------------------------------------------------------------ names

def test_writer_names_resolve_in_the_readers_namespace():
    assert resolve_writer_name("gsrmr_robot", "/") == "/gsrmr_robot"
    assert resolve_writer_name("gsrmr_robot", "/robot2") == "/robot2/gsrmr_robot"  # a fleet reads its own robot
    assert resolve_writer_name("/robot/gsrmr_robot", "/robot2") == "/robot/gsrmr_robot"
    assert resolve_writer_name("ns/gsrmr_robot", "/a") == "/a/ns/gsrmr_robot"
    assert resolve_writer_name("*", "/a") == "*"
    assert join_node_name("/", "gsrmr_server") == "/gsrmr_server"
    assert join_node_name("/robot1", "gsrmr_server") == "/robot1/gsrmr_server"
    for bad in ("", "x/", "a//b"):
        with pytest.raises(ValueError):
            resolve_writer_name(bad, "/")
    assert writer_list_problem("robot_writers", []) is not None
    assert writer_list_problem("robot_writers", ["gsrmr_robot", "x/"]) is not None
    assert writer_list_problem("robot_writers", ["gsrmr_robot", "/robot/gsrmr_uplink_relay", "*"]) is None


def test_writer_lists_are_read_only_string_lists_of_every_node():
    for cls in (RobotParameters, ServerParameters, SchedulerParameters):
        lists = [f.name for f, _ in cls.specs() if f.name.endswith(("_writers", "_readers"))]
        assert lists, cls
        for name in lists:
            assert name in cls.read_only_names(), (cls, name)
            assert cls.problem(name, ["gsrmr_robot", "/a/b"]) is None
            assert "list of strings" in cls.problem(name, [1.0])
            assert "at least one" in cls.problem(name, [])
        assert "live_parameter_changes" in cls.read_only_names() and cls().live_parameter_changes is False
    with pytest.raises(ValueError, match="robot_writers"):
        ServerParameters().with_values({"robot_writers": ["gsrmr_robot/"]})
    assert ServerParameters().with_values({"robot_writers": ["a", "b"]}).robot_writers == ("a", "b")
    assert ServerParameters().ros_values()["robot_writers"] == ["gsrmr_robot"]


# ------------------------------------------------------------------------------------------------ the gate

def _gate(*writers: str, namespace: str = "/", hold_s: float = 1.0, hold_max: int = 32) -> WriterGate:
    """A gate of one topic, its writers listed, no rate limit."""
    gate = WriterGate(namespace, hold_s=hold_s, hold_max=hold_max)
    gate.add_topic(TOPIC, writers or ("gsrmr_robot",))
    return gate


def test_listed_writers_are_admitted_others_refused_and_named():
    gate = _gate("gsrmr_robot")
    gate.update(TOPIC, [Endpoint(ROBOT, "/gsrmr_robot"), Endpoint(ROGUE, "/hostile")])
    assert gate.check(TOPIC, ROBOT, 0.0) is Verdict.ADMIT
    for _ in range(3):
        assert gate.check(TOPIC, ROGUE, 0.0) is Verdict.REFUSE
    assert gate.refused[(TOPIC, "/hostile", "unlisted")] == 3
    assert gate.refused_by_writer() == {"/hostile": {f"{TOPIC} unlisted": 3}}
    assert gate.problems() == [f"ignored writer /hostile on {TOPIC} (3 messages)"]
    assert gate.admitted[TOPIC] == 1


def test_an_open_topic_admits_any_writer_a_namespaced_one_only_its_own():
    gate = _gate("*")
    gate.update(TOPIC, [Endpoint(ROGUE, "/hostile")])
    assert gate.check(TOPIC, ROGUE, 0.0) is Verdict.ADMIT
    assert gate.check(TOPIC, b"\x09" * 16, 0.0) is Verdict.ADMIT  # not even in the graph: open means open
    fleet = _gate("gsrmr_robot", namespace="/robot2")
    fleet.update(TOPIC, [Endpoint(ROBOT, "/robot1/gsrmr_robot"), Endpoint(SERVER, "/robot2/gsrmr_robot")])
    assert fleet.check(TOPIC, SERVER, 0.0) is Verdict.ADMIT
    assert fleet.check(TOPIC, ROBOT, 0.0) is Verdict.REFUSE  # robot 1 writes nothing robot 2's server takes


def test_a_writer_unknown_to_the_graph_is_held_then_admitted_or_refused():
    gate = _gate("gsrmr_robot", hold_s=1.0, hold_max=3)
    assert gate.check(TOPIC, ROBOT, 0.0) is Verdict.HOLD  # its first message before discovery named it
    gate.hold(TOPIC, ROBOT, "key 1", 0.0)
    gate.hold(TOPIC, ROGUE, "rogue key", 0.0)
    assert gate.release(0.5) == [] and gate.held == 2  # still unknown, not yet too old
    gate.update(TOPIC, [Endpoint(ROBOT, "/gsrmr_robot"), Endpoint(ROGUE, "/_NODE_NAME_UNKNOWN_")])
    assert gate.writer_name(TOPIC, ROGUE) is None  # Fast DDS has the endpoint, not yet its node's name
    assert gate.release(0.6) == [(TOPIC, "key 1")] and gate.held == 1
    assert gate.release(1.2) == [] and gate.held == 0
    assert gate.refused[(TOPIC, "gid:030303030303…", "unknown")] == 1
    for i in range(5):  # a bounded queue: the oldest are refused past hold_max
        gate.hold(TOPIC, SERVER, i, 2.0)
    assert gate.held == 3 and gate.refused[(TOPIC, "gid:020202020202…", "held_over")] == 2


def test_a_restarted_writer_is_readmitted_two_live_endpoints_are_an_alarm():
    gate = _gate("gsrmr_robot")
    gate.update(TOPIC, [Endpoint(ROBOT, "/gsrmr_robot")])
    new = b"\x05" * 16
    assert gate.check(TOPIC, new, 0.0) is Verdict.HOLD  # the restarted robot: a new GID, not in the graph yet
    gate.update(TOPIC, [Endpoint(ROBOT, "/gsrmr_robot"), Endpoint(new, "/gsrmr_robot")])  # old lease not expired
    assert gate.check(TOPIC, new, 0.0) is Verdict.ADMIT
    assert gate.alarms[(TOPIC, "/gsrmr_robot")] == 1
    assert any("two live endpoints under /gsrmr_robot" in p for p in gate.problems())
    gate.update(TOPIC, [Endpoint(new, "/gsrmr_robot")])  # the old one is gone: no alarm now, the count stays
    assert not gate.alarm_gids and gate.alarms[(TOPIC, "/gsrmr_robot")] == 1
    assert gate.check(TOPIC, ROBOT, 0.0) is Verdict.HOLD  # the dead GID is no longer known


def test_a_writers_later_message_is_known_to_wait_behind_its_held_ones():
    gate = _gate("gsrmr_robot")
    gate.hold(TOPIC, ROBOT, "seq 3", 0.0)
    assert gate.holding(TOPIC, ROBOT) and not gate.holding(TOPIC, ROGUE) and not gate.holding("other", ROBOT)
    gate.update(TOPIC, [Endpoint(ROBOT, "/gsrmr_robot")])
    assert gate.release(0.1) == [(TOPIC, "seq 3")] and not gate.holding(TOPIC, ROBOT)


def test_every_writer_endpoint_is_rate_limited():
    gate = WriterGate("/")
    gate.add_topic(TOPIC, ["gsrmr_robot", "gsrmr_uplink_relay"], rate_hz=40.0, burst=10.0)
    gate.update(TOPIC, [Endpoint(ROBOT, "/gsrmr_robot"), Endpoint(RELAY, "/gsrmr_uplink_relay")])
    verdicts = [gate.check(TOPIC, ROBOT, 1e-4 * i) for i in range(1000)]  # a 10 kHz flood for 0.1 s
    assert verdicts.count(Verdict.ADMIT) == 10 + 3  # the burst, then 40/s: tokens at 25, 50, 75 ms
    assert gate.refused[(TOPIC, "/gsrmr_robot", "rate")] == 1000 - 13
    assert gate.check(TOPIC, RELAY, 0.1) is Verdict.ADMIT  # another endpoint has its own bucket
    bucket = RateLimit(10.0, 2.0)
    assert [bucket.take(t) for t in (0.0, 0.0, 0.0, 0.1, 0.15, 0.2)] == [True, True, False, True, False, True]
    assert all(RateLimit(0.0, 1.0).take(0.0) for _ in range(100))


def test_a_flood_trips_the_breaker_a_legit_rate_does_not():
    breaker = FloodBreaker(refusals=200, window_s=1.0, pause_s=1.0)
    assert not any(breaker.refused(TOPIC, "/w", 0.1 * i) for i in range(1000))  # 10 refused per second: no flood
    trips = [breaker.refused(TOPIC, "/rogue", 200 + 1e-4 * i) for i in range(1000)]  # 10 kHz for 0.1 s
    assert trips.count(True) == 5 and trips.index(True) == 199  # every 200th refusal
    assert breaker.trips == {(TOPIC, "/rogue"): 5}
    assert not breaker.refused("other", "/rogue", 200.1)  # per topic
    with pytest.raises(ValueError):
        FloodBreaker(refusals=0)


def test_seq_must_grow_per_writer_endpoint():
    seq = SeqTracker(keep=2)
    assert seq.accept(ROBOT, 5) and seq.accept(ROBOT, 6)
    assert not seq.accept(ROBOT, 6) and not seq.accept(ROBOT, 3)  # a repeat, a replayed older schedule
    assert seq.check(ROBOT, 6) == "repeat" and seq.check(ROBOT, 3) == "older" and seq.check(ROBOT, 7) == "new"
    assert seq.accept(SERVER, 1)  # a restarted scheduler (new endpoint) starts afresh
    assert seq.accept(ROGUE, 100) and seq.accept(ROBOT, 1)  # keep=2: ROBOT forgotten behind SERVER and ROGUE


# ------------------------------------------------------------------------------------------------ plausibility

def test_the_mr_loss_bound_is_the_metrics():
    assert round(MR_LOSS_MAX, 12) == 1.2
    rng = np.random.default_rng(0)
    a = rng.integers(0, 2, (32, 32, 3)).astype(np.float64)
    worst = mr_loss(a, 1.0 - a)  # a binary image against its negative: L1 = 1 and SSIM ≈ −1
    assert 1.0 < worst <= MR_LOSS_MAX


def test_loss_samples_in_range_once_per_image_slot_at_the_reported_key():
    check = LossSampleCheck(keep_slots=3)
    pose = (1.0, 2.0, 0.5)
    assert check.problem(LossSample(10, *pose, 5.0), True, pose) == "loss_range"
    assert check.problem(LossSample(10, *pose, 0.02), False, pose) == "loss_key_slot"
    assert check.problem(LossSample(10, *pose, 0.02), None, pose) == "loss_unledgered"
    assert check.problem(LossSample(10, 4.0, 2.0, 0.5, 0.02), True, pose) == "loss_pose"
    assert check.problem(LossSample(10, *pose, 0.0), True, None) is None  # 0 is a loss; no key known: no pose rule
    assert check.problem(LossSample(10, *pose, 0.0), True, pose) == REDELIVERED  # the same sample again: a resubscribed
    assert check.problem(LossSample(10, *pose, 0.02), True, pose) == "loss_repeat"  # reader, no lie; another: one
    for slot in (11, 12, 13):
        assert check.problem(LossSample(slot, *pose, 0.02), True, pose) is None
    assert check.problem(LossSample(10, *pose, 0.02), True, pose) is None  # forgotten past keep_slots


def test_a_schedule_is_bounded_near_now_within_the_radios_power():
    limits = ScheduleLimits(max_slots=100, max_ahead_slots=50, max_power_w=0.1)

    def sched(first: int, n: int, power: float = 1e-3) -> ScheduleMsg:
        return ScheduleMsg(first, 0.1, 1, np.ones(n, np.int8), np.full(n, power))

    assert schedule_problem(sched(1001, 100), 1000, limits) is None
    assert schedule_problem(sched(1001, 101), 1000, limits) == "schedule_length"
    assert schedule_problem(sched(1050, 10), 1000, limits) is None
    assert schedule_problem(sched(1051, 10), 1000, limits) == "schedule_future"
    assert schedule_problem(sched(990, 10), 1000, limits) == "schedule_stale"
    assert schedule_problem(sched(995, 10), 1000, limits) is None  # still covers now
    assert schedule_problem(sched(1001, 10, power=0.05), 1000, limits) is None  # "50 mW" is within a radio's reach
    assert schedule_problem(sched(1001, 10, power=0.2), 1000, limits) == "schedule_power"


def test_ledger_rows_name_a_slot_near_now_with_sane_values():
    row = LedgerRow(1000, 1, 0.0, 64_000, 1e-6, 1e-3, 1e-4, 64_000, 1e-4)
    assert ledger_problem(row, 1010) is None
    assert ledger_problem(row, 1100) == "ledger_slot"
    assert ledger_problem(LedgerRow(1000, 2, 0.0, 0, 1e-6, 0, 0, 0, 0), 1000) == "ledger_values"
    assert ledger_problem(LedgerRow(1000, 0, 0.0, 0, 1e-6, 0, 0, 0, 0, uplink_rate_bps=-1.0), 1000) == "ledger_values"
    # an image is what left: x = 1 with the pose key's bits only (no frame to send, an older robot) is a key
    assert ledger_image_sent(row) == 1
    assert ledger_image_sent(LedgerRow(1000, 1, 0.0, POSE_KEY_BITS, 1e-6, 1e-3, 1e-4, 64_000, 1e-4)) == 0
    assert ledger_image_sent(LedgerRow(1000, 0, 0.0, 64_000, 1e-6, 1e-3, 1e-4, 64_000, 1e-4)) == 0


def test_pose_keys_move_within_the_top_speed_a_relocalisation_needs_agreeing_keys():
    track = PoseTrack(max_speed_mps=1.0, slot_s=0.1, slack_m=0.3, relocalise_keys=5)
    x = 0.0
    for k in range(20):  # driving at 0.5 m/s
        assert track.offer(k, x, 0.0)
        x += 0.05
    assert not track.offer(20, x + 3.0, 0.0)  # across the room in one slot
    assert track.offer(21, x + 0.05, 0.0)  # the real robot carries on
    assert track.offer(15, x - 0.25, 0.0)  # a late key of an earlier slot, where the robot was then
    rng = np.random.default_rng(1)
    rogue_taken = 0
    for i in range(200):  # random keys across a 10 m room beside the robot's, 1 per slot each
        x += 0.05
        assert track.offer(22 + i, x, 0.0)
        a, b = rng.uniform(-5, 5, 2)
        if track.offer(22 + i, a, b):  # taken only within the slack of where the robot is
            assert math.hypot(a - x, b) <= 0.3
            rogue_taken += 1
    assert rogue_taken <= 2 and track.relocalisations == 0
    track = PoseTrack(max_speed_mps=1.0, slot_s=0.1)
    assert track.offer(0, 0.0, 0.0)
    for k in range(1, 5):  # a relocalisation: 4 keys at the new place are refused, the 5th agreeing one accepted
        assert not track.offer(k, 4.0 + 0.01 * k, 1.0)
    assert track.offer(5, 4.05, 1.0) and track.relocalisations == 1
    assert track.offer(6, 4.06, 1.0)
    assert track.reach_m(10) == pytest.approx(1.3)


# ------------------------------------------------------------------------------------------------ the gain band

def test_the_rician_cdf_and_quantiles_are_scipys():
    scipy_stats = pytest.importorskip("scipy.stats")
    for k in (0.0, 1.0, 5.0):
        for x in (1e-6, 1e-3, 0.1, 1.0, 3.0, 10.0):
            ref = scipy_stats.ncx2.cdf(2 * (k + 1) * x, 2, 2 * k) if k > 0 else 1 - math.exp(-x)
            assert rician_power_cdf(x, k) == pytest.approx(ref, rel=1e-9, abs=1e-300)
            sf = scipy_stats.ncx2.sf(2 * (k + 1) * x, 2, 2 * k) if k > 0 else math.exp(-x)
            assert rician_power_cdf(x, k, upper=True) == pytest.approx(sf, rel=1e-7)
        for p in (1e-7, 0.05, 0.5, 0.95, 1 - 1e-7):
            assert rician_power_cdf(rician_power_quantile(p, k), k) == pytest.approx(p, rel=1e-6)
    assert median_alarm_probability(25, 0.05) < 1e-10


def test_the_gain_band_raises_no_alarm_on_the_true_channel_and_catches_the_lies():
    model = ChannelModel(-30.0, 3.0, 1.0, seed=11)
    band = GainBand(k_factor=1.0, pathloss_exponent=3.0)
    assert band.false_alarm_per_sample() < 3e-7
    assert 10 * math.log10(band.high) == pytest.approx(10.58, abs=0.01)
    assert 10 * math.log10(band.low) == pytest.approx(-68.67, abs=0.01)
    d = np.full(200_000, 9.0)
    gains, mean = model.gains(d), float(model.pathloss(d[:1])[0])
    alarms = [band.problem(g, mean, 9.0) for g in gains]
    assert alarms.count(None) == len(gains)  # 200k clean samples: none refused (expected 0.04)
    assert np.mean(gains / mean) == pytest.approx(1.0, abs=0.01)
    lie = GainBand(k_factor=1.0, pathloss_exponent=3.0)
    assert lie.problem(gains[0] * 1000, mean, 9.0) == "gain_band"  # ×1000: beyond any fade in one sample
    low = GainBand(k_factor=1.0, pathloss_exponent=3.0)
    verdicts = [low.problem(g / 1000, mean, 9.0) for g in gains[:40]]
    assert verdicts[:12].count(None) == 12  # ÷1000 one at a time: deep fades happen
    assert set(verdicts[25:]) == {"gain_bias"}  # a lasting ÷1000: the window's median leaves its band
    recovered = [low.problem(g, mean, 9.0) for g in gains[40:80]]
    assert recovered[-1] is None and recovered.count("gain_bias") <= 13
    # a position error of the robot widens the band: 1 m at 9 m is (10/9)^3 in the mean gain
    assert band.widening(9.0) == pytest.approx((10 / 9) ** 3)
    assert band.problem(mean * band.high * 1.3, mean, 9.0) is None


# ------------------------------------------------------------------------------------------------ robust aggregation

def test_one_outlier_moves_a_loss_map_cell_by_a_bounded_step_a_lasting_change_is_followed():
    m = LossMap()
    for _ in range(4):
        m.add(1.0, 1.0, 0.0, 0.01)
    m.add(1.0, 1.0, 0.0, MR_LOSS_MAX)  # one outlier of the metric's maximum (120× the cell)
    assert m.predict(1.0, 1.0, 0.0) == pytest.approx(0.01 + 0.5 * (0.2 - 0.01))  # counted as 20× the cell
    before = m.predict(1.0, 1.0, 0.0)
    m.add(1.0, 1.0, 0.0, 0.0)
    assert m.predict(1.0, 1.0, 0.0) == pytest.approx(before + 0.5 * (before / 20 - before))
    for _ in range(6):  # the world changed: 5× the first level for good
        m.add(1.0, 1.0, 0.0, 0.05)
    assert m.predict(1.0, 1.0, 0.0) == pytest.approx(0.05, rel=0.05)
    unbounded = LossMap(outlier_factor=1e9)
    for _ in range(4):
        unbounded.add(1.0, 1.0, 0.0, 0.01)
    unbounded.add(1.0, 1.0, 0.0, MR_LOSS_MAX)
    assert unbounded.predict(1.0, 1.0, 0.0) > 0.5  # what the bound prevents
    with pytest.raises(ValueError):
        LossMap(outlier_factor=0.5)


def test_one_outlier_moves_the_loss_predictor_little_a_lasting_change_is_followed():
    seed = LossMap()
    seed.add(0.0, 0.0, 0.0, 0.03)
    pred = LossPredictor(seed)
    for k in range(20):
        pred.observe(k, (0.0, 0.0, 0.0), 0.036)  # steady 1.2× the seed
    level = pred.level
    pred.observe(20, (0.0, 0.0, 0.0), 0.0)  # a zero: ln(1e-4 / 0.03) = −5.7 without the clip
    assert pred.log_ratio(np.array([20]))[0] == pytest.approx(level - MAX_LOG_DEVIATION)
    assert pred.level == pytest.approx(level)
    for k in range(21, 60):  # a lasting 5×
        pred.observe(k, (0.0, 0.0, 0.0), 0.15)
    assert math.exp(pred.level) == pytest.approx(5.0, rel=0.01)


# ------------------------------------------------------------------------------------------------ the robot's hold-back

def test_without_trusted_acks_an_image_is_delivered_by_the_throughput_model():
    b = UplinkBacklog(stale_after_s=1.0)
    b.sent(64_000, 0.0)
    b.acked(0.032)  # a trusted acknowledgement: 2 Mbit/s measured
    b.acks_trusted = False  # a stranger's reliable reader matched: acks say nothing
    b.sent(64_000, 1.0)
    assert b.queued(1.01)  # 64 kbit at 2 Mbit/s: 32 ms on its way
    assert not b.queued(1.033) and not b.waiting and b.model_deliveries == 1
    fresh = UplinkBacklog(acks_trusted=False)
    fresh.sent(64_000, 0.0)
    assert not fresh.queued(0.0)  # no throughput estimate yet: nothing held back


def test_the_dds_profile_is_written_where_no_other_user_can_replace_it(tmp_path):
    from gsrmr_robot.dds_profile import private_dir, uplink_profile_path

    env = {"XDG_RUNTIME_DIR": str(tmp_path)}
    path = uplink_profile_path(env)
    assert path.parent == tmp_path / "gsrmr"
    assert stat.S_IMODE(path.parent.stat().st_mode) == 0o700 and stat.S_IMODE(path.stat().st_mode) == 0o600
    assert "heartbeat_period" in path.read_text() and path.parent.stat().st_uid == os.getuid()
    assert uplink_profile_path(env) == path  # rewritten in place (atomic rename), no stray files
    assert sorted(p.name for p in path.parent.iterdir()) == [path.name]
    loose = tmp_path / "loose"
    (loose / "gsrmr").mkdir(parents=True, mode=0o755)
    os.chmod(loose / "gsrmr", 0o755)  # another user could write here: not used
    assert private_dir({"XDG_RUNTIME_DIR": str(loose)}) != loose / "gsrmr"
    linked = tmp_path / "linked"
    linked.mkdir()
    (linked / "gsrmr").symlink_to(tmp_path / "gsrmr")  # a link planted under the name: not followed
    chosen = private_dir({"XDG_RUNTIME_DIR": str(linked)})
    assert chosen != linked / "gsrmr" and not Path(chosen).is_symlink()
