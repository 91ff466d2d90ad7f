"""Robot and server on two network stacks (root only): real network faults on the link between them.

One stack for the module: the robot's processes in the robot namespace and the server's in the server
namespace of a :class:`gsrmr_sim.netns.TwoHosts` (5 Mbit/s uplink, DDS over UDPv4), an untrained point model,
the scheduler asking for an image in every slot (L_th = 0) so that every slot should carry one. The tests run
in file order on it: the link taken down for 2 s, the robot's participant killed and restarted, the uplink cut
below one image per slot; the last one stops everything and checks the recording and that nothing is left.
Everything is read from what the nodes write (``slots.csv``, logs): the test process is in neither namespace.
"""

from __future__ import annotations

from collections import Counter
import re
import time

from conftest import ros_env
import pytest
from support import stack_harness

from gsrmr_server.recording import TOPIC_SLOT_LOG, read_mcap
from gsrmr_sim.netns import TwoHosts, namespaces, unavailable_reason
from gsrmr_sim.scores import read_scores

pytestmark = [pytest.mark.ros, pytest.mark.slow,
              pytest.mark.skipif(unavailable_reason() is not None, reason=f"two hosts: {unavailable_reason()}")]


@pytest.fixture(scope="module")
def two_hosts(tmp_path_factory):
    h = stack_harness
    tmp = tmp_path_factory.mktemp("two_hosts")
    model = h.make_point_model(tmp)
    env = ros_env()
    hosts = TwoHosts(uplink_mbit=5.0, domain_id=int(env["ROS_DOMAIN_ID"])).open()
    stack = h.Stack(tmp, model, env, hosts=hosts,
                    overrides={"gsrmr_scheduler": {"loss_threshold": 0.0, "horizon": 100, "replan_period_s": 1.0}})
    state = {"stopped": False}
    try:
        stack.start_all()
        yield stack, hosts, state
    finally:
        if not state["stopped"]:
            stack.stop()
        hosts.close()


def _rows(stack) -> list[dict]:
    return stack_harness.slot_rows(stack.tmp / "rec")


def _wait_rows(stack, predicate, timeout_s: float) -> list[dict]:
    deadline = time.monotonic() + timeout_s
    rows = _rows(stack)
    while time.monotonic() < deadline and not predicate(rows):
        time.sleep(0.2)
        rows = _rows(stack)
    return rows


def _consecutive(rows) -> bool:
    slots = [r["slot"] for r in rows]
    return bool(slots) and slots == list(range(slots[0], slots[0] + len(slots)))


def _faults(rows) -> Counter:
    return Counter(f for r in rows for f in (r["faults"] or "").split(";") if f)


def _alive(stack) -> None:
    for name, proc in stack.procs.items():
        assert proc.poll() is None, (name, stack.log(name)[-2000:])


def test_images_cross_the_veth_not_shared_memory(two_hosts):
    stack, hosts, _ = two_hosts
    rows = _wait_rows(stack, lambda rs: sum(r["source"] == "image" for r in rs) >= 30, 90)
    assert sum(r["source"] == "image" for r in rows) >= 30, (stack.log("gsrmr_server")[-2000:],
                                                             stack.log("gsrmr_robot")[-2000:])
    before = hosts.link_bytes()
    time.sleep(3.0)
    after = hosts.link_bytes()
    recent = [r for r in _rows(stack) if r["stamp_s"] >= before["wall_s"] and r["stamp_s"] < after["wall_s"] - 0.5]
    sent = sum(r["bytes_sent"] or 0 for r in recent)
    assert sent > 0 and after["uplink"] - before["uplink"] >= sent  # the uploads went through the veth
    # the scorer, on the server's side, scores against the true frames of the simulation backplane (no raw
    # frame crosses the link)
    def scored() -> list[dict]:
        return [r for r in read_scores(stack.tmp / "rec").values() if r["loss"] is not None]

    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and len(scored()) < 20:
        time.sleep(0.5)
    assert len(scored()) >= 20, stack.log("gsrmr_sim_scorer")[-2000:]
    assert "truth from folder" in stack.log("gsrmr_sim_scorer")
    _alive(stack)


