"""LIMO kinematics (command ↔ wire ↔ body velocity) and odometry integration, pure."""

import math

import pytest

from gsrmr_common.pose2d import Pose2D, wrap_angle
from gsrmr_robot.limo import kinematics as kin
from gsrmr_robot.limo.odometry import Odometry2D
from gsrmr_robot.limo.protocol import MotionCommand, MotionMode, MotionState


def test_diff_and_mecanum_field_mapping():
    assert kin.command_to_wire(MotionMode.DIFF, 0.3, 0.4, 0.5) == MotionCommand(0.3, 0.4, 0.0, 0.0)
    assert kin.command_to_wire(MotionMode.MECANUM, 0.3, 0.4, 0.5) == MotionCommand(0.3, 0.4, 0.5, 0.0)


def test_clamps_linear_lateral_angular():
    cmd = kin.command_to_wire(MotionMode.MECANUM, 3.0, -100.0, -2.0)
    assert cmd.linear_mps == 1.0 and cmd.lateral_mps == -1.0
    assert cmd.angular_radps == pytest.approx(-2 / 0.172)


def test_ackermann_inner_angle_clamped_to_limo_limit():
    cmd = kin.command_to_wire(MotionMode.ACKERMANN, 0.5, 5.0)  # r = 0.1 m, far tighter than possible
    assert cmd.steering_raw * kin.ANGLE_SCALE == pytest.approx(kin.MAX_INNER_ANGLE_RAD)
    right = kin.command_to_wire(MotionMode.ACKERMANN, 0.5, -5.0)
    assert right.steering_raw * kin.ANGLE_SCALE == pytest.approx(-kin.MAX_INNER_ANGLE_RAD)


@pytest.mark.parametrize("mode", [MotionMode.DIFF, MotionMode.ACKERMANN, MotionMode.MECANUM, MotionMode.UNKNOWN])
@pytest.mark.parametrize("vx, wz", [(0.0, 0.0), (0.0, 0.5), (0.5, 0.0), (math.nan, 0.1), (0.2, math.inf)])
def test_no_nan_ever(mode, vx, wz):
    cmd = kin.command_to_wire(mode, vx, wz)
    assert all(math.isfinite(x) for x in (cmd.linear_mps, cmd.angular_radps, cmd.lateral_mps, cmd.steering_raw))
    body = kin.wire_to_body(mode, cmd)
    assert all(math.isfinite(x) for x in (body.vx_mps, body.vy_mps, body.wz_radps))


def test_unknown_mode_holds_the_base():
    assert kin.command_to_wire(MotionMode.UNKNOWN, 0.5, 0.5) == MotionCommand()
    assert kin.feedback_to_body(MotionMode.UNKNOWN, MotionState(0.5, 0.5)) == kin.BodyVelocity()


@pytest.mark.parametrize("vx, wz", [(0.3, 0.5), (-0.3, 0.5), (0.6, -0.4), (-0.2, -0.1)])
def test_ackermann_command_then_feedback_recovers_yaw_rate(vx, wz):
    cmd = kin.command_to_wire(MotionMode.ACKERMANN, vx, wz)
    body = kin.wire_to_body(MotionMode.ACKERMANN, cmd)
    assert body.vx_mps == pytest.approx(vx)
    assert body.wz_radps == pytest.approx(wz, rel=2e-3)  # exact but for 0.001 steering quantisation


def test_parse_motion_mode():
    assert kin.parse_motion_mode("auto") is None
    assert kin.parse_motion_mode("Ackermann") == MotionMode.ACKERMANN
    with pytest.raises(ValueError):
        kin.parse_motion_mode("tank")


def test_wrap_angle():
    assert wrap_angle(math.pi) == pytest.approx(math.pi)
    assert wrap_angle(-math.pi) == pytest.approx(math.pi)
    assert wrap_angle(3 * math.pi / 2) == pytest.approx(-math.pi / 2)


def test_odometry_circle_with_gyro_integration():
    odo = Odometry2D("gyro_integration")
    v, w, dt = 0.5, 0.5, 0.02
    for k in range(int(2 * math.pi / w / dt) + 1):
        odo.update_velocity(kin.BodyVelocity(v, 0.0, w), k * dt)
    t = int(2 * math.pi / w / dt) * dt
    r = v / w
    assert odo.pose.x_m == pytest.approx(r * math.sin(w * t), abs=1e-3)
    assert odo.pose.y_m == pytest.approx(r * (1 - math.cos(w * t)), abs=1e-3)
    assert odo.distance_m == pytest.approx(v * t)


def test_odometry_imu_heading_keeps_slow_turns_no_dead_band():
    odo = Odometry2D("imu")
    step = math.radians(0.05)  # below the official 0.1°-per-frame dead-band
    for k in range(400):
        odo.update_imu_yaw(wrap_angle(3.1 + k * step))  # crosses ±π on the way
        odo.update_velocity(kin.BodyVelocity(0.0, 0.0, 0.0), k * 0.02)
    assert odo.using_imu
    assert odo.pose.theta_rad == pytest.approx(399 * step, abs=1e-9)


def test_odometry_gap_is_not_integrated_and_counted():
    odo = Odometry2D("gyro_integration", max_gap_s=0.25)
    odo.update_velocity(kin.BodyVelocity(1.0), 0.0)
    odo.update_velocity(kin.BodyVelocity(1.0), 0.02)
    odo.update_velocity(kin.BodyVelocity(1.0), 5.0)  # link was down for 5 s
    odo.update_velocity(kin.BodyVelocity(1.0), 5.02)
    assert odo.pose.x_m == pytest.approx(0.04)
    assert odo.gaps == 1


def test_odometry_covariance_grows_with_distance_and_is_symmetric_psd():
    odo = Odometry2D("gyro_integration")
    c0 = odo.pose_covariance()
    for k in range(100):
        odo.update_velocity(kin.BodyVelocity(0.5, 0.0, 0.2), k * 0.02)
    c1 = odo.pose_covariance()
    assert len(c1) == 36 and c1[0] > c0[0] > 0 and c1[35] > c0[35] > 0
    assert all(c1[6 * i + j] == c1[6 * j + i] for i in range(6) for j in range(6))
    odo.reset(Pose2D(1.0, 2.0, 0.5))
    assert odo.pose == Pose2D(1.0, 2.0, 0.5)


def test_switching_heading_source_does_not_jump():
    odo = Odometry2D("gyro_integration")
    odo.update_imu_yaw(1.0)
    for k in range(50):
        odo.update_velocity(kin.BodyVelocity(0.0, 0.0, 0.3), k * 0.02)
    yaw = odo.pose.theta_rad
    odo.set_heading_source("imu")
    odo.update_velocity(kin.BodyVelocity(), 1.0)
    assert odo.pose.theta_rad == pytest.approx(yaw)
