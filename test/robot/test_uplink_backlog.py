"""The uplink backlog (pure): the robot holds images back while one is queued, the scheduler plans fewer."""

from __future__ import annotations

from dataclasses import replace
import math
from pathlib import Path

import numpy as np
import pytest

from gsrmr_common.link_model import LinkBudget
from gsrmr_robot.dds_profile import HEARTBEAT_PERIOD_NS, use_uplink_profile
from gsrmr_robot.uplink_backlog import UplinkBacklog
from gsrmr_robot.uplink_core import SlotInputs, UplinkCore
from gsrmr_scheduler.loss_map import LossMap
from gsrmr_scheduler.planner import OnlinePlanner, PlannerConfig, RoutePredictor
from gsrmr_scheduler.planner.link_cap import (
    DELIVERY_GRACE_SLOTS,
    DELIVERY_WINDOW_IMAGES,
    LINK_WINDOW_SLOTS,
    PROBE_IMAGE_FRACTION,
    LinkCap,
    cap_planned_images,
)
from gsrmr_scheduler.slot_price import cap_expected_images, rician_power_samples

BLIND = PlannerConfig(loss_threshold=0.0, horizon_slots=40, slot_s=0.1, image_bits=64_000, pose_bits=192)


def test_backlog_queues_until_acked_and_measures_the_rate():
    b = UplinkBacklog(stale_after_s=1.0, window_s=5.0)
    assert not b.queued(0.0) and math.isnan(b.rate_bps)
    b.sent(64_000, 10.0)
    assert b.waiting and b.queued(10.05) and b.queued_for_s(10.05) == pytest.approx(0.05)
    b.acked(10.032)  # 64 kbit in 32 ms: 2 Mbit/s
    assert not b.queued(10.04) and b.rate_bps == pytest.approx(2e6)
    b.sent(64_000, 11.0)
    b.acked(11.128)  # the window: 128 kbit over the 160 ms the two images waited (not the 1.128 s since the first)
    assert b.rate_bps == pytest.approx(128_000 / 0.160)
    b.acked(12.0)  # nothing queued: no sample
    assert b.acked_images == 2
    rate = b.rate_bps
    b.sent(64_000, 13.0)
    b.acked(15.0)  # acknowledged after an outage: no throughput sample, the rate after it is what it was
    assert b.rate_bps == pytest.approx(rate) and b.last_ack_delay_s == pytest.approx(2.0) and not b.waiting
    b.sent(64_000, 17.0)
    b.acked(17.1)  # the first two images are older than the window: this one alone
    assert b.rate_bps == pytest.approx(640_000)
    with pytest.raises(ValueError):
        UplinkBacklog(window_s=0.0)


def test_backlog_stops_holding_back_after_stale_time():
    b = UplinkBacklog(stale_after_s=0.5)
    b.sent(8000, 0.0)
    assert b.queued(0.49) and not b.queued(0.5)
    assert b.waiting  # still polled for its acknowledgement
    # the robot sends again into the link that does not answer — at most one image per stale_after_s: the new one
    # holds the next back for stale_after_s again
    b.sent(8000, 0.6)
    assert b.queued(0.7) and b.queued(1.09) and not b.queued(1.1)
    assert b.queued_for_s(1.1) == pytest.approx(1.1)  # the oldest has waited since 0.0
    b.acked(1.2)  # the link is back: no throughput sample from what waited through the outage
    assert not b.waiting and math.isnan(b.rate_bps)
    with pytest.raises(ValueError):
        UplinkBacklog(stale_after_s=0.0)


TAU_S = 0.1  # slot


