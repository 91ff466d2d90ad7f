"""The robot's key poses (gsrmr_robot.key_poses, map_source's staleness, UplinkCore's stale-fix image): keys are
map → odom ∘ the calibrated odometry pose of the frame's stamp, TF's map → odom joins the driver's odom frame, and a
correction gone stale asks for one image at the first fair fade. Pure, no ROS."""

from __future__ import annotations

import math

import numpy as np

from gsrmr_common.link_model import LinkBudget
from gsrmr_common.plausibility import Implausible
from gsrmr_common.pose2d import Pose2D
from gsrmr_common.wire import MapCorrection
from gsrmr_robot.key_poses import KeyPoses
from gsrmr_robot.map_source import CorrectionLimits, MapSource
from gsrmr_robot.uplink_core import SlotInputs, UplinkCore

MS = 1_000_000


def _keys(calibrate: bool = True, stale_fix_m: float = 1.0) -> KeyPoses:
    return KeyPoses(MapSource(Pose2D(1.0, 0.5, 0.2), CorrectionLimits(), Implausible()), calibrate, stale_fix_m)


def _drive(keys: KeyPoses, metres: float, start_ns: int = 0, speed_mps: float = 0.3) -> int:
    """Straight odometry at 50 Hz, a key each 100 ms; returns the stamp after."""
    raw = keys.history.latest or Pose2D()
    steps = round(metres / speed_mps * 50)
    stamp = start_ns
    for n in range(1, steps + 1):
        stamp = start_ns + n * 20 * MS
        raw = raw.compose(Pose2D(speed_mps * 0.02, 0.0, 0.0))
        keys.odom(stamp, raw, 0.0, stamp)
        if n % 5 == 0:
            keys.key(stamp // (100 * MS), stamp, stamp, 500 * MS)
    return stamp


def test_the_key_is_map_to_odom_of_the_pose_at_the_frame_stamp_and_tf_joins_the_driver_frame():
    keys = _keys()
    for n, x in enumerate((0.0, 0.01, 0.02, 0.03)):
        keys.odom(n * 20 * MS, Pose2D(x, 0.0, 0.0), 0.0, n * 20 * MS)
    key, tf = keys.key(0, 21 * MS, 60 * MS, 500 * MS)  # nearest sample: 20 ms
    want = Pose2D(1.0, 0.5, 0.2).compose(Pose2D(0.01, 0.0, 0.0))
    assert key.distance_m(want) < 1e-12
    assert tf.compose(Pose2D(0.01, 0.0, 0.0)).distance_m(key) < 1e-12  # TF: map → odom ∘ odom → base_link
    assert keys.key(1, None, 2_000 * MS, 500 * MS)[0] is None  # odometry 2 s old: no key


def test_a_correction_goes_stale_after_driving_and_an_image_restarts_the_wait_for_its_fix():
    keys = _keys(stale_fix_m=1.0)
    stamp = _drive(keys, 0.9)
    assert not keys.fix_stale()
    stamp = _drive(keys, 0.3, stamp)
    assert keys.fix_stale()  # 1.2 m with no correction and no image
    keys.image_sent()
    stamp = _drive(keys, 0.3, stamp)
    assert not keys.fix_stale()  # its fix may still come
    stamp = _drive(keys, 0.3, stamp)
    assert keys.fix_stale()  # half the distance again without one: ask again
    assert keys.maps.offer(MapCorrection(1, stamp / 1e9, 0.01, 0.0, 0.0, 1e-5, 1e-5, 1e-6), b"server") is None
    assert not keys.fix_stale()
    assert not _keys(stale_fix_m=0.0).fix_stale()


def test_a_stale_fix_sends_one_image_at_the_first_fair_fade():
    core = UplinkCore(LinkBudget(), 0.1, change_wait_slots=3)
    frame = np.full((24, 32, 3), 128, np.uint8)
    mean = core.link.mean_gain((0.0, 0.0))
    good, deep = 1.2 * core.change_probe.fades[0] * mean, 0.9 * core.change_probe.fades[-1] * mean

    def slot(k: int, gain: float, stale: bool) -> int:
        return core.run_slot(SlotInputs(k, frame, k, Pose2D(), (0, 0.01), measured_gain=gain,
                                        gain_threshold=math.inf, fix_stale=stale)).x

    assert slot(0, good, False) == 0
    assert slot(1, deep, True) == 0  # stale, but a deep fade: wait
    assert slot(2, good, True) == 1 and core.stale_fix_images == 1 and core.change_images == 0
    assert slot(3, good, False) == 0  # one image per wait
