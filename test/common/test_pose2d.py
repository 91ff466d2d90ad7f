"""The planar pose type: composition against homogeneous matrices, inverse, wrapping at the extremes, quaternions."""

from __future__ import annotations

import math

from hypothesis import given
from hypothesis import strategies as st
import numpy as np
import pytest

from gsrmr_common.pose2d import Pose2D, quaternion_from_yaw, wrap_angle, yaw_from_quaternion

finite = st.floats(-1e3, 1e3, allow_nan=False)
angle = st.floats(-50.0, 50.0, allow_nan=False)


def matrix(p) -> np.ndarray:
    c, s = math.cos(p[2]), math.sin(p[2])
    return np.array([[c, -s, p[0]], [s, c, p[1]], [0.0, 0.0, 1.0]])


@given(finite, finite, angle, finite, finite, angle)
def test_compose_is_the_product_of_the_homogeneous_matrices(x1, y1, t1, x2, y2, t2):
    a, b = Pose2D(x1, y1, t1), Pose2D(x2, y2, t2)
    m = matrix(a) @ matrix(b)
    ab = a.compose(b)
    np.testing.assert_allclose(matrix(ab), m, atol=1e-9 * (1 + abs(x1) + abs(y1) + abs(x2) + abs(y2)))
    assert -math.pi < ab.theta_rad <= math.pi


@given(finite, finite, angle)
def test_the_inverse_undoes_the_pose(x, y, t):
    p = Pose2D(x, y, t)
    identity = p.compose(p.inverse())
    assert identity.distance_m((0.0, 0.0)) <= 1e-9 * (1 + abs(x) + abs(y))
    assert abs(wrap_angle(identity.theta_rad)) <= 1e-12
    ahead = p.compose((1.0, 0.5, 0.25))  # a pose 1 m ahead, 0.5 m left of p, turned 0.25 rad
    rel = ahead.relative_to(p)
    assert rel.distance_m((1.0, 0.5)) == pytest.approx(0.0, abs=1e-9 * (1 + abs(x) + abs(y)))
    assert rel.theta_rad == pytest.approx(0.25, abs=1e-9)


def test_wrap_angle_is_half_open_and_exact_in_range():
    assert wrap_angle(math.pi) == math.pi and wrap_angle(-math.pi) == math.pi
    assert wrap_angle(3 * math.pi) == pytest.approx(math.pi) and wrap_angle(-3 * math.pi) == pytest.approx(math.pi)
    for a in (0.0, 0.1, -0.1, 1.5, -3.14, 3.14):
        assert wrap_angle(a) == a  # exact, not atan2(sin, cos)'s ulp noise
    assert wrap_angle(1e9) == pytest.approx(math.remainder(1e9, math.tau))
    assert math.isnan(wrap_angle(math.nan))


@given(angle)
def test_yaw_quaternion_round_trip_with_nonnegative_w(t):
    q = quaternion_from_yaw(t)
    assert q[3] >= 0 and math.isclose(sum(v * v for v in q), 1.0)
    assert yaw_from_quaternion(*q) == pytest.approx(wrap_angle(t), abs=1e-12) or abs(wrap_angle(t)) == pytest.approx(
        math.pi)
    assert Pose2D(0.0, 0.0, t).quaternion() == q


def test_a_pose_is_a_tuple():
    p = Pose2D.of(np.array([1.0, 2.0, 3.0]))
    x, y, t = p
    assert (x, y, t) == (1.0, 2.0, 3.0) == p and p[:2] == (1.0, 2.0) and isinstance(p.x_m, float)
    assert p.heading_error_rad((0.0, 0.0, 3.0 - 2 * math.pi)) == pytest.approx(0.0, abs=1e-12)
