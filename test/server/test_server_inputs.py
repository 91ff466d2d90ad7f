"""The server's input checks (gsrmr_server.server_inputs), without a node: what is refused, counted and taken."""

from __future__ import annotations

import threading

import numpy as np
from sensor_msgs.msg import CompressedImage
from std_msgs.msg import Float64MultiArray

from gsrmr_common.ros_wire import (
    compressed_to_msg,
    ledger_to_msg,
    pose_key_to_msg,
    schedule_to_msg,
)
from gsrmr_common.slot_clock import SlotClock
from gsrmr_common.tf_tree import CAMERA_OPTICAL_FRAME
from gsrmr_common.wire import MAX_COMPRESSED_BYTES, LedgerRow, PoseKey, ScheduleMsg, UplinkFault
from gsrmr_server.server_inputs import ServerInputs

CLOCK = SlotClock(0.1)
SLOT0 = 10_000


def _inputs() -> ServerInputs:
    return ServerInputs(CLOCK, max_speed_mps=1.5, lock=threading.Lock())


def _now(slot: int) -> int:
    return CLOCK.start_ns(slot) + 1_000_000


def _row(slot: int, x: int = 0) -> LedgerRow:
    return LedgerRow(slot=slot, x=x, scheduled_power_w=0.01, bits_sent=192, gain=1e-7, power_w=0.01, energy_j=1e-4,
                     upload_all_bits=400_000, upload_all_energy_j=0.1)


def _schedule(first_slot: int, seq: int) -> ScheduleMsg:
    return ScheduleMsg(first_slot=first_slot, slot_s=0.1, seq=seq, x=np.zeros(20, np.int8),
                       power_w=np.full(20, 0.01))


def test_a_pose_key_that_jumps_past_the_robots_reach_is_refused_counted_and_explained():
    inputs = _inputs()
    assert inputs.on_key(pose_key_to_msg(PoseKey(SLOT0, 1.0, 2.0, 0.0), CLOCK), _now(SLOT0)) is None
    assert inputs.on_key(pose_key_to_msg(PoseKey(SLOT0 + 1, 1.05, 2.0, 0.0), CLOCK), _now(SLOT0 + 1)) is None
    line = inputs.on_key(pose_key_to_msg(PoseKey(SLOT0 + 2, 3.0, 2.0, 0.0), CLOCK), _now(SLOT0 + 2))
    assert inputs.implausible == {"pose_jump": 1}
    assert line is not None and "pose_jump" in line and "1.950 m" in line and f"slot {SLOT0 + 1}" in line
    # the accepted keys are in the books, the refused one is not: slot SLOT0 + 2 renders at the extrapolation
    with inputs.lock:
        _, uploads, best = inputs.take(SLOT0 + 2)
    assert uploads.key is None and best is not None and abs(best.a_m - 1.10) < 1e-6


def test_a_malformed_or_oversized_upload_is_a_wire_fault_not_an_exception():
    inputs = _inputs()
    bad = pose_key_to_msg(PoseKey(SLOT0, 1.0, 2.0, 0.0), CLOCK)
    bad.header.frame_id = "odom_wrong"
    inputs.on_key(bad, _now(SLOT0))
    inputs.on_image(CompressedImage(data=b"\xff" * (MAX_COMPRESSED_BYTES + 1)), _now(SLOT0))
    inputs.on_ledger(Float64MultiArray(data=[1.0, 2.0]), _now(SLOT0))
    assert inputs.uplink.faults[UplinkFault.MALFORMED_KEY] == 1
    assert inputs.uplink.faults[UplinkFault.OVERSIZED_IMAGE] == 1
    assert inputs.uplink.faults[UplinkFault.MALFORMED_LEDGER] == 1
    assert not inputs.implausible


def test_one_ledger_row_per_slot_near_the_slot_composed():
    inputs = _inputs()
    inputs.on_ledger(ledger_to_msg(_row(SLOT0, x=1)), _now(SLOT0))
    inputs.on_ledger(ledger_to_msg(_row(SLOT0, x=0)), _now(SLOT0))  # a second row for the slot: the first stands
    inputs.on_ledger(ledger_to_msg(_row(SLOT0 + 100_000)), _now(SLOT0))  # far from now
    assert inputs.implausible["ledger_repeat"] == 1
    assert sum(inputs.implausible.values()) == 2
    # the first row's x = 1 stands: the slot is not complete on its key alone, it waits for the image
    inputs.on_key(pose_key_to_msg(PoseKey(SLOT0, 1.0, 2.0, 0.0), CLOCK), _now(SLOT0))
    assert not inputs.complete(SLOT0)
    inputs.on_image(compressed_to_msg(b"\xff\xd8jpeg", CLOCK.start_ns(SLOT0), CAMERA_OPTICAL_FRAME), _now(SLOT0))
    assert inputs.complete(SLOT0)


def test_a_schedule_is_taken_once_per_seq_and_an_older_one_is_refused():
    inputs = _inputs()
    newer = schedule_to_msg(_schedule(SLOT0, seq=5))
    assert inputs.on_schedule(newer, b"writer-a", _now(SLOT0)) is None
    assert inputs.ledgers.schedule is not None and inputs.ledgers.schedule.seq == 5
    inputs.on_schedule(newer, b"writer-a", _now(SLOT0))  # latched redelivery: nothing new, nothing counted
    inputs.on_schedule(schedule_to_msg(_schedule(SLOT0, seq=4)), b"writer-a", _now(SLOT0))
    assert inputs.implausible == {"schedule_seq": 1}
    assert inputs.ledgers.schedule.seq == 5
    line = inputs.on_schedule(Float64MultiArray(data=[1.0]), b"writer-a", _now(SLOT0))
    assert line is not None and line.startswith("schedule refused")
    assert inputs.implausible["schedule_malformed"] == 1
    assert inputs.problems() == ["implausible inputs refused: schedule_malformed 1, schedule_seq 1"]
