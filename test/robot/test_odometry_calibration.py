"""The robot's odometry calibration (gsrmr_robot/odometry_calibration.py): a slipping wheel odometry driven through
fixes of its true pose learns its gain and turn slip, and the keys between fixes err less for it; bad fixes, short
pairs and an odometry reset teach nothing."""

import math

import numpy as np

from gsrmr_common.pose2d import Pose2D
from gsrmr_robot.odometry_calibration import CalibratedOdometry

SCALE_ERROR, TURN_SLIP = 0.03, 0.1  # the wheels over-report speed by 3 % + 10 % per rad/s of turn
RATE_HZ, FIX_EVERY_S, FIX_DELAY_S = 50, 1.0, 0.3


def drive(seconds: float, seed: int = 0):
    """(stamp_ns, true pose, raw odometry pose, ω) at 50 Hz: 0.3 m/s, turning between ±1.2 rad/s."""
    rng = np.random.default_rng(seed)
    true, raw = Pose2D(1.0, 2.0, 0.3), Pose2D()
    dt = 1.0 / RATE_HZ
    phase = rng.uniform(0, 6)
    for n in range(int(seconds * RATE_HZ)):
        w = 1.2 * math.sin(0.4 * n * dt + phase)
        yield round(n * dt * 1e9), true, raw, w
        v = 0.3
        true = true.compose(Pose2D(v * dt, 0.0, w * dt))
        reported = v * (1 + SCALE_ERROR + TURN_SLIP * abs(w))
        raw = raw.compose(Pose2D(reported * dt, 0.0, w * dt))


def run(calibrate: bool, seconds: float = 60.0, seed: int = 0, bad_fix_at_s: float | None = None):
    """Keys = map_from_odom ∘ calibrated pose; a fix each second (its correction in force 0.3 s later). Returns
    (the calibration, key position errors [m] after the first 10 s)."""
    odo = CalibratedOdometry()
    if not calibrate:
        odo.config = type(odo.config)(gain_range=(1.0, 1.0), max_slip_per_radps=0.0)
    frame = None
    pending = []
    errors = []
    for stamp_ns, true, raw, w in drive(seconds, seed):
        t_s = stamp_ns / 1e9
        pose = odo.add(stamp_ns, raw, w)
        if frame is None:
            frame = true.compose(pose.inverse())  # the operator's start pose: exact here
        slot = round(t_s * 10)
        if stamp_ns % round(0.1e9) == 0:
            odo.key_made(slot, stamp_ns)
            if t_s > 10:
                errors.append(frame.compose(pose).distance_m(true))
            if slot % round(FIX_EVERY_S * 10) == 0 and slot:
                fixed = true if bad_fix_at_s is None or abs(t_s - bad_fix_at_s) > 1e-6 else \
                    true.compose(Pose2D(0.5, 0.0, 0.0))
                pending.append((t_s + FIX_DELAY_S, slot, fixed.compose(pose.inverse())))
        while pending and pending[0][0] <= t_s + 1e-9:
            _, fix_slot, frame = pending.pop(0)
            odo.learn(fix_slot, frame)
    return odo, np.array(errors)


def assert_learned(odo: CalibratedOdometry) -> None:
    """The learned scale, gain − slip·|ω|, is the true distance per reported one, 1 / (1 + 0.03 + 0.1·|ω|), within
    1.5 % over the turn rates driven (a line through a curve)."""
    for w in np.linspace(0.0, 1.2, 7):
        assert abs((odo.gain - odo.slip * w) * (1 + SCALE_ERROR + TURN_SLIP * w) - 1) < 0.015, w
    assert odo.slip > 0.05


def test_learns_gain_and_slip_and_the_keys_err_less():
    plain_odo, plain = run(calibrate=False)
    odo, calibrated = run(calibrate=True)
    assert plain_odo.pairs_used > 0 and (plain_odo.gain, plain_odo.slip) == (1.0, 0.0)
    assert_learned(odo)
    assert np.median(calibrated) < 0.3 * np.median(plain)
    assert np.percentile(calibrated, 95) < 0.3 * np.percentile(plain, 95)


def test_a_bad_fix_teaches_nothing():
    odo, _ = run(calibrate=True, seconds=30.0, bad_fix_at_s=20.0)
    assert odo.pairs_skipped >= 1
    assert_learned(odo)


def test_short_pairs_and_resets_teach_nothing():
    odo = CalibratedOdometry()
    odo.add(0, Pose2D())
    odo.key_made(0, 0)
    assert not odo.learn(0, Pose2D())  # the first fix: nothing to pair with
    odo.add(int(1e9), Pose2D(0.05, 0.0, 0.0))
    odo.key_made(10, int(1e9))
    assert not odo.learn(10, Pose2D(0.0, 0.0, 0.0))  # 5 cm: too short
    odo.add(int(2e9), Pose2D(5.0, 0.0, 0.0))  # the driver reset its odometry: a 5 m step
    odo.key_made(20, int(2e9))
    assert not odo.learn(20, Pose2D())
    assert odo.pairs_used == 0 and (odo.gain, odo.slip) == (1.0, 0.0)
    assert not odo.learn(99, Pose2D())  # a slot without a key


def test_raw_frame_joins_the_calibrated_pose_to_the_driver_odometry():
    odo = CalibratedOdometry()
    odo.gain, odo.slip = 0.95, 0.1  # as learned
    raw = Pose2D(0.2, -0.1, 0.4)
    for n in range(1, 60):
        raw = raw.compose(Pose2D(0.006, 0.0, 0.01))
        pose = odo.add(n * 20_000_000, raw, 0.5)
        joined = odo.raw_frame().compose(raw)
        assert joined.distance_m(pose) < 1e-9 and abs(joined.heading_error_rad(pose)) < 1e-9
    assert pose.distance_m(raw) > 0.01  # the calibrated pose went less far
