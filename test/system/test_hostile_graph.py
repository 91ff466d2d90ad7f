"""The hostile graph over DDS: a stranger (test/support/hostile.py) joins a running stack and lies with well-formed
messages.

First the ROS adapter of the known-writer check alone, in one process (``ros``, a few seconds). Then one stack for
the module (``ros`` + ``slow``) (the simulated closed loop as processes, every node's writer lists from
``gsrmr_sim.sim_stack.SIM_WRITERS``; the scheduler plans an image in every slot, so that the robot's hold-back shows),
one rogue node (``gsrmr_hostile``) lying case after case (``hostile.CASES``); each test checks that the lie changed
nothing it must not change, that its target named the rogue on ``/diagnostics``, and that a clean stack counted
nothing before the first lie. The full rounds with the energy and loss figures are
``bench/acceptance/hostile_graph.py``.
"""

from __future__ import annotations

import json
import os
import signal
import time

import pytest
from support.hostile import READER_NAME, ROGUE_NAME, DiagnosticsWatch, Rogue
from support.stack_harness import Stack, make_point_model, ros_client, slot_rows, spin_until


@pytest.mark.ros
def test_gated_inputs_admit_by_writer_gid_and_name_the_stranger():
    """In one process (a few seconds): a listed writer's messages are delivered with its GID, a stranger's refused,
    counted and named, a restarted writer (a new publisher of the listed node) admitted again."""
    from conftest import ros_env
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from std_msgs.msg import Float64MultiArray

    from gsrmr_common.ros_admission import GatedInputs

    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(ros_env()["ROS_DOMAIN_ID"]))
    try:
        reader = rclpy.create_node("gated_reader", context=ctx)
        robot = rclpy.create_node("gsrmr_robot", context=ctx)
        stranger = rclpy.create_node(ROGUE_NAME, context=ctx)
        ex = SingleThreadedExecutor(context=ctx)
        for n in (reader, robot, stranger):
            ex.add_node(n)
        got: list[tuple[float, bytes]] = []
        inputs = GatedInputs(reader)
        inputs.subscribe(Float64MultiArray, "gated", lambda m, gid: got.append((m.data[0], gid)), 10, ["gsrmr_robot"],
                         rate_hz=0.0, burst=10.0)
        pubs = [robot.create_publisher(Float64MultiArray, "gated", 10),
                stranger.create_publisher(Float64MultiArray, "gated", 10)]
        assert spin_until(ex, lambda: all(p.get_subscription_count() for p in pubs), 5)
        for i in range(5):
            pubs[0].publish(Float64MultiArray(data=[float(i)]))
            pubs[1].publish(Float64MultiArray(data=[100.0 + i]))
        assert spin_until(ex, lambda: len(got) == 5 and inputs.gate.refused, 5)
        spin_until(ex, lambda: False, 0.3)
        assert [v for v, _ in got] == [0.0, 1.0, 2.0, 3.0, 4.0] and len({g for _, g in got}) == 1
        assert inputs.gate.refused_by_writer() == {f"/{ROGUE_NAME}": {"gated unlisted": 5}}
        assert inputs.writer_of("gated", got[0][1]) == "/gsrmr_robot"
        robot.destroy_publisher(pubs[0])  # the listed node restarts its writer: a new GID under its name
        again = robot.create_publisher(Float64MultiArray, "gated", 10)
        assert spin_until(ex, lambda: again.get_subscription_count() > 0, 5)
        again.publish(Float64MultiArray(data=[9.0]))
        assert spin_until(ex, lambda: len(got) == 6, 5)
        assert got[-1][0] == 9.0 and got[-1][1] != got[0][1]
    finally:
        rclpy.shutdown(context=ctx)


class _FakeTimer:
    def __init__(self) -> None:
        self.canceled = False

    def cancel(self) -> None:
        self.canceled = True

    def reset(self) -> None:
        self.canceled = False

    def is_canceled(self) -> bool:
        return self.canceled


