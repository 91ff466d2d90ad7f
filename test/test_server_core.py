"""Tests of the server's uplink bookkeeping, the loss map, the wire formats and the server node's slot clock."""

import math

import numpy as np
import pytest

from gsrmr_common.wire import PoseKey, ScheduleMsg
from gsrmr_server.loss_map import LossMap
from gsrmr_server.uplink import UplinkAssembler


def test_schedule_roundtrip_and_rejects_inconsistent_data():
    msg = ScheduleMsg(1_000_000_123, 0.1, 7, np.array([1, 0, 0, 1], np.int8), np.array([0.5, 1e-6, 0.0, 2.0]))
    back = ScheduleMsg.from_data(msg.to_data())
    assert back.first_slot == msg.first_slot and back.seq == 7 and back.slot_s == 0.1
    np.testing.assert_array_equal(back.x, msg.x)
    np.testing.assert_allclose(back.power_w, msg.power_w)
    assert back.lookup(1_000_000_124) == (0, pytest.approx(1e-6))
    assert back.lookup(1_000_000_122) is None and back.lookup(1_000_000_127) is None
    data = msg.to_data()
    for bad in (data[:-1], [*data[:4], 2.0, *data[5:]], [*data[:-1], -1.0], [*data[:1], float("nan"), *data[2:]]):
        with pytest.raises(ValueError):
            ScheduleMsg.from_data(bad)


def test_assembler_counts_every_fault_and_never_blocks():
    up = UplinkAssembler(max_future_slots=10)
    up.on_key(PoseKey(5, 1.0, 2.0, 0.1), now_slot=5, now_ns=0)
    up.on_key(PoseKey(5, 1.0, 2.0, 0.1), now_slot=5, now_ns=0)  # duplicate
    up.on_key(PoseKey(6, float("nan"), 2.0, 0.1), now_slot=6, now_ns=0)  # invalid
    up.on_image(5, b"jpeg", now_slot=5, now_ns=0)
    up.on_image(5, b"jpeg", now_slot=5, now_ns=0)  # duplicate
    up.on_key(PoseKey(500, 0.0, 0.0, 0.0), now_slot=6, now_ns=0)  # far future: forged or bad clock
    s5 = up.take(5, image_expected=True)
    assert s5.key == PoseKey(5, 1.0, 2.0, 0.1) and s5.jpeg == b"jpeg" and not s5.faults
    up.on_image(5, b"late", now_slot=6, now_ns=0)  # after its slot was taken
    s6 = up.take(6, image_expected=True)
    assert s6.key is None and s6.jpeg is None and set(s6.faults) == {"missing_key", "missing_image"}
    assert dict(up.faults) == {"duplicate_key": 1, "invalid_key": 1, "duplicate_image": 1, "future": 1,
                               "late": 1, "missing_key": 1, "missing_image": 1}


def test_best_pose_extrapolates_and_is_bounded():
    up = UplinkAssembler(max_extrapolation_slots=3)
    assert up.best_pose(0) is None
    up.on_key(PoseKey(10, 0.0, 0.0, 0.0), 10, 0)
    up.on_key(PoseKey(12, 0.2, 0.0, 0.1), 12, 0)
    est = up.best_pose(13)
    assert (est.a_m, est.theta_rad) == (pytest.approx(0.3), pytest.approx(0.15))
    far = up.best_pose(100)
    assert far.a_m == pytest.approx(0.5)  # at most 3 slots of extrapolation


def test_loss_map_learns_neighbours_prior_and_forgets():
    lm = LossMap(cell_m=0.5, heading_bins=4, radius_m=1.0, prior=0.07, forgetting=0.5)
    assert lm.predict(0.1, 0.1, 0.0) == 0.07
    lm.add(0.1, 0.1, 0.0, 0.02)
    assert lm.predict(0.2, 0.3, 0.1) == pytest.approx(0.02)  # same cell, same sector
    assert lm.predict(0.6, 0.1, 0.0) == pytest.approx(0.02)  # neighbour cell
    assert lm.predict(0.1, 0.1, math.pi) == 0.07  # facing the other way: no information
    assert lm.predict(5.0, 5.0, 0.0) == 0.07  # far away
    for _ in range(5):
        lm.add(0.1, 0.1, 0.0, 0.2)  # the world changed here
    assert lm.predict(0.1, 0.1, 0.0) > 0.19
    lm.add(0.1, 0.1, 0.0, float("nan"))
    back = LossMap.from_json(lm.to_json())
    assert back.predict_many(np.array([[0.1, 0.1, 0.0], [9, 9, 0]])) == pytest.approx([lm.predict(0.1, 0.1, 0), 0.07])