def _fifo_link(link_bps: float, other_bps: float, image_bits: int, slots: int, asks=lambda k: True,
               hold: bool = True, ack_latency_ms: int = 0) -> tuple[UplinkBacklog, list[tuple]]:
    """The robot's slots on a FIFO rate limit of ``link_bps`` that also carries ``other_bps`` of steady traffic
    (keys, ledger rows, heartbeats): an image is acknowledged once the link has served it and everything queued
    before it (``ack_latency_ms`` later). The robot asks :meth:`UplinkBacklog.queued` at every slot's start and
    sends an image when the plan asks for one (``asks(k)``) and none is queued. Returns the backlog and the
    ledger rows ``(slot, x, held_back, uplink_rate_bps, image_bits)`` the scheduler would read."""
    b, rows = UplinkBacklog(), []
    queue_bits, ahead = 0.0, []  # bits in the FIFO; for each image on its way, the bits before its end
    acks: list[int] = []  # ms of acknowledgements due
    for k in range(slots):
        ms0 = round(k * TAU_S * 1000)
        queued = hold and b.queued(ms0 / 1000)
        rows.append((k, int(asks(k) and not queued), int(asks(k) and queued), b.rate_bps, image_bits))
        if rows[-1][1]:
            b.sent(image_bits, ms0 / 1000)
            queue_bits += image_bits
            ahead.append(queue_bits)
        for ms in range(ms0 + 1, ms0 + round(TAU_S * 1000) + 1):
            served = min(queue_bits + other_bps / 1000, link_bps / 1000)
            queue_bits = max(0.0, queue_bits + other_bps / 1000 - served)
            ahead = [a - served for a in ahead]
            if ahead and ahead[-1] <= 0:  # the last one served: all of them
                ahead = []
                acks.append(ms + ack_latency_ms)
            while acks and acks[0] <= ms:
                b.acked(acks.pop(0) / 1000)
    return b, rows


def _caps(rows) -> list[float]:
    """τ·R/b of every ledger row with a throughput estimate."""
    return [TAU_S * r / bits for *_, r, bits in rows if math.isfinite(r)]


def test_backlog_rate_is_the_share_images_get_on_a_shared_link_not_one_image_alone():
    # the two-host cut: 0.59 Mbit/s for 48 kbit images (0.48 Mbit/s at one per slot) beside 0.3 Mbit/s of other
    # traffic — room for 60 % of the images. An image alone crosses at the link's whole rate (81 ms: it reads 1.2
    # images per slot); back to back the images get the 0.29 Mbit/s the other traffic leaves
    link, other, bits = 0.59e6, 0.3e6, 48_000
    share = TAU_S * (link - other) / bits
    _, rows = _fifo_link(link, other, bits, 200)
    steady = rows[100:]
    carried = sum(x for _, x, *_ in steady) / len(steady)
    assert carried == pytest.approx(share, abs=0.05) and sum(h for _, _, h, *_ in steady) > 0.3 * len(steady)
    caps = _caps(steady)
    assert max(caps) < 1.0 and float(np.median(caps)) == pytest.approx(share, abs=0.06)
    # without the hold-back, on a link where an image alone takes longer than a slot (0.4 Mbit/s), five images queue
    # back to back in the rate limit: acknowledged together, their bits over the time from the first publication
    # (0.9 s) measure the images' share of the link too
    burst, _ = _fifo_link(0.4e6, other, bits, 12, asks=lambda k: k < 5, hold=False)
    assert burst.acked_images == 1 and burst.rate_bps == pytest.approx(5 * bits / 0.9)


def test_backlog_reads_sparse_images_on_a_fast_link_fast():
    # a healthy link (5 Mbit/s; each acknowledgement 50 ms late, a heartbeat): one image per slot, or one per second
    for asks in (lambda k: True, lambda k: k % 10 == 0):
        _, rows = _fifo_link(5e6, 0.3e6, 48_000, 100, asks=asks, ack_latency_ms=50)
        assert min(_caps(rows[20:])) > 1.5 and sum(h for _, _, h, *_ in rows) == 0
    # the cut link of the test above, the plan asking for fewer images than it carries (one every other slot): each
    # image reads the link's whole rate, the slots without one are not busy — the estimate does not follow the plan
    # down (a cap from it does not ratchet itself down)
    _, rows = _fifo_link(0.59e6, 0.3e6, 48_000, 100, asks=lambda k: k % 2 == 0)
    assert min(_caps(rows[20:])) > 1.0