class _FakeNode:
    """What GatedInputs uses of a node: the graph is a list the test sets, the raw callback is called by hand."""

    def __init__(self) -> None:
        self.graph: list = []
        self.callback = None
        self.subscriptions = 0  # live ones
        self.timers: list = []  # (period, callback) of every timer created

    def get_namespace(self) -> str:
        return "/"

    def get_logger(self):
        import logging

        return type("Logger", (), {"warning": lambda _self, msg, **_kw: logging.getLogger("fake").warning(msg)})()

    def create_timer(self, period, callback, callback_group=None) -> _FakeTimer:
        self.timers.append((period, callback))
        return _FakeTimer()

    def destroy_timer(self, _timer) -> None:
        pass

    def create_subscription(self, _kind, topic, callback, _qos, callback_group=None, raw=False):
        assert raw
        self.callback = callback
        self.subscriptions += 1
        return type("Sub", (), {"topic_name": "/" + topic})()

    def destroy_subscription(self, _sub) -> None:
        self.subscriptions -= 1

    def get_publishers_info_by_topic(self, _name) -> list:
        return list(self.graph)


@pytest.mark.ros
def test_a_held_writers_later_message_never_overtakes_its_earlier_ones():
    """A schedule that arrives before its writer's name is known is held; the next one (the graph names the writer by
    then) is delivered after it, not before — else the first would then look like a replayed older seq."""
    from types import SimpleNamespace

    from rclpy.serialization import serialize_message
    from std_msgs.msg import Float64MultiArray

    from gsrmr_common.ros_admission import PROMPT_REFRESH_S, GatedInputs

    node = _FakeNode()
    got: list[float] = []
    inputs = GatedInputs(node)
    inputs.subscribe(Float64MultiArray, "gsrmr/schedule", lambda m, _gid: got.append(m.data[0]), 1,
                     ["gsrmr_scheduler"], rate_hz=0.0, burst=1.0)
    gid = b"\x07" * 16

    def endpoint(name: str):
        return SimpleNamespace(endpoint_gid=gid, node_namespace="/", node_name=name)

    def arrive(seq: float) -> None:
        time.sleep(1.5 * PROMPT_REFRESH_S)  # past the refresh throttle: each arrival may re-read the graph
        node.callback(serialize_message(Float64MultiArray(data=[seq])), {"publisher_gid": {"data": gid}})

    node.graph = [endpoint("_NODE_NAME_UNKNOWN_")]  # discovery has the endpoint, not yet its node's name
    arrive(3.0)
    arrive(4.0)
    assert got == [] and inputs.gate.held == 2  # both wait, in order
    node.graph = [endpoint("gsrmr_scheduler")]
    arrive(5.0)
    assert got == [3.0, 4.0, 5.0] and inputs.gate.held == 0
    arrive(6.0)
    assert got == [3.0, 4.0, 5.0, 6.0] and not inputs.gate.refused


@pytest.mark.ros
def test_a_flooded_topic_is_not_read_for_a_while_then_read_again():
    """200 refused messages within 1 s: the subscription goes (the flood then reaches no reader of this node), a
    timer brings it back after 1 s; the pause is counted by topic and writer and warned about."""
    from types import SimpleNamespace

    from rclpy.serialization import serialize_message
    from std_msgs.msg import Float64MultiArray

    from gsrmr_common.ros_admission import GatedInputs

    node = _FakeNode()
    got: list[float] = []
    inputs = GatedInputs(node)
    inputs.subscribe(Float64MultiArray, "gsrmr/loss_sample", lambda m, _gid: got.append(m.data[0]), 50,
                     ["gsrmr_server"], rate_hz=40.0, burst=60.0)
    rogue, server = b"\x03" * 16, b"\x02" * 16
    node.graph = [SimpleNamespace(endpoint_gid=rogue, node_namespace="/", node_name=ROGUE_NAME),
                  SimpleNamespace(endpoint_gid=server, node_namespace="/", node_name="gsrmr_server")]
    inputs.refresh()
    payload = serialize_message(Float64MultiArray(data=[0.5]))
    callback = node.callback
    for _ in range(199):
        callback(payload, {"publisher_gid": {"data": rogue}})
    assert node.subscriptions == 1 and not inputs.breaker.trips
    callback(payload, {"publisher_gid": {"data": server}})  # the listed writer still gets through
    callback(payload, {"publisher_gid": {"data": rogue}})  # the 200th refusal within the second
    assert node.subscriptions == 0 and got == [0.5]
    assert inputs.diagnostic_values()["floods"] == {f"gsrmr/loss_sample by /{ROGUE_NAME}": 1}
    assert any("flooded" in p for p in inputs.problems())
    period, resume = node.timers[-1]
    assert period == 1.0
    resume()
    assert node.subscriptions == 1
    node.callback(payload, {"publisher_gid": {"data": server}})
    assert got == [0.5, 0.5]