def test_link_down_two_seconds_server_composes_through_and_images_resume(two_hosts):
    stack, hosts, _ = two_hosts
    t_down = time.time()
    hosts.set_link(False)
    time.sleep(2.0)
    hosts.set_link(True)
    t_up = time.time()
    rows = _wait_rows(stack, lambda rs: bool(rs) and rs[-1]["stamp_s"] > t_up + 4.0, 30)
    assert _consecutive(rows), "the server skipped slots"
    gap = [r for r in rows if t_down + 0.3 <= r["stamp_s"] <= t_up - 0.1]
    assert len(gap) >= 15  # composed all through the outage …
    assert all(r["source"] in ("render", "fallback") for r in gap), Counter(r["source"] for r in gap)
    # … from the GS render at the extrapolated pose, every missing upload counted
    assert _faults(gap)["missing_key"] >= len(gap) - 2, _faults(gap)
    first_image = next((r for r in rows if r["stamp_s"] >= t_up and r["source"] == "image"), None)
    assert first_image is not None, Counter(r["source"] for r in rows if r["stamp_s"] >= t_up)
    # promptly (about 0.5 s idle; a bound against "stuck", not a latency figure: a clean-clone run at load 7–10 took
    # 1.03 s), and keep coming from then on
    assert first_image["stamp_s"] - t_up <= 3.0, first_image["stamp_s"] - t_up
    rows = _wait_rows(stack, lambda rs: rs[-1]["stamp_s"] > first_image["stamp_s"] + 3.0, 30)
    after = [r for r in rows if first_image["stamp_s"] + 0.5 <= r["stamp_s"] <= first_image["stamp_s"] + 3.0]
    # and keep coming (the robot may hold one back while the outage's queue drains)
    assert sum(r["source"] == "image" for r in after) >= 0.5 * len(after), \
        Counter((r["source"], r["held_back"]) for r in after)
    _alive(stack)


def test_robot_participant_killed_and_restarted_images_resume(two_hosts):
    stack, _, _ = two_hosts
    stack.kill9("gsrmr_robot")
    t_kill = time.time()
    time.sleep(1.0)
    stack.start("gsrmr_robot")
    t_start = time.time()
    rows = _wait_rows(stack, lambda rs: any(r["stamp_s"] > t_start and r["source"] == "image" for r in rs), 30)
    assert _consecutive(rows)
    gap = [r for r in rows if t_kill + 0.2 <= r["stamp_s"] <= t_start]
    assert gap and all(r["source"] in ("render", "fallback") for r in gap)
    first_image = next(r for r in rows if r["stamp_s"] > t_start and r["source"] == "image")
    assert first_image["stamp_s"] - t_start <= 15.0  # process start-up and SUBNET discovery across the veth
    _alive(stack)


# The longest the scheduler may take to cap the images after the cut: a bound against "never", not a latency figure
# (the cap waits for ledger rows that queue behind images on the cut link; at load 7–9 a scheduler replanned 12 s
# apart and a 12 s bound failed a clean-clone run)
CAP_WITHIN_S = 40.0
STEADY_S = 8.0  # the steady state measured after the cap
_CAP_LINE = re.compile(r"\[(\d+\.\d+)\] \[gsrmr_scheduler\]: uplink image cap: image_cap=(?!none)")


def _first_cap_s(log: str, after_s: float) -> float | None:
    """Stamp (s) of the scheduler's first log line capping the images (a number, not none) after ``after_s``."""
    stamps = [float(m.group(1)) for m in _CAP_LINE.finditer(log)]
    return next((t for t in stamps if t >= after_s), None)


def _other_bps(stack, before: dict, after: dict) -> tuple[float, list[int]]:
    """What the uplink carried besides the images between two :meth:`TwoHosts.link_bytes` readings (bit/s), and the
    sizes (bytes) of the images sent in between."""
    window = [r for r in _rows(stack) if before["wall_s"] <= r["stamp_s"] < after["wall_s"]]
    images = [r["bytes_sent"] for r in window if r["x"] == 1 and r["bytes_sent"]]
    seconds = after["wall_s"] - before["wall_s"]
    return max(0.0, 8 * (after["uplink"] - before["uplink"] - sum(images)) / seconds), images


