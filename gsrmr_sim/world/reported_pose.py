"""The pose the robot would report along a headless drive: the LIMO's odometry, replayed offline (pure).

What the replay models and what it leaves out: docs/world.md, "The reported pose". Poses are (a_m, b_m, theta_rad)
of ``base_link`` in ``map`` (REP-103).
"""

from __future__ import annotations

import numpy as np

from gsrmr_common.pose2d import Pose2D, wrap_angle
from gsrmr_robot.limo import protocol as proto
from gsrmr_robot.limo.kinematics import feedback_to_body
from gsrmr_robot.limo.odometry import Odometry2D
from gsrmr_sim.limo.odometry_errors import OdometryErrorDraw
from gsrmr_sim.world.kinematics import Drive, unicycle_step


def _wire(msg):
    """``msg`` as the driver decodes it after one trip over the serial wire (quantised fields)."""
    return proto.decode_message(proto.decode_frame(proto.encode_message(msg)))


def reported_poses(drive: Drive, slot_s: float, odometry: OdometryErrorDraw | None = None) -> np.ndarray:
    """T×3 poses the robot reports at each slot start of ``drive`` (true start pose ``drive.poses[0]``), its
    odometry wrong as ``odometry`` says (the mock LIMO's model; None: only the wire's quantisation and the
    integration): the robot believes it started at the true start moved by the operator's error."""
    steps = drive.step_controls.shape[1]
    dt = slot_s / steps
    true = Pose2D.of(drive.poses[0])
    believed = true if odometry is None else true.compose(odometry.start_error.inverse())
    odo = Odometry2D(heading_source="imu")
    now = 0.0
    imu_offset = 0.0
    out = np.zeros_like(drive.poses)

    def feed(v_mps: float, w_radps: float) -> None:
        yaw = wrap_angle(true[2] + imu_offset)
        odo.update_imu_yaw(_wire(proto.ImuEuler(yaw, 0.0, 0.0)).yaw_rad)
        v_reported = v_mps if odometry is None else odometry.errors.reported_speed(v_mps, w_radps)
        state = _wire(proto.MotionState(v_reported, w_radps, 0.0, 0.0))
        odo.update_velocity(feedback_to_body(proto.MotionMode.DIFF, state), now)

    feed(0.0, 0.0)
    for t in range(drive.poses.shape[0]):
        out[t] = believed.compose(odo.pose)
        for v, w in drive.step_controls[t]:
            true = unicycle_step(true, float(v), float(w), dt)
            now += dt
            imu_offset = 0.0 if odometry is None else odometry.advance(dt)
            feed(float(v), float(w))
    return out


def pose_errors(reported: np.ndarray, true: np.ndarray) -> dict[str, float]:
    """Position (m) and heading (rad) error of ``reported`` against ``true`` (both T×3): mean and max."""
    d = np.hypot(reported[:, 0] - true[:, 0], reported[:, 1] - true[:, 1])
    h = np.abs(np.arctan2(np.sin(reported[:, 2] - true[:, 2]), np.cos(reported[:, 2] - true[:, 2])))
    return {"position_mean_m": float(d.mean()), "position_max_m": float(d.max()),
            "heading_mean_rad": float(h.mean()), "heading_max_rad": float(h.max())}