@pytest.mark.ros
def test_a_node_started_without_live_changes_refuses_every_change_and_says_why():
    """The robot node as deployed (``live_parameter_changes`` false): a live parameter is refused with the reason, a
    writer list is read-only; started with live changes on, a change is taken, logged and counted."""
    from conftest import ros_env
    import rclpy
    from rclpy.context import Context
    from rclpy.parameter import Parameter

    from gsrmr_robot.robot_node import RobotNode

    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(ros_env()["ROS_DOMAIN_ID"]))
    try:
        locked = RobotNode(context=ctx)
        refused = locked.set_parameters([Parameter("jpeg_quality", value=60)])[0]
        assert not refused.successful and "live_parameter_changes is false" in refused.reason
        read_only = locked.set_parameters([Parameter("schedule_writers", value=[ROGUE_NAME])])[0]
        assert not read_only.successful and "read-only" in read_only.reason
        assert locked.params.jpeg_quality == 80 and locked.params.schedule_writers == ("gsrmr_scheduler",)
        assert locked.audit.diagnostic_values() == {"parameter_changes": {},
                                                    "parameter_changes_refused": {"jpeg_quality": 1}}
        locked.destroy_node()
        live = RobotNode(context=ctx, parameter_overrides=[Parameter("live_parameter_changes", value=True)])
        assert live.set_parameters([Parameter("jpeg_quality", value=60)])[0].successful
        assert live.core.jpeg_quality == 60 and live.audit.changes == {"jpeg_quality": 1}
        live.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    from conftest import ros_env

    tmp = tmp_path_factory.mktemp("hostile_stack")
    s = Stack(tmp, make_point_model(tmp), ros_env(), overrides={"gsrmr_scheduler": {"loss_threshold": 0.0}})
    s.start_all()
    try:
        yield s
    finally:
        s.stop()


@pytest.fixture(scope="module")
def rogue(stack):
    with ros_client(stack.env, ROGUE_NAME) as (node, ex):
        watch = DiagnosticsWatch(node)
        watch.look_for(ROGUE_NAME, READER_NAME, "two live endpoints under /gsrmr_server")
        rows = stack.tmp / "rec"
        assert spin_until(ex, lambda: any(r["source"] == "image" for r in slot_rows(rows)), 90), \
            stack.log("gsrmr_server")[-2000:]
        yield node, ex, watch


def _refused(watch: DiagnosticsWatch, node: str, writer: str = f"/{ROGUE_NAME}") -> dict[str, int]:
    return watch.counters(node).get("writers_refused", {}).get(writer, {})


def _alive(stack) -> None:
    for name, proc in stack.procs.items():
        assert proc.poll() is None, (name, stack.log(name)[-2000:])


def _eventually(ex, predicate, timeout_s: float = 30.0) -> bool:
    """Spin until ``predicate()`` holds — a node on a loaded machine may report its counts a few statuses late (its
    executor still works through the lies) — at most ``timeout_s``; whether it held."""
    return spin_until(ex, predicate, timeout_s)


