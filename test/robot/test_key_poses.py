"""The robot's key poses (gsrmr_robot.key_poses, map_source, map_source's external pose helpers): keys are map → odom ∘
the calibrated odometry pose of the frame's stamp, TF's map → odom joins the driver's odom frame, and another
localizer's pose or TF edge becomes map → odom."""

from __future__ import annotations

import math
from types import SimpleNamespace

from gsrmr_common.plausibility import Implausible
from gsrmr_common.pose2d import Pose2D, quaternion_from_yaw
from gsrmr_robot.key_poses import KeyPoses
from gsrmr_robot.map_source import CorrectionLimits, MapSource, map_from_odom_of, map_to_odom_edges

MS = 1_000_000


def _keys(calibrate: bool = True) -> KeyPoses:
    return KeyPoses(MapSource(Pose2D(1.0, 0.5, 0.2), CorrectionLimits(), Implausible()), calibrate)


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


def test_another_localizers_pose_becomes_map_to_odom_with_the_odometry_at_its_stamp():
    keys = _keys(calibrate=False)
    stamp = _drive(keys, 0.6)  # 0.6 m along odom's x, 50 Hz
    assert keys.odom_at(stamp + 30 * MS, 50 * MS).distance_m(Pose2D(0.6, 0.0, 0.0)) < 1e-9
    assert keys.odom_at(stamp + 80 * MS, 50 * MS) is None  # no odometry sample near the stamp
    truth = Pose2D(3.0, -1.0, 0.7)  # map → odom of the other localizer
    odom = keys.odom_at(stamp - 200 * MS, 50 * MS)  # its pose is 200 ms old: the odometry then
    map_from_base = truth.compose(odom)
    assert keys.maps.set_external(map_from_odom_of(map_from_base, odom), stamp / 1e9 - 0.2) is None
    assert keys.maps.seq == 1 and keys.maps.map_from_odom().distance_m(truth) < 1e-9
    assert abs(keys.maps.map_from_odom().theta_rad - 0.7) < 1e-12
    key, _ = keys.key(99, stamp, stamp, 500 * MS)
    assert key.distance_m(truth.compose(Pose2D(0.6, 0.0, 0.0))) < 1e-9
    # a jump far beyond a server correction's limits is the other localizer's to make; a NaN is refused
    assert keys.maps.set_external(Pose2D(40.0, 0.0, 3.0), stamp / 1e9) is None and keys.maps.seq == 2
    assert keys.maps.set_external(Pose2D(math.nan, 0.0, 0.0), stamp / 1e9) == "correction_malformed"
    assert keys.maps.seq == 2 and keys.maps.implausible["correction_malformed"] == 1


def test_map_to_odom_edges_are_picked_from_a_tf_message_by_frame_names():
    def tf(parent: str, child: str, sec: int, x: float, yaw: float) -> SimpleNamespace:
        q = quaternion_from_yaw(yaw)
        return SimpleNamespace(
            header=SimpleNamespace(frame_id=parent, stamp=SimpleNamespace(sec=sec, nanosec=5)),
            child_frame_id=child,
            transform=SimpleNamespace(translation=SimpleNamespace(x=x, y=2.0, z=0.1),
                                      rotation=SimpleNamespace(x=q[0], y=q[1], z=q[2], w=q[3])))

    edges = map_to_odom_edges([tf("odom", "base_link", 1, 9.0, 0.0), tf("/map", "odom", 2, 1.5, 0.4),
                               tf("map", "odom_other", 3, 7.0, 0.0)], "odom")
    assert len(edges) == 1 and edges[0][0] == 2_000_000_005
    assert edges[0][1].distance_m(Pose2D(1.5, 2.0, 0.0)) < 1e-12 and abs(edges[0][1].theta_rad - 0.4) < 1e-12