def test_backlog_rate_falls_while_nothing_is_acknowledged():
    b = UplinkBacklog(stale_after_s=1.0, window_s=5.0)
    for k in range(20):  # fast: 48 kbit acknowledged in 20 ms, one per slot
        b.sent(48_000, k * TAU_S)
        b.acked(k * TAU_S + 0.02)
    fast = b.rate_bps
    assert fast == pytest.approx(48_000 / 0.02)
    b.sent(48_000, 2.0)  # then the link carries (almost) nothing: never acknowledged
    rates = []
    for k in range(21, 120):
        now = k * TAU_S
        if not b.queued(now):  # one image per stale_after_s into the link that does not answer
            b.sent(48_000, now)
        rates.append(b.rate_bps)
    assert fast > rates[0] > rates[9] > rates[29] > rates[59] > rates[-1]
    assert TAU_S * rates[29] / 48_000 < 1.0  # 3 s without an acknowledgement: below an image per slot
    assert rates[-1] == pytest.approx(b.queued_bits / (11.9 - 2.0))  # the window left: bits waiting / time waited
    assert b.queued_bits == 10 * 48_000  # one image per second
    b.acks_trusted = False  # acknowledgements say nothing: the last trusted estimate, not the wait
    assert b.rate_bps == pytest.approx(fast)


def test_link_cap_from_the_robot_rows_caps_a_cut_link_and_not_a_fast_one():
    """The rows of the shared-link runs above (acknowledged 20 ms after the link served them), as the scheduler's
    LinkCap reads them: on the cut link the cap is the fraction of slots the link carried an image in while every
    slot asked for one (an image then takes longer than a slot: one every other slot), on a fast one none."""
    cut, fast = LinkCap(TAU_S), LinkCap(TAU_S)
    carried = {}
    for cap, link in ((cut, 0.59e6), (fast, 5e6)):
        rows = _fifo_link(link, 0.3e6, 48_000, 150, ack_latency_ms=20)[1]
        for row in rows:
            cap.record(*row)
        carried[link] = sum(x for _, x, *_ in rows[-LINK_WINDOW_SLOTS:]) / LINK_WINDOW_SLOTS
    assert fast.image_cap() is None and carried[5e6] == 1.0
    assert carried[0.59e6] < 0.65 and cut.image_cap() == pytest.approx(carried[0.59e6], abs=0.08)


def _inputs(slot: int, queued: bool, rate: float = float("nan")) -> SlotInputs:
    frame = np.full((24, 32, 3), 128, np.uint8)
    return SlotInputs(slot, frame, 1_000, (0.0, 0.0, 0.0), (1, 0.01), measured_gain=1e-6, uplink_queued=queued,
                      uplink_rate_bps=rate)


def test_core_holds_an_image_back_while_the_last_is_queued():
    core = UplinkCore(LinkBudget(), 0.1)
    sent = core.run_slot(_inputs(1, queued=False))
    assert sent.x == 1 and sent.jpeg is not None and sent.row.held_back == 0
    held = core.run_slot(_inputs(2, queued=True, rate=1.5e6))
    assert held.x == 0 and held.jpeg is None and held.key is not None
    assert held.row.held_back == 1 and held.row.uplink_rate_bps == 1.5e6
    assert held.row.upload_all_bits > 0  # the upload-all reference still prices the frame
    assert core.ledger.totals()["images_held_back"] == 1


