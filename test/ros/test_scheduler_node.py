"""The scheduler node and the planner's other users talk to the planner through its public API only; a live
parameter change (`ros2 param set`) builds a new planner configuration and requests a replan."""

from __future__ import annotations

import ast
from dataclasses import replace
from pathlib import Path
import time

from conftest import ros_env
import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

from gsrmr_scheduler.scheduler_node import SchedulerNode

REPO = Path(__file__).resolve().parents[2]
# every module that drives an OnlinePlanner from outside the planner package
PLANNER_USERS = ["gsrmr_scheduler/scheduler_node.py", "gsrmr_scheduler/replan_log.py",
                 "gsrmr_sim/analysis/planner_replay.py", "gsrmr_sim/replay.py", "bench/perf/scheduler.py",
                 "bench/perf/scheduler_start.py"]
ROUTE = [-1.0, -1.1, 1.0, -1.1, 1.2, 0.9, -1.2, 0.9]


def private_uses(source: str) -> list[str]:
    """``line: what`` for every private attribute of another object (``x._name``, anything but ``self._name``),
    every ``setattr`` and every assignment to an attribute of a planner (``….planner.x = …``) in ``source``: a
    module that does none of these cannot reach into the planner's state."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
            if not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls")):
                found.append(f"{node.lineno}: {ast.unparse(node)}")
        elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store):
            chain = node.value
            while isinstance(chain, ast.Attribute) and chain.attr != "planner":
                chain = chain.value
            if (isinstance(chain, ast.Attribute) and chain.attr == "planner") or (
                    isinstance(chain, ast.Name) and chain.id == "planner"):
                found.append(f"{node.lineno}: {ast.unparse(node)} =")
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "setattr":
            found.append(f"{node.lineno}: {ast.unparse(node)}")
    return sorted(found, key=lambda line: int(line.split(":")[0]))


def test_the_scan_finds_what_it_looks_for():
    sample = ("def f(self, planner):\n    self.planner._active = 1\n    p = self.planner\n    p.seq = p._seq\n"
              "    setattr(planner, 'horizon', 5)\n    self._lock = None\n    planner.options = {}\n"
              "    self.planner.budget.slots_done = 0\n    self.params.x = 1\n    return planner.__class__\n")
    assert private_uses(sample) == ["2: self.planner._active", "4: p._seq", "5: setattr(planner, 'horizon', 5)",
                                    "7: planner.options =", "8: self.planner.budget.slots_done ="]


@pytest.mark.parametrize("path", PLANNER_USERS)
def test_planner_users_touch_no_private_attribute_and_set_nothing_by_name(path):
    assert private_uses((REPO / path).read_text()) == []


def test_the_server_s_samples_of_a_flood_pause_reach_the_scheduler_when_it_reads_again(scheduler):
    """Issue 28: a flood pauses the scheduler's ``gsrmr/loss_sample`` reader for a second; the server's samples of
    that second are not lost — the topic is latched (``LOSS_SAMPLE_QOS``), the new reader gets the writer's history
    over DDS, takes what it missed and drops what it had taken (``loss_samples_redelivered``), none implausible."""
    from std_msgs.msg import Float64MultiArray

    from gsrmr_common.ros_wire import LOSS_SAMPLE_QOS, ledger_to_msg, loss_sample_to_msg
    from gsrmr_common.wire import LedgerRow, LossSample

    node, spin_until = scheduler
    assert spin_until(lambda: node.log.last is not None)
    server = rclpy.create_node("gsrmr_server", context=node.context)
    try:
        pub = server.create_publisher(Float64MultiArray, "gsrmr/loss_sample", LOSS_SAMPLE_QOS)
        now = node.clock.slot_at(node.get_clock().now().nanoseconds)
        slots = list(range(now - 8, now))
        for slot in slots:
            node._on_ledger(ledger_to_msg(LedgerRow(slot, 1, 1e-3, 64_000, 1e-6, 1e-3, 1e-4, 64_000, 1e-4)))
        samples = node.planner.forecast.samples

        def send(slot: int) -> None:
            pub.publish(loss_sample_to_msg(LossSample(slot, -1.0, -1.1, 0.0, 0.02)))

        assert spin_until(lambda: pub.get_subscription_count() == 1)
        for slot in slots[:4]:
            send(slot)
        assert spin_until(lambda: node.planner.forecast.samples == samples + 4)
        node.inputs._pause("gsrmr/loss_sample", "/a_test_flood")  # what FloodBreaker's 200th refusal does
        assert spin_until(lambda: pub.get_subscription_count() == 0)
        for slot in slots[4:]:
            send(slot)  # no reader now
        spin_until(lambda: False, timeout_s=0.3)
        assert node.planner.forecast.samples == samples + 4
        node.inputs._resume("gsrmr/loss_sample")
        assert spin_until(lambda: node.planner.forecast.samples == samples + 8
                          and node.intake.loss_samples_redelivered == 4)
        assert not node.intake.implausible
    finally:
        server.destroy_node()


# ---------------------------------------------------------------------------- a live parameter change
@pytest.fixture
def scheduler(monkeypatch):
    """A SchedulerNode in this process, in its own ROS domain, spun by a single-threaded executor."""
    env = ros_env()
    for key in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE"):
        monkeypatch.setenv(key, env[key])
    monkeypatch.delenv("ROS_LOCALHOST_ONLY", raising=False)
    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(env["ROS_DOMAIN_ID"]))
    node = None
    try:
        node = SchedulerNode(context=ctx, parameter_overrides=[Parameter("route_waypoints_m", value=ROUTE),
                                                               Parameter("live_parameter_changes", value=True)])
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(node)

        def spin_until(done, timeout_s: float = 20.0) -> bool:
            end = time.monotonic() + timeout_s
            while time.monotonic() < end and not done():
                executor.spin_once(timeout_sec=0.02)
            return done()

        yield node, spin_until
        executor.shutdown()
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.shutdown(context=ctx)


def test_a_live_parameter_change_builds_a_new_config_and_requests_a_replan(scheduler):
    node, spin_until = scheduler
    assert spin_until(lambda: node.log.last is not None)  # the start-up plan
    before, seq = node.planner.config, node.planner.seq
    assert before == node.params.planner_config(node.planner.loss_map) and before.loss_threshold == 0.03
    result, = node.set_parameters([Parameter("loss_threshold", value=0.02)])
    assert result.successful, result.reason
    after = node.planner.config
    assert after is not before and after == replace(before, loss_threshold=0.02)
    assert before.loss_threshold == 0.03  # the old configuration is a value: unchanged
    assert spin_until(lambda: node.log.replans.get("parameters", 0) == 1)  # the change requested a replan …
    assert node.planner.seq > seq and node.log.last.schedule.seq == node.planner.seq  # … and it was published


def test_a_change_the_planner_refuses_is_refused_on_set(scheduler):
    node, _ = scheduler
    before = node.planner.config
    result, = node.set_parameters([Parameter("image_bits", value=100.0)])  # not larger than a pose key
    assert not result.successful and "image_bits must exceed pose_bits" in result.reason
    result, = node.set_parameters([Parameter("oracle_channel", value=True)])
    assert not result.successful and "read-only" in result.reason
    assert node.planner.config is before and node.params.image_bits == before.image_bits


def test_a_new_loss_map_file_reseeds_the_forecast_and_replans(scheduler, tmp_path):
    """Issue 27: after a model swap the operator sets the new model's survey as loss_map_file: the forecast predicts
    from it and a replan follows; a file that is no loss map is refused and changes nothing."""
    from gsrmr_scheduler.loss_map import LossMap

    node, spin_until = scheduler
    assert spin_until(lambda: node.log.last is not None)
    (tmp_path / "bad.json").write_text("[1, 2]")
    result, = node.set_parameters([Parameter("loss_map_file", value=str(tmp_path / "bad.json"))])
    assert not result.successful and "is no loss map" in result.reason
    result, = node.set_parameters([Parameter("loss_map_file", value=str(tmp_path / "missing.json"))])
    assert not result.successful and node.params.loss_map_file == ""
    seeded = LossMap(prior=0.05)
    for x in np.linspace(0.0, 3.0, 30):
        seeded.add(float(x), 0.0, 0.0, 0.011)
    seeded.save(tmp_path / "v1.json")
    old_map = node.planner.loss_map
    result, = node.set_parameters([Parameter("loss_map_file", value=str(tmp_path / "v1.json"))])
    assert result.successful, result.reason
    assert node.planner.loss_map is not old_map and len(node.planner.loss_map.cells) == len(seeded.cells)
    assert node.planner.loss_map.predict(1.5, 0.0, 0.0) == pytest.approx(0.011)
    assert spin_until(lambda: node.log.replans.get("parameters", 0) >= 1)


# ---------------------------------------------------------------------------- loss samples checked against the ledger
def test_loss_samples_are_taken_once_per_image_slot_the_ledger_names(scheduler):
    """Issue 28: a loss sample counts only for a slot whose ledger row says it carried an image, once; one for a slot
    before the first ledger row heard (start-up) is not used and counted apart, never as implausible."""
    from gsrmr_common.ros_wire import ledger_to_msg, loss_sample_to_msg
    from gsrmr_common.wire import LedgerRow, LossSample

    node, spin_until = scheduler
    assert spin_until(lambda: node.log.last is not None)
    now = node.clock.slot_at(node.get_clock().now().nanoseconds)

    def ledger(slot: int, x: int) -> None:
        node._on_ledger(ledger_to_msg(LedgerRow(slot, x, 1e-3, 64_000 if x else 192, 1e-6, 1e-3, 1e-4, 64_000,
                                                1e-4)))

    def loss(slot: int, value: float = 0.02) -> None:
        node._on_loss(loss_sample_to_msg(LossSample(slot, -1.0, -1.1, 0.0, value)))

    loss(now - 30)  # before any ledger row: the robot's rows of that time may not have reached the scheduler
    assert spin_until(lambda: node.intake.loss_samples_unverified == 1) and not node.intake.implausible
    ledger(now - 5, 1)
    ledger(now - 4, 0)
    samples = node.planner.forecast.samples
    loss(now - 5)
    assert node.planner.forecast.samples == samples + 1 and not node.intake.implausible  # an image slot: observed
    loss(now - 5)  # the very same sample again (the latched history, read by a reader that resubscribed)
    assert node.intake.loss_samples_redelivered == 1 and node.planner.forecast.samples == samples + 1
    assert not node.intake.implausible
    loss(now - 5, 0.5)
    loss(now - 4)
    loss(now - 5, 5.0)
    assert node.intake.implausible == {"loss_repeat": 1, "loss_key_slot": 1, "loss_range": 1}
    loss(now - 40)  # before the first row heard: unverified
    loss(now - 3)  # after it, its row never comes: waits 20 slots, then implausible
    assert spin_until(lambda: node.intake.implausible.get("loss_unledgered") == 1, timeout_s=10.0)
    assert node.intake.loss_samples_unverified == 2 and node.planner.forecast.samples == samples + 1


def test_the_server_s_slot_info_reaches_the_budget_and_a_far_slot_is_refused(scheduler):
    """``mr/slot_info`` from the server (a ``loss_writers`` node) says what each slot was composed from: the budget
    charges the slot by it (an image that missed its slot as the render used, a render below full size with its
    level's extra loss); a slot far from now is refused, and
    so is what a node not in ``loss_writers`` says (it could make the planner over-charge and send images)."""
    from std_msgs.msg import Float64MultiArray

    from gsrmr_common.ros_wire import UPLINK_QOS, mr_slot_info_to_msg
    from gsrmr_common.wire import MR_SLOT_INFO_TOPIC, MRSlotInfo, PoseKey, RealSource

    node, spin_until = scheduler
    assert spin_until(lambda: node.log.last is not None)
    server = rclpy.create_node("gsrmr_server", context=node.context)
    rogue = rclpy.create_node("gsrmr_rogue", context=node.context)
    try:
        pub = server.create_publisher(Float64MultiArray, MR_SLOT_INFO_TOPIC, UPLINK_QOS)
        forged = rogue.create_publisher(Float64MultiArray, MR_SLOT_INFO_TOPIC, UPLINK_QOS)
        assert spin_until(lambda: pub.get_subscription_count() == 1 and forged.get_subscription_count() == 1)
        now = node.clock.slot_at(node.get_clock().now().nanoseconds)
        pose = PoseKey(now - 2, -1.0, -1.1, 0.0)
        forged.publish(mr_slot_info_to_msg(MRSlotInfo.of(now - 3, RealSource.NONE, pose, 1.0)))
        pub.publish(mr_slot_info_to_msg(MRSlotInfo.of(now - 2, RealSource.FALLBACK, pose, 1.0, level=1)))
        pub.publish(mr_slot_info_to_msg(MRSlotInfo.of(now - 500, RealSource.RENDER, pose, 1.0)))
        assert spin_until(lambda: node.intake.implausible.get("slot_info_slot") == 1
                          and node.planner.budget._composed.get(now - 2) == ("fallback", 1))  # and its level
        assert now - 500 not in node.planner.budget._composed
        # refused by its name ("unlisted"), or as "unknown" should the graph not name its writer within the hold
        refused = node.inputs.gate.refused
        assert spin_until(lambda: sum(n for (topic, _w, why), n in list(refused.items())
                                      if topic == MR_SLOT_INFO_TOPIC and why in ("unlisted", "unknown")) == 1)
        assert node.inputs.gate.refused_by_writer().get("/gsrmr_rogue", {}) in (
            {f"{MR_SLOT_INFO_TOPIC} unlisted": 1}, {})
        assert now - 3 not in node.planner.budget._composed
    finally:
        rogue.destroy_node()
        server.destroy_node()