def _fresh_diagnostics(ex, watch: DiagnosticsWatch) -> None:
    """Wait for a status of every deployment node published after now."""
    watch.latest.clear()
    assert spin_until(ex, lambda: all(n in watch.latest for n in ("gsrmr_robot", "gsrmr_server", "gsrmr_scheduler",
                                                                  "gsrmr_limo_base")), 10), list(watch.latest)


@pytest.mark.ros
@pytest.mark.slow
def test_a_clean_stack_counts_nothing(stack, rogue):
    """Nothing counted on a clean stack — not even after the robot node stalled 2 s (SIGSTOP: a starved process on a
    loaded machine; clean-clone run 38 counted a pose_jump when the robot keyed the slot after a stall with the pose
    from before it)."""
    _node, ex, watch = rogue
    spin_until(ex, lambda: False, 3.0)  # several seconds of composing, image slots, replans
    robot = stack.procs["gsrmr_robot"]
    os.kill(robot.pid, signal.SIGSTOP)
    try:
        spin_until(ex, lambda: False, 2.0)  # the robot drives on (the base and route follower run), unheard
    finally:
        os.kill(robot.pid, signal.SIGCONT)
    spin_until(ex, lambda: False, 3.0)
    _fresh_diagnostics(ex, watch)
    for name in ("gsrmr_robot", "gsrmr_server", "gsrmr_scheduler", "gsrmr_limo_base"):
        counted = watch.counters(name)
        assert counted.get("writers_refused") == {}, (name, counted)
        assert counted.get("implausible", {}) == {}, (name, counted)
        assert counted.get("writer_alarms") == {}, (name, counted)


@pytest.mark.ros
@pytest.mark.slow
def test_lies_from_a_stranger_are_ignored_and_it_is_named(stack, rogue):
    node, ex, watch = rogue
    camera_before = watch.latest["gsrmr_server"]["camera_info"]
    lies = Rogue(node, ex)
    t0 = time.monotonic()
    for case in ("loss_high", "loss_zero", "schedule", "gain_high", "gain_low", "pose_jump", "image_replay", "ledger",
                 "camera_info"):
        lies.run(case, 1.5)
    took = time.monotonic() - t0

    def counted() -> bool:
        robot, server, scheduler = (_refused(watch, n) for n in ("gsrmr_robot", "gsrmr_server", "gsrmr_scheduler"))
        return (robot.get("gsrmr/schedule unlisted", 0) >= 10 and robot.get("radio/channel_gain unlisted", 0) >= 20
                and scheduler.get("gsrmr/loss_sample unlisted", 0) >= 50  # 20/s for 3 s
                and all(scheduler.get(f"{t} unlisted", 0) >= 10 and server.get(f"{t} unlisted", 0) >= 10
                        for t in ("uplink/pose_key", "gsrmr/ledger"))
                and all(server.get(f"{t} unlisted", 0) >= 1
                        for t in ("uplink/image_raw/compressed", "uplink/camera_info", "gsrmr/schedule")))

    assert _eventually(ex, counted), {n: _refused(watch, n) for n in ("gsrmr_robot", "gsrmr_server", "gsrmr_scheduler")}
    assert {"gsrmr_robot", "gsrmr_server", "gsrmr_scheduler"} <= set(watch.named_by(ROGUE_NAME))
    _fresh_diagnostics(ex, watch)
    # what the lies would have changed did not change
    assert int(watch.latest["gsrmr_robot"]["schedule_seq"]) < 1_000_000  # the scheduler's schedule, not the rogue's
    assert watch.latest["gsrmr_server"]["camera_info"] == camera_before
    for name in ("gsrmr_robot", "gsrmr_server", "gsrmr_scheduler"):
        assert watch.counters(name).get("implausible", {}) == {}, name  # refused as a stranger, before any parsing
    recent = [r for r in slot_rows(stack.tmp / "rec") if r["stamp_s"] > time.time() - took]
    assert sum(r["source"] == "image" for r in recent) > 0.5 * len(recent), [r["source"] for r in recent][-30:]
    _alive(stack)