@pytest.mark.ros
def test_server_catches_up_a_short_stall_and_skips_ahead_only_past_the_backlog_bound(tmp_path):
    """ServerNode's slot clock: a stall shorter than max_backlog_slots composes every missed slot in
    order (late); a longer one skips ahead to the current slot and counts skipped_slots once."""
    from types import SimpleNamespace

    from conftest import ros_env
    import rclpy
    from rclpy.context import Context
    from rclpy.parameter import Parameter
    from stack_harness import make_point_model

    from gsrmr_common.camera import Intrinsics
    from gsrmr_common.ros_wire import camera_info_from_intrinsics
    from gsrmr_server.server_node import ServerNode

    env = ros_env()
    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(env["ROS_DOMAIN_ID"]))
    try:
        node = ServerNode(context=ctx, parameter_overrides=[
            Parameter("model_path", value=str(make_point_model(tmp_path, n=50))),
            Parameter("process_delay_s", value=0.0)])
        slot_ns = node.clock.slot_len_ns
        now = {"ns": 1_000_000 * slot_ns}
        node.get_clock = lambda: SimpleNamespace(now=lambda: SimpleNamespace(nanoseconds=now["ns"]))
        composed: list[int] = []
        node.process_slot = composed.append
        node._tick()
        assert node.cursor.next is None and node.intrinsics is None  # no camera_info yet: the clock waits
        node.use_camera_info(camera_info_from_intrinsics(Intrinsics.from_fov(32, 24, 1.2), 0, "camera_optical_frame"))
        assert (node.intrinsics.width, node.intrinsics.height) == (32, 24) == (node.composer.intrinsics.width, 24)

        def tick_until_idle() -> None:
            for _ in range(1000):
                before = len(composed)
                node._tick()
                if len(composed) == before:
                    return

        node._tick()  # the clock starts at the next slot
        first = node.cursor.next
        now["ns"] += 20 * slot_ns  # a 2 s stall: 20 slots due, within the default bound of 30
        tick_until_idle()
        assert composed == list(range(first, first + 20))
        assert node.uplink.faults["skipped_slots"] == 0
        now["ns"] += 45 * slot_ns  # 4.5 s: past the bound → one skip ahead to the current slot
        tick_until_idle()
        assert node.uplink.faults["skipped_slots"] == 1
        assert composed[-1] == now["ns"] // slot_ns and composed[20] == composed[-1]
        # The bound is a live parameter; out of range is refused.
        assert node.set_parameters([Parameter("max_backlog_slots", value=100)])[0].successful
        assert node.params.max_backlog_slots == 100
        assert not node.set_parameters([Parameter("max_backlog_slots", value=0)])[0].successful
        assert node.set_parameters([Parameter("process_delay_s", value=0.05)])[0].successful
        assert node.params.process_delay_s == 0.05
        assert not node.set_parameters([Parameter("jpeg_quality", value=90.0)])[0].successful  # wrong type
        read_only = node.set_parameters([Parameter("render_threads", value=2)])[0]
        assert not read_only.successful and "read-only" in read_only.reason
        assert node.params.render_threads == 1 and node.params.jpeg_quality == 85
        assert node.set_parameters([Parameter("jpeg_quality", value=70)])[0].successful
        assert node.params.jpeg_quality == node.core.jpeg_quality == 70
        # A slot is composed before its deadline once its uploads are complete (no schedule: key + image).
        slot = node.cursor.next
        now["ns"] = slot * slot_ns + 1_000_000  # 1 ms into the slot, 49 ms before its deadline
        n = len(composed)
        node._tick()
        node.uplink.on_key(PoseKey(slot, 0.0, 0.0, 0.0), slot, now["ns"])
        node._tick()
        assert len(composed) == n  # the image may still come
        node.uplink.on_image(slot, b"jpeg", slot, now["ns"])
        node._tick()
        assert composed[n:] == [slot]
        node._tick()
        assert composed[n:] == [slot]  # the next slot has not started
        # A key-only slot is complete once the robot's ledger row says no image follows (whatever x the
        # schedule had: the robot decides in the slot).
        from gsrmr_common.wire import LedgerRow

        slot = node.cursor.next
        now["ns"] = slot * slot_ns + 1_000_000
        node._tick()
        node.uplink.on_key(PoseKey(slot, 0.0, 0.0, 0.0), slot, now["ns"])
        node._tick()
        assert composed[-1] != slot  # no image, no ledger: wait
        node._ledger[slot] = LedgerRow(slot, 0, 0.0, 192, 1e-6, 0.0, 0.0, 8000, 0.0)
        node._tick()
        assert composed[-1] == slot
        node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)


@pytest.mark.ros
def test_server_renders_with_the_robots_camera_info_and_refuses_an_unusable_one(tmp_path):
    """The render intrinsics are the robot's calibration: the first usable camera_info starts the slot clock,
    a new one is adopted for the next slot (the MR image has its size), a distorted one is refused (WARN in
    /diagnostics) and the last usable one kept."""
    from conftest import ros_env
    import rclpy
    from rclpy.context import Context
    from rclpy.parameter import Parameter
    from stack_harness import make_point_model

    from gsrmr_common.camera import Intrinsics
    from gsrmr_common.ros_wire import camera_info_from_intrinsics
    from gsrmr_server.server_node import ServerNode

    env = ros_env()
    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(env["ROS_DOMAIN_ID"]))
    try:
        node = ServerNode(context=ctx, parameter_overrides=[
            Parameter("model_path", value=str(make_point_model(tmp_path, n=50)))])
        assert node.camera_info_status == "waiting for camera_info"
        small, large = Intrinsics.from_fov(32, 24, 1.2), Intrinsics.from_fov(48, 36, 1.0)
        node.use_camera_info(camera_info_from_intrinsics(small, 0, "camera_optical_frame"))
        assert node.intrinsics == small and node.camera_info_status.startswith("32×24 fx=")
        node.process_slot(10)
        node.use_camera_info(camera_info_from_intrinsics(large, 0, "camera_optical_frame"))
        assert node.intrinsics == large == node.composer.intrinsics
        distorted = camera_info_from_intrinsics(small, 0, "camera_optical_frame")
        distorted.d = [0.1, 0.0, 0.0, 0.0, 0.0]
        node.use_camera_info(distorted)
        assert node.intrinsics == large and node.camera_info_status.startswith("unusable:")
        shapes: list[tuple[int, int]] = []
        node._pub_mr.publish = lambda msg: shapes.append((msg.width, msg.height))
        node.process_slot(11)
        assert shapes == [(48, 36)]
        node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
