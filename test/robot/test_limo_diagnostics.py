"""Diagnostics of gsrmr-limo-base from driver snapshots (uses the ROS message types, no processes)."""

from __future__ import annotations

from diagnostic_msgs.msg import DiagnosticStatus
import pytest

from gsrmr_common.pose2d import Pose2D
from gsrmr_robot.limo import kinematics as kin
from gsrmr_robot.limo import protocol as p
from gsrmr_robot.limo.driver import DriverSnapshot, LinkStatus
from gsrmr_robot.limo.node import diagnose, diagnostic_values, yaw_pitch_roll_to_quaternion


def snapshot(system: p.SystemState | None, connected: bool = True, rx_age_s: float = 0.01,
             mode: int = p.MotionMode.DIFF) -> DriverSnapshot:
    link = LinkStatus("/dev/ttyTHS1", connected=connected, connects=2, disconnects=1,
                      last_error="" if connected else "read: EIO", last_rx_t_s=100.0 - rx_age_s)
    return DriverSnapshot(t_s=100.0, pose=Pose2D(), velocity=kin.BodyVelocity(), pose_covariance=[0.0] * 36,
                          twist_covariance=[0.0] * 36, heading_from_imu=True, motion_mode=mode,
                          motion_mode_param="auto", system_state=system, imu=None, wheel_odometry=None, link=link,
                          parser={"frames_ok": 10, "bad_checksum": 2}, unknown_ids={0x777: 3}, implausible_frames=0,
                          frames_by_id={0x221: 10}, commands_sent=5, command_active=False,
                          last_command=p.MotionCommand(), enables_sent=1)


GOOD = p.SystemState(p.VehicleState.NORMAL, p.ControlMode.COMMANDED, 12.3, 0, p.MotionMode.DIFF)


def test_healthy_base_is_ok_and_values_are_decoded():
    level, problems = diagnose(snapshot(GOOD))
    assert level == DiagnosticStatus.OK and problems == []
    values = dict(diagnostic_values(snapshot(GOOD)))
    assert values["battery_voltage_v"] == "12.3" and values["control_mode"] == "commanded"
    assert values["reconnects"] == "1" and values["disconnects"] == "1"
    assert values["parser_bad_checksum"] == "2" and values["unknown_ids"] == "0x777:3"
    assert values["frames_0x221"] == "10"


@pytest.mark.parametrize("snap, level, text", [
    (snapshot(GOOD, connected=False), DiagnosticStatus.ERROR, "serial link down"),
    (snapshot(GOOD, rx_age_s=2.0), DiagnosticStatus.ERROR, "no data"),
    (snapshot(None, mode=p.MotionMode.UNKNOWN), DiagnosticStatus.WARN, "motion mode unknown"),
    (snapshot(p.SystemState(0, p.ControlMode.STANDBY, 12.3, 0, 0)), DiagnosticStatus.WARN, "standby"),
    (snapshot(p.SystemState(0, 1, 10.2, 0x0002, 0)), DiagnosticStatus.WARN, "battery_low_warning"),
    (snapshot(p.SystemState(0, 1, 12.0, 0x0001 | 0x0010, 0)), DiagnosticStatus.ERROR, "motor2_driver_error"),
    (snapshot(p.SystemState(p.VehicleState.EMERGENCY_STOP, 1, 12.0, 0, 0)), DiagnosticStatus.ERROR,
     "emergency_stop"),
])
def test_problems_raise_the_level(snap, level, text):
    got_level, problems = diagnose(snap)
    assert got_level == level
    assert any(text in msg for msg in problems), problems


def test_quaternion_from_yaw_pitch_roll():
    q = yaw_pitch_roll_to_quaternion(1.0, 0.0, 0.0)
    assert (q.x, q.y) == (0.0, 0.0) and q.z == pytest.approx(0.4794255) and q.w == pytest.approx(0.8775826)
    q = yaw_pitch_roll_to_quaternion(0.3, -0.2, 0.1)
    assert q.w ** 2 + q.x ** 2 + q.y ** 2 + q.z ** 2 == pytest.approx(1.0)