@pytest.mark.ros
@pytest.mark.slow
def test_a_flood_from_a_stranger_is_refused_and_the_node_keeps_planning(stack, rogue):
    node, ex, watch = rogue
    _fresh_diagnostics(ex, watch)
    replans = json.loads(watch.latest["gsrmr_scheduler"]["replans"])
    lies = Rogue(node, ex)
    result = lies.run("flood", 3.0, flood_s=2.0)
    assert result["sent"] >= 1000, result  # it aims at 10 kHz for 2 s (8.6 kHz reached at load 17 here)
    implausible = dict(watch.counters("gsrmr_scheduler").get("implausible", {}))
    # DDS drops what the reader's history cannot hold (how much depends on the machine's load: 500 to 2000 of ~17,000
    # reached the gate here): each of those refused by name, none parsed
    assert _eventually(ex, lambda: _refused(watch, "gsrmr_scheduler").get("gsrmr/loss_sample unlisted", 0) >= 100), \
        (_refused(watch, "gsrmr_scheduler"), result)
    assert watch.counters("gsrmr_scheduler").get("implausible", {}) == implausible
    # the flood paused the scheduler's reader of the topic (it then reaches no one there), at least once
    assert _eventually(ex, lambda: watch.counters("gsrmr_scheduler").get("floods", {}).get(
        f"gsrmr/loss_sample by /{ROGUE_NAME}", 0) >= 1), watch.counters("gsrmr_scheduler")
    assert _eventually(ex, lambda: sum(json.loads(watch.latest["gsrmr_scheduler"]["replans"]).values())
                       > sum(replans.values()))  # it still plans
    _alive(stack)


@pytest.mark.ros
@pytest.mark.slow
def test_a_reader_that_never_acknowledges_does_not_hold_images_back(stack, rogue):
    node, ex, watch = rogue
    lies = Rogue(node, ex, watch=watch)
    lies.run("reader", 6.0)
    assert lies.notes["reader_ready"] and lies.notes["reader_matched"], lies.notes
    t0 = lies.notes["stopped_at"]
    rows = [r for r in slot_rows(stack.tmp / "rec") if t0 + 1.0 < r["stamp_s"] < t0 + 6.0]  # the reader stopped
    assert len(rows) >= 30
    held = sum(r["held_back"] or 0 for r in rows)
    images = sum(r["source"] == "image" for r in rows)
    # every slot plans an image: waiting for the stopped reader's acknowledgement would hold ~9 of 10 back (1 s stale)
    assert held <= 0.1 * len(rows) and images >= 0.7 * len(rows), (held, images, len(rows))
    assert _eventually(ex, lambda: int(watch.latest["gsrmr_robot"]["images_delivered_by_model"]) > 0)
    assert watch.named_by(READER_NAME) == ["gsrmr_robot"]
    _alive(stack)


@pytest.mark.ros
@pytest.mark.slow
def test_parameters_and_replans_from_a_stranger(stack, rogue):
    node, ex, watch = rogue
    lies = Rogue(node, ex)
    lies.run("params", 8.0)
    results = lies.notes["set_parameters"]
    assert all(v.startswith("refused") for v in results.values()), results
    assert "read-only" in results["gsrmr_robot.schedule_writers"]  # it cannot list itself as a writer
    assert "live_parameter_changes" in results["gsrmr_scheduler.loss_threshold"]
    answers = lies.notes["replan_answers"]
    assert answers["refused"] > 20 and answers["success"] <= 5, answers  # 20/s for 3 s; one per second answered
    assert _eventually(ex, lambda: watch.counters("gsrmr_scheduler")["replans_refused"] >= answers["refused"]
                       and watch.counters("gsrmr_scheduler")["parameter_changes_refused"].get("loss_threshold") == 1)
    assert watch.counters("gsrmr_scheduler")["parameter_changes"] == {}
    _alive(stack)