def test_cap_expected_images_keeps_the_most_valuable_images():
    samples = rician_power_samples(1.0)
    mean_gain = np.full(10, 1e-6)
    # thresholds c/(λ L): slot 0 has the largest L (lowest threshold), slot 9 the smallest; slot 5 always a key
    thresholds = mean_gain * np.linspace(0.2, 1.5, 10)
    thresholds[5] = np.inf
    expected = lambda t: float(np.sum(1 - np.searchsorted(samples, t / mean_gain) / samples.size))  # noqa: E731
    assert expected(thresholds) > 4
    capped, scale = cap_expected_images(thresholds, mean_gain, samples, 4.0)
    assert scale > 1 and expected(capped) <= 4.0 + 1e-6 and expected(capped) > 3.9
    assert np.isinf(capped[5]) and np.all(np.diff(capped[[0, 1, 2, 3, 4, 6, 7, 8, 9]]) > 0)  # order kept
    same, one = cap_expected_images(thresholds, mean_gain, samples, 20.0)
    assert one == 1.0 and np.array_equal(same, thresholds)
    zero = np.zeros(10)  # "always an image" thresholds rise too
    capped0, _ = cap_expected_images(zero, mean_gain, samples, 2.0)
    assert expected(capped0) <= 2.0 + 1e-6


def test_planner_caps_images_when_the_robot_held_them_back():
    link = LinkBudget()
    planner = OnlinePlanner(replace(BLIND, in_slot_decision=True),
                            RoutePredictor([[0, 0], [4, 0], [4, 4], [0, 4]], 0.3), LossMap(prior=0.2), link)
    free = planner.plan(0, (0.0, 0.0, 0.0))
    assert planner.link_cap.image_cap() is None and planner.last_image_cap is None
    for k in range(1, LINK_WINDOW_SLOTS + 1):  # a fast link: 64 kbit images acknowledged at 2 Mbit/s: no cap
        planner.record_action(k, 1, 0, 2e6, 64_000)
    assert planner.link_cap.image_cap() is None
    for k in range(LINK_WINDOW_SLOTS + 1, 2 * LINK_WINDOW_SLOTS + 1):  # 0.2 Mbit/s: an image per 3.2 slots
        planner.record_action(k, int(k % 3 == 0), int(k % 3 != 0), 0.2e6, 64_000)
    cap = planner.link_cap.image_cap()
    assert cap == pytest.approx(0.1 * 0.2e6 / 64_000) and planner.link_cap.images_held_back() == 33
    capped = planner.plan(2 * LINK_WINDOW_SLOTS, (0.0, 0.0, 0.0))
    samples = rician_power_samples(1.0)
    gains = planner.gains(2 * LINK_WINDOW_SLOTS + 1, planner.route.predict((0.0, 0.0, 0.0), 40, 0.1))

    def expected(s) -> float:
        t = np.asarray(s.schedule.gain_threshold)
        return float(np.sum(1 - np.searchsorted(samples, t / gains) / samples.size))

    assert expected(free) > 30  # L_th = 0: images in every slot but the deepest fades
    assert expected(capped) <= cap * 40 + 1e-6
    assert planner.last_image_cap == cap


def test_robot_uses_the_uplink_profile_unless_one_is_set(tmp_path):
    env: dict[str, str] = {}
    path = use_uplink_profile(env)
    text = Path(path).read_text()
    assert env["FASTDDS_DEFAULT_PROFILES_FILE"] == path and f"<nanosec>{HEARTBEAT_PERIOD_NS}</nanosec>" in text
    assert 'is_default_profile="true"' in text
    own = {"FASTRTPS_DEFAULT_PROFILES_FILE": str(tmp_path / "mine.xml")}
    assert use_uplink_profile(own) == own["FASTRTPS_DEFAULT_PROFILES_FILE"]
    assert "FASTDDS_DEFAULT_PROFILES_FILE" not in own


