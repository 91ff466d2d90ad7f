"""The robot's map → odom: its parameter, corrected by the server's numbered corrections, each checked."""

from __future__ import annotations

import math

import pytest

from gsrmr_common.plausibility import Implausible
from gsrmr_common.pose2d import Pose2D
from gsrmr_common.wire import MapCorrection
from gsrmr_robot.map_source import (
    CORRECTION_SEQ,
    CORRECTION_STEP,
    CORRECTION_TOTAL,
    CorrectionLimits,
    MapSource,
)


def correction(seq: int, x: float, y: float = 0.0, theta: float = 0.0) -> MapCorrection:
    return MapCorrection(seq, float(seq), x, y, theta, 1e-5, 1e-5, 1e-6)


def test_a_correction_moves_map_to_odom_and_names_itself():
    m = MapSource(Pose2D(1.0, 2.0, math.pi / 2), CorrectionLimits(), Implausible())
    assert m.map_from_odom() == Pose2D(1.0, 2.0, math.pi / 2) and m.seq == 0
    assert m.offer(correction(1, 0.05, -0.02, 0.01), b"server") is None
    x, y, theta = m.map_from_odom()  # X ∘ M₀: the correction on the left, in map
    c, s = math.cos(0.01), math.sin(0.01)
    assert (x, y, theta) == pytest.approx((0.05 + c * 1.0 - s * 2.0, -0.02 + s * 1.0 + c * 2.0, math.pi / 2 + 0.01))
    assert m.seq == 1 and m.stamp_s == 1.0
    assert m.offer(correction(1, 0.05, -0.02, 0.01), b"server") is None and m.seq == 1  # latched again: a repeat


def test_replays_jumps_and_runaway_corrections_are_refused_and_counted():
    implausible = Implausible()
    m = MapSource(Pose2D(), CorrectionLimits(), implausible)
    assert m.offer(correction(5, 0.1), b"server") is None
    assert m.offer(correction(4, 0.1), b"server") == CORRECTION_SEQ  # a replay of an older one
    assert m.offer(correction(6, 0.9), b"server") == CORRECTION_STEP  # 0.8 m in one step
    assert m.offer(correction(7, 0.1, theta=math.radians(25)), b"server") == CORRECTION_STEP
    far = MapSource(Pose2D(), CorrectionLimits(max_step_m=10.0), Implausible())
    assert far.offer(correction(1, 5.0), b"server") == CORRECTION_TOTAL
    assert dict(implausible) == {CORRECTION_SEQ: 1, CORRECTION_STEP: 2}
    assert m.correction == Pose2D(0.1, 0.0, 0.0) and m.seq == 5
    assert m.offer(correction(1, 0.12), b"restarted server") is None and m.seq == 1  # a new writer starts afresh