def test_uplink_cut_below_one_image_per_slot_robot_holds_back_scheduler_plans_fewer(two_hosts):
    stack, hosts, _ = two_hosts
    # what the link carries besides images (keys and ledger rows to server and scheduler, cmd_vel, DDS
    # heartbeats, acknowledgements and discovery), measured over 4 s of one image per slot once it is steady. The
    # robot's participant was restarted just before (the test above): its discovery across the link (measured up to
    # 0.7 Mbit/s against 0.3 steady, for a few seconds) taken for steady traffic set a cut under which the link
    # still carried an image per slot (0.58 Mbit/s: none held back, rightly no cap). So 2 s windows until two in a
    # row agree within 20 %; those two are the measurement
    readings = [hosts.link_bytes()]
    for _ in range(10):
        time.sleep(2.0)
        readings.append(hosts.link_bytes())
        if len(readings) >= 3:
            earlier = _other_bps(stack, readings[-3], readings[-2])[0]
            last = _other_bps(stack, readings[-2], readings[-1])[0]
            if abs(earlier - last) <= 0.2 * max(earlier, last):
                break
    time.sleep(0.3)  # the server writes a slot's row after composing it
    before, after_bytes = readings[-3], readings[-1]
    other_bps, images = _other_bps(stack, before, after_bytes)
    window = [r for r in _rows(stack) if before["wall_s"] <= r["stamp_s"] < after_bytes["wall_s"]]
    assert len(images) >= 20
    image_bps = 8 * sorted(images)[len(images) // 2] / 0.1  # one image per slot
    # below one image per slot: room for 60 % of the images beside the rest of the traffic
    cut_mbit = (other_bps + 0.6 * image_bps) / 1e6
    hosts.set_rate(cut_mbit)
    t_cut = time.time()
    # the steady state starts 1 s after the scheduler capped the images (how soon it does depends on how soon the
    # robot's ledger rows cross the cut link and on the machine's load: bounded here, then measured after it)
    deadline = time.monotonic() + CAP_WITHIN_S
    while time.monotonic() < deadline and _first_cap_s(stack.log("gsrmr_scheduler"), t_cut) is None:
        time.sleep(0.2)
    t_capped = _first_cap_s(stack.log("gsrmr_scheduler"), t_cut)
    print(f"uplink cut to {cut_mbit:.2f} Mbit/s: the scheduler capped the images "
          f"{'never' if t_capped is None else f'{t_capped - t_cut:.1f} s'} after the cut")
    rates_since_cut = [r["uplink_rate_bps"] for r in _rows(stack) if r["stamp_s"] >= t_cut]
    assert t_capped is not None, (f"no cap within {CAP_WITHIN_S} s of the cut; the robot's uplink rates since then "
                                  f"{rates_since_cut}: {stack.log('gsrmr_scheduler')[-3000:]}")
    steady_from = t_capped + 1.0
    time.sleep(max(0.0, steady_from - time.time()))
    drops_before = hosts.queue_stats()["dropped"]
    rows = _wait_rows(stack, lambda rs: bool(rs) and rs[-1]["stamp_s"] > steady_from + STEADY_S, 40)
    drops = hosts.queue_stats()["dropped"] - drops_before
    assert _consecutive(rows)
    after = [r for r in rows if steady_from <= r["stamp_s"] <= steady_from + STEADY_S]
    assert len(after) >= 60
    log = stack.log("gsrmr_scheduler")
    # the robot notices: its image acknowledgements slow down (its throughput estimate falls) and an image
    # asked for while the last one is unacknowledged is held back (key only)
    before_rates = [r["uplink_rate_bps"] for r in window if r["uplink_rate_bps"]]
    rates = [r["uplink_rate_bps"] for r in after if r["uplink_rate_bps"]]
    assert rates and before_rates and min(rates) < 0.5 * sorted(before_rates)[len(before_rates) // 2]
    held_logged = [int(m.group(1)) for m in re.finditer(r"\((\d+) held back in the last slots", log)]
    assert sum(r["held_back"] or 0 for r in rows if r["stamp_s"] >= t_cut) >= 1 or max(held_logged, default=0) >= 1
    # the scheduler notices (the robot's ledger rows) and caps the images it plans at what the link carries
    caps = [float(line.rsplit("image_cap=", 1)[1].split()[0]) for line in log.splitlines()
            if "image_cap=" in line and "image_cap=none" not in line]
    assert caps and min(caps) < 1.0, log[-3000:]
    # the uplink does not fall behind: the rate limiter's queue never overflowed in the steady state (no drops,
    # so no retransmission storm), and images still get through
    assert drops <= 5, drops
    # at the cap the scheduler logs (0.06 in these runs: about 5 images planned in the 80 slots, and on a link with room
    # for 60 % of them some arrive after their slot) images are few: at least one is composed from its image
    assert sum(r["source"] == "image" for r in after) >= 1, Counter(r["source"] for r in after)
    hosts.set_rate(5.0)
    _alive(stack)


def test_two_host_stack_stops_cleanly_recording_complete_nothing_left(two_hosts):
    stack, hosts, state = two_hosts
    took = stack.stop()
    state["stopped"] = True
    assert all(t < 10 for t in took.values()), took
    rows = _rows(stack)
    assert _consecutive(rows)
    logs = [msg for topic, _, msg in read_mcap(stack.tmp / "rec" / "run.mcap") if topic == TOPIC_SLOT_LOG]
    assert len(logs) == len(rows)  # every composed slot is in the MCAP too
    made = {hosts.robot_ns, hosts.server_ns}
    hosts.close()
    assert not made & set(namespaces())
    assert not list((stack.tmp / "truth_frames").glob("*.tmp"))