def test_link_cap_only_probes_when_images_arrive_after_their_slot():
    cap = LinkCap(0.1)
    fast, slow = (2e6, 64_000), (0.5e6, 64_000)  # 0.5 Mbit/s: 0.78 images per slot
    for k in range(1, 21):  # images composed in their slots (the server's loss samples came)
        cap.record(k, 1, 0, *fast)
        cap.record_sample(k)
    assert cap.delivery_ratio() == 1.0 and cap.image_cap() is None
    k0 = 21 + DELIVERY_WINDOW_IMAGES + DELIVERY_GRACE_SLOTS
    for k in range(21, k0):  # then none composed (an outage), the link as fast as before: no cap
        cap.record(k, 1, 0, *fast)
    assert cap.delivery_ratio() < 0.5 and cap.image_cap() is None
    for k in range(k0, k0 + LINK_WINDOW_SLOTS):  # a slow link whose images all arrive late: only probe
        cap.record(k, 1, 0, *slow)
    assert cap.delivery_ratio() < 0.5
    assert cap.image_cap() == PROBE_IMAGE_FRACTION
    k1 = k0 + LINK_WINDOW_SLOTS
    for k in range(k1, k1 + DELIVERY_WINDOW_IMAGES + DELIVERY_GRACE_SLOTS):  # the probes arrive again
        cap.record(k, 1, 0, *slow)
        cap.record_sample(k)
    assert cap.delivery_ratio() >= 0.5
    assert cap.image_cap() == pytest.approx(0.1 * 0.5e6 / 64_000)  # the throughput cap alone
    silent = LinkCap(0.1)
    for k in range(1, 40):  # a server that never measures L_t: no verdict on delivery
        silent.record(k, 1, 0, *fast)
    assert silent.delivery_ratio() is None and silent.image_cap() is None
    unknown = LinkCap(0.1)  # rows without a rate or a size (an older robot): no cap
    for k in range(1, 10):
        unknown.record(k, 1)
    assert unknown.image_cap() is None and unknown.images_held_back() == 0
    with pytest.raises(ValueError):
        LinkCap(0.0)


def test_planner_feeds_the_link_cap_from_ledger_rows_and_loss_samples():
    """The planner's inputs reach the link cap: ledger rows (record_action) and loss samples (observe)."""
    planner = OnlinePlanner(BLIND, RoutePredictor([[0, 0], [4, 0], [4, 4], [0, 4]], 0.3), LossMap(prior=0.2),
                            LinkBudget())
    for k in range(1, 21):
        planner.record_action(k, 1, int(k % 2), 2e6, 64_000)
        planner.observe(k, 0.0, 0.0, 0.0, 0.1)
    assert planner.link_cap.delivery_ratio() == 1.0 and planner.link_cap.images_held_back() == 10


def test_cap_planned_images_keeps_the_most_loss_per_joule():
    """Without the in-slot rule a capped plan keeps the images with the largest key cost × gain."""
    x = np.array([1, 1, 0, 1, 1], np.int8)
    key_cost = np.array([0.05, 0.01, 0.09, 0.02, 0.05])
    gains = np.array([1.0, 1.0, 1.0, 1.0, 2.0])
    np.testing.assert_array_equal(cap_planned_images(x, key_cost, gains, 2.5), [1, 0, 0, 0, 1])
    assert cap_planned_images(x, key_cost, gains, 4.0) is None  # it fits already


def test_planner_without_the_in_slot_rule_holds_its_images_to_the_link():
    planner = OnlinePlanner(BLIND, RoutePredictor([[0, 0], [4, 0], [4, 4], [0, 4]], 0.3), LossMap(prior=0.2),
                            LinkBudget())
    assert planner.plan(0, (0.0, 0.0, 0.0)).images == 40  # L_th = 0: an image in every slot
    for k in range(1, LINK_WINDOW_SLOTS + 1):  # 0.2 Mbit/s: an image per 3.2 slots
        planner.record_action(k, int(k % 3 == 0), int(k % 3 != 0), 0.2e6, 64_000)
    capped = planner.plan(LINK_WINDOW_SLOTS, (0.0, 0.0, 0.0))
    assert capped.images == int(0.1 * 0.2e6 / 64_000 * 40) and any("images capped" in n for n in capped.notes)
