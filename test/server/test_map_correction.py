"""The server's correction filter: fixes of the robot's pose become a numbered map → odom correction; fixes that
cannot be trusted are refused; the states unlocalized, tracking, lost."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gsrmr_common.pose2d import Pose2D
from gsrmr_server.map_correction import (
    FIX_JUMP,
    FIX_STALE,
    FIX_UNKNOWN_CORRECTION,
    LOST,
    TRACKING,
    UNLOCALIZED,
    CorrectionFilter,
    Fix,
)

#: The robot's odometry is off by this: the true pose is ERROR ∘ (what it reports with no correction).
ERROR = Pose2D(0.06, -0.04, math.radians(1.5))


def fix_at(t_s: float, believed: Pose2D, correction: Pose2D, seq: int, rng: np.random.Generator,
           noise_m: float = 0.003, noise_rad: float = math.radians(0.05)) -> Fix:
    """The fix of a key the robot made with correction ``seq`` (= ``correction``) where it believed itself at
    ``believed`` (uncorrected): the key is correction ∘ believed, the truth ERROR ∘ believed, seen with noise."""
    truth = ERROR.compose(believed)
    seen = Pose2D(truth.x_m + rng.normal(0, noise_m), truth.y_m + rng.normal(0, noise_m),
                  truth.theta_rad + rng.normal(0, noise_rad))
    return Fix(t_s, seen, correction.compose(believed), seq)


def test_fixes_converge_on_the_odometry_error_through_the_corrections_sent():
    rng = np.random.default_rng(1)
    f = CorrectionFilter()
    assert f.update_state(0.0) == UNLOCALIZED and f.next_correction() is None
    correction, seq = Pose2D(), 0
    for k in range(20):
        believed = Pose2D(1.0 + 0.3 * k, 0.5, 0.1 * k)
        assert f.offer(fix_at(float(k), believed, correction, seq, rng), travelled_m=0.3) is None
        sent = f.next_correction()  # the robot applies it: its next keys are made with it
        correction, seq = sent.x, sent.seq
    assert f.state == TRACKING and seq == 20 and f.accepted == 20
    assert correction.distance_m(ERROR) < 0.003 and abs(correction.heading_error_rad(ERROR)) < math.radians(0.05)
    assert max(sent.variance[:2]) < 0.005 ** 2 and f.correction_of(seq) == correction


def test_jumps_stale_and_unknown_fixes_are_refused_and_a_run_of_them_is_lost():
    rng = np.random.default_rng(2)
    f = CorrectionFilter()
    far = Fix(0.0, Pose2D(2.0, 0.0, 0.0), Pose2D(), 0)  # a first fix no start error explains
    assert f.offer(far) == FIX_JUMP and f.state == UNLOCALIZED
    assert f.offer(fix_at(1.0, Pose2D(1.0, 0.0, 0.0), Pose2D(), 0, rng)) is None
    assert f.offer(Fix(0.5, Pose2D(), Pose2D(), 0)) == FIX_STALE
    assert f.offer(fix_at(2.0, Pose2D(1.0, 0.0, 0.0), Pose2D(), 7, rng)) == FIX_UNKNOWN_CORRECTION
    assert f.state == TRACKING
    for k in range(3):  # 30 cm off a tracked estimate, a second apart: odometry cannot drift so
        jump = Fix(3.0 + k, ERROR.compose(Pose2D(1.3, 0.0, 0.0)), Pose2D(1.0, 0.0, 0.0), 0)
        assert f.offer(jump, travelled_m=0.0) == FIX_JUMP
    assert f.state == LOST and f.refused[FIX_JUMP] == 4  # five refused in a row
    relocalized = Fix(9.0, Pose2D(1.2, 0.1, 0.0), Pose2D(1.0, 0.0, 0.0), 0)  # within a start error: taken
    assert f.offer(relocalized) is None and f.state == TRACKING


def test_a_robot_without_fixes_for_a_while_is_lost():
    rng = np.random.default_rng(3)
    f = CorrectionFilter()
    f.offer(fix_at(100.0, Pose2D(), Pose2D(), 0, rng))
    assert f.update_state(105.0) == TRACKING and f.update_state(110.5) == LOST


@pytest.mark.parametrize("travelled_m", [0.0, 5.0])
def test_the_estimate_follows_a_drift_more_readily_the_further_the_robot_drove(travelled_m):
    """The same surprise is weighed against the drift odometry could have made: after 5 m the filter moves most
    of the way to a 2 cm jump, parked it moves little."""
    f = CorrectionFilter()
    f.offer(Fix(0.0, Pose2D(1.0, 0.0, 0.0), Pose2D(1.0, 0.0, 0.0), 0))
    f.offer(Fix(1.0, Pose2D(1.02, 0.0, 0.0), Pose2D(1.0, 0.0, 0.0), 0), travelled_m=travelled_m)
    moved = f.x.x_m
    assert (moved > 0.015) if travelled_m else (moved < 0.012)


def test_the_correction_record_round_trips_and_refuses_what_is_no_correction():
    from gsrmr_common.wire import MapCorrection

    c = MapCorrection(3, 12.5, 0.1, -0.2, 0.03, 1e-5, 2e-5, 1e-6)
    assert MapCorrection.from_data(c.to_data()) == c
    for bad in ([0, 1, 0, 0, 0, 0, 0, 0], [1.5, 1, 0, 0, 0, 0, 0, 0], [1, 1, math.nan, 0, 0, 0, 0, 0],
                [1, 1, 0, 0, 0, -1, 0, 0], [1, 1, 0, 0, 0, 0, 0]):
        with pytest.raises(ValueError):
            MapCorrection.from_data(bad)