@pytest.mark.ros
@pytest.mark.slow
def test_cmd_vel_from_a_stranger_does_not_drive_the_base(stack, rogue):
    from nav_msgs.msg import Odometry

    from gsrmr_sim.limo.mock import GROUND_TRUTH_TOPIC

    node, ex, watch = rogue
    speeds: list[float] = []
    sub = node.create_subscription(Odometry, GROUND_TRUTH_TOPIC, lambda m: speeds.append(m.twist.twist.linear.x), 50)
    lies = Rogue(node, ex)
    lies.run("cmd_vel", 3.0)
    node.destroy_subscription(sub)
    assert lies.sent >= 40 and len(speeds) > 50
    assert max(speeds) < 0.5, max(speeds)  # the route's 0.3 m/s, never the rogue's 1 m/s
    assert _eventually(ex, lambda: _refused(watch, "gsrmr_limo_base").get("cmd_vel unlisted", 0) >= 40), \
        watch.counters("gsrmr_limo_base")
    assert "gsrmr_limo_base" in watch.named_by(ROGUE_NAME)


@pytest.mark.ros
@pytest.mark.slow
def test_an_impostor_under_a_legit_name_is_detected_and_its_lies_still_refused(stack, rogue):
    _node, ex, watch = rogue
    with ros_client(stack.env, "gsrmr_server") as (impostor, impostor_ex):
        lies = Rogue(impostor, impostor_ex)
        lies.run("impostor_loss", 3.0)
    assert lies.sent >= 40

    def counted() -> bool:
        scheduler = watch.counters("gsrmr_scheduler")
        return (scheduler["writer_alarms"].get("/gsrmr_server on gsrmr/loss_sample", 0) >= 1
                and scheduler["implausible"].get("loss_range", 0) >= lies.sent // 2)  # admitted by name, not by range

    assert _eventually(ex, counted), (lies.sent, watch.counters("gsrmr_scheduler"))
    assert "gsrmr_scheduler" in watch.named_by("two live endpoints under /gsrmr_server")
    _alive(stack)


@pytest.mark.ros
@pytest.mark.slow
def test_the_stack_exits_cleanly_after_the_lies(stack):
    took = stack.stop()
    for name, proc in stack.procs.items():
        assert proc.returncode == 0, (name, proc.returncode, took.get(name), stack.log(name)[-1500:])
    summary = json.loads((stack.tmp / "rec" / "server_summary.json").read_text())
    assert f"/{ROGUE_NAME}" in summary["writers_refused"]
    # each deployment node's last word: what its input checks counted, one JSON object (what
    # bench/acceptance/demo.py sums)
    from gsrmr_common.ros_admission import SUMMARY_PREFIX

    checks = {}
    for name in ("gsrmr_robot", "gsrmr_server", "gsrmr_scheduler", "gsrmr_limo_base"):
        lines = [line for line in stack.log(name).splitlines() if SUMMARY_PREFIX in line]
        assert len(lines) == 1, (name, stack.log(name)[-1500:])
        checks[name] = json.loads(lines[0].split(SUMMARY_PREFIX, 1)[1])
    assert checks["gsrmr_scheduler"]["writers_refused"][f"/{ROGUE_NAME}"]["gsrmr/loss_sample unlisted"] >= 100
    assert checks["gsrmr_scheduler"]["implausible"]["loss_range"] >= 40  # the impostor's
    assert checks["gsrmr_scheduler"]["replans_refused"] > 20
    assert checks["gsrmr_limo_base"]["writers_refused"][f"/{ROGUE_NAME}"]["cmd_vel unlisted"] >= 40
    # the simulation's measuring instrument took neither the foreign ledger nor the rogue camera_info
    (line,) = [line for line in stack.log("gsrmr_sim_scorer").splitlines() if SUMMARY_PREFIX in line]
    scorer = json.loads(line.split(SUMMARY_PREFIX, 1)[1])["writers_refused"][f"/{ROGUE_NAME}"]
    assert scorer.get("gsrmr/ledger unlisted", 0) >= 10 and scorer.get("uplink/camera_info unlisted", 0) >= 1, scorer
