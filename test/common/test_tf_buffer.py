"""The pure TF buffer (gsrmr_common.tf_buffer): interpolation, slerp, chains, gaps, frame names, 6-DoF.

Truths are built independently of the buffer: motions whose interpolation is exact (constant velocity, a
constant-axis rotation at a constant rate) checked to 1e-9, and for arbitrary 6-DoF sample sequences scipy's
``Slerp`` as the reference rotation interpolation.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from gsrmr_common.camera import rpy_matrix
from gsrmr_common.tf_buffer import GAP, NO_TF_PATH, OUT_OF_RANGE, TfBuffer, TfLookupError, invert, slerp
from gsrmr_common.tf_tree import Transform, quaternion_from_matrix, transform_matrix

NS = 1_000_000_000
MS = 1_000_000
T0 = 1_700_000_000 * NS  # a realistic epoch stamp: float seconds would lose the nanoseconds here


def tf(translation, rotation_matrix=None) -> Transform:
    rot = np.eye(3) if rotation_matrix is None else rotation_matrix
    return Transform(tuple(float(v) for v in translation), quaternion_from_matrix(rot))


def yaw(theta: float) -> np.ndarray:
    return rpy_matrix(0.0, 0.0, theta)


def angle_between(a: np.ndarray, b: np.ndarray) -> float:
    cos = (np.trace(a[:3, :3].T @ b[:3, :3]) - 1.0) / 2.0
    return math.acos(max(-1.0, min(1.0, cos)))


def test_interpolation_is_linear_in_translation_and_slerp_in_rotation():
    buf = TfBuffer()
    axis = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    total = math.radians(170.0)  # a large turn: lerp of quaternions would be visibly off, slerp is exact
    buf.add_sample("a", "b", T0, tf((0.0, 0.0, 0.0)))
    buf.add_sample("a", "b", T0 + 20_000_000, tf((1.0, 2.0, 3.0), Rotation.from_rotvec(total * axis).as_matrix()))
    for fraction in (0.0, 0.1, 0.25, 0.5, 0.9, 1.0):
        got = buf.lookup("a", "b", T0 + round(fraction * 20_000_000)).target_from_source
        np.testing.assert_allclose(got[:3, 3], fraction * np.array([1.0, 2.0, 3.0]), atol=1e-12)
        want = Rotation.from_rotvec(fraction * total * axis).as_matrix()
        np.testing.assert_allclose(got[:3, :3], want, atol=1e-9)
    # the shorter arc whatever the quaternions' signs: q and −q are the same rotation
    q0 = np.array(quaternion_from_matrix(yaw(0.1)))
    q1 = np.array(quaternion_from_matrix(yaw(0.5)))
    for sign in (1.0, -1.0):
        mid = slerp(q0, sign * q1, 0.5)
        np.testing.assert_allclose(Rotation.from_quat(mid).as_matrix(), yaw(0.3), atol=1e-12)


def test_a_stamp_on_a_sample_takes_it_and_reports_no_gap():
    buf = TfBuffer()
    for k in range(3):
        buf.add_sample("odom", "base_link", T0 + k * 20_000_000, tf((k, 0.0, 0.0)))
    exact = buf.lookup("odom", "base_link", T0 + 20_000_000)
    assert exact.widest_gap_s == 0.0 and exact.target_from_source[0, 3] == 1.0
    between = buf.lookup("odom", "base_link", T0 + 30_000_000)
    assert between.widest_gap_s == pytest.approx(0.02) and between.target_from_source[0, 3] == pytest.approx(1.5)
    assert between.moving_edges == (("odom", "base_link"),)


def robot_chain(buf: TfBuffer, stamps_ns: list[int], speed_mps: float = 0.4, yaw_rate: float = 0.7) -> dict:
    """map → odom (static) → base_link (moving: constant velocity along odom x, constant yaw rate) → camera_link
    (static, 6-DoF) → camera_optical_frame (static optical rotation). Returns the static matrices."""
    map_odom = transform_matrix(tf((1.0, -2.0, 0.0), yaw(0.8)))
    base_link = transform_matrix(tf((0.12, 0.03, 0.2), rpy_matrix(0.05, 0.2, -0.1)))
    optical = transform_matrix(Transform((0.0, 0.0, 0.0), (-0.5, 0.5, -0.5, 0.5)))
    buf.set_static("map", "odom", tf(map_odom[:3, 3], map_odom[:3, :3]))
    buf.set_static("base_link", "camera_link", tf(base_link[:3, 3], base_link[:3, :3]))
    buf.set_static("camera_link", "camera_optical_frame", Transform((0.0, 0.0, 0.0), (-0.5, 0.5, -0.5, 0.5)))
    for s in stamps_ns:
        t = (s - T0) / NS
        buf.add_sample("odom", "base_link", s, tf((speed_mps * t, 0.1, 0.0), yaw(yaw_rate * t)))

    def truth(stamp_ns: int) -> np.ndarray:
        t = (stamp_ns - T0) / NS
        odom_base = transform_matrix(tf((speed_mps * t, 0.1, 0.0), yaw(yaw_rate * t)))
        return map_odom @ odom_base @ base_link @ optical

    return {"truth": truth}


def test_chain_with_static_and_moving_edges_at_unaligned_stamps():
    buf = TfBuffer()
    chain = robot_chain(buf, [T0 + k * 20_000_000 for k in range(100)])  # 50 Hz for 2 s
    for stamp in (T0 + 7_300_000, T0 + 1_234_567_891, T0 + 1_970_000_001):
        look = buf.lookup("map", "camera_optical_frame", stamp, max_gap_s=0.05)
        np.testing.assert_allclose(look.target_from_source, chain["truth"](stamp), atol=1e-9)
        assert look.moving_edges == (("odom", "base_link"),)
        # the other direction is the inverse; a lookup between siblings meets at their common ancestor
        back = buf.lookup("camera_optical_frame", "map", stamp).target_from_source
        np.testing.assert_allclose(back, invert(look.target_from_source), atol=1e-9)
    static = buf.lookup("base_link", "camera_optical_frame", T0 - 50 * NS)  # static chain: any stamp
    assert static.widest_gap_s == 0.0 and static.moving_edges == ()
    buf.set_static("base_link", "imu_link", tf((0.0, 0.0, 0.05)))
    cam_in_imu = buf.lookup("imu_link", "camera_optical_frame", T0).target_from_source
    np.testing.assert_allclose(cam_in_imu[:3, 3], static.target_from_source[:3, 3] - [0.0, 0.0, 0.05], atol=1e-12)
    assert buf.time_range_ns("map", "camera_optical_frame") == (T0, T0 + 99 * 20_000_000)
    assert buf.time_range_ns("base_link", "camera_optical_frame") is None


def test_gaps_and_range_are_refused_with_their_reason():
    buf = TfBuffer()
    stamps = [T0 + k * 20_000_000 for k in range(50) if not 20 <= k < 35]  # a 0.32 s dropout after 0.38 s
    robot_chain(buf, stamps)
    inside_gap = T0 + 500_000_000
    with pytest.raises(TfLookupError) as err:
        buf.lookup("map", "camera_optical_frame", inside_gap, max_gap_s=0.1)
    assert err.value.reason == GAP and err.value.widest_gap_s == pytest.approx(0.32)
    assert "odom → base_link" in str(err.value)
    assert buf.lookup("map", "camera_optical_frame", inside_gap).widest_gap_s == pytest.approx(0.32)  # no limit
    assert buf.lookup("map", "camera_optical_frame", T0 + 370_000_000, max_gap_s=0.1).widest_gap_s == \
        pytest.approx(0.02)
    for outside in (T0 - 1, stamps[-1] + 1):
        with pytest.raises(TfLookupError) as err:
            buf.lookup("map", "camera_optical_frame", outside, max_gap_s=10.0)
        assert err.value.reason == OUT_OF_RANGE and "1700000000.000000" in str(err.value)


def test_leading_slashes_are_stripped_as_tf2_does():
    buf = TfBuffer()
    buf.set_static("/map", "/odom", tf((1.0, 0.0, 0.0)))
    buf.add_sample("/odom", "base_link", T0, tf((0.0, 2.0, 0.0)))
    buf.add_sample("odom", "/base_link", T0 + NS, tf((0.0, 4.0, 0.0)))
    for target, source in (("map", "base_link"), ("/map", "/base_link"), ("map", "/base_link")):
        got = buf.lookup(target, source, T0 + NS // 2).target_from_source
        np.testing.assert_allclose(got[:3, 3], [1.0, 3.0, 0.0])
    assert buf.parents() == {"base_link": "odom", "map": None, "odom": "map"}


def test_six_dof_motion_matches_scipy_slerp():
    """A handheld camera: map → camera_link moving in all six degrees of freedom at 30 Hz (irregular samples),
    the optical frame static under it; every lookup equals scipy's Slerp and linear translation."""
    rng = np.random.default_rng(7)
    stamps = np.cumsum(rng.integers(25_000_000, 40_000_000, size=40)) + T0
    rotations = Rotation.from_rotvec(np.cumsum(rng.normal(0.0, 0.15, size=(40, 3)), axis=0))
    positions = np.cumsum(rng.normal(0.0, 0.02, size=(40, 3)), axis=0)
    buf = TfBuffer()
    for s, r, p in zip(stamps, rotations, positions, strict=True):
        buf.add_sample("map", "camera_link", int(s), tf(p, r.as_matrix()))
    buf.set_static("camera_link", "camera_optical_frame", Transform((0.0, 0.0, 0.0), (-0.5, 0.5, -0.5, 0.5)))
    optical = transform_matrix(Transform((0.0, 0.0, 0.0), (-0.5, 0.5, -0.5, 0.5)))
    reference = Slerp((stamps - T0) / NS, rotations)
    queries = np.sort(rng.integers(int(stamps[0]), int(stamps[-1]), size=60))
    for q in queries:
        got = buf.lookup("map", "camera_optical_frame", int(q), max_gap_s=0.05).target_from_source
        want = np.eye(4)
        want[:3, :3] = reference((q - T0) / NS).as_matrix()
        i = int(np.searchsorted(stamps, q, side="right")) - 1
        f = (q - stamps[i]) / (stamps[i + 1] - stamps[i]) if q != stamps[i] else 0.0
        want[:3, 3] = positions[i] + f * (positions[min(i + 1, 39)] - positions[i])
        np.testing.assert_allclose(got, want @ optical, atol=1e-9)


def test_disconnected_and_unknown_frames_have_no_path():
    buf = TfBuffer()
    buf.set_static("map", "odom", tf((0.0, 0.0, 0.0)))
    buf.set_static("camera_link", "camera_optical_frame", tf((0.0, 0.0, 0.0)))
    with pytest.raises(TfLookupError) as err:
        buf.lookup("map", "camera_optical_frame", T0)
    assert err.value.reason == NO_TF_PATH
    assert "camera_optical_frame leads up to camera_link" in str(err.value)
    assert "odom (parent map, static)" in str(err.value)
    with pytest.raises(TfLookupError) as err:
        buf.lookup("map", "nowhere", T0)
    assert err.value.reason == NO_TF_PATH and "'nowhere' is not in the TF tree" in str(err.value)


def test_one_parent_per_frame_repeated_stamps_and_static_over_samples():
    buf = TfBuffer()
    buf.add_sample("odom", "base_link", T0, tf((1.0, 0.0, 0.0)))
    buf.add_sample("map", "base_link", T0, tf((9.0, 0.0, 0.0)))  # a second parent: ignored and reported
    buf.add_sample("odom", "base_link", T0 + NS, tf((2.0, 0.0, 0.0)))
    buf.add_sample("odom", "base_link", T0 + NS, tf((3.0, 0.0, 0.0)))  # same stamp again: the last one counts
    assert buf.parent_conflicts == {"base_link": {"map"}} and buf.ignored_samples == 1
    assert buf.lookup("odom", "base_link", T0 + NS).target_from_source[0, 3] == 3.0
    assert buf.lookup("odom", "base_link", T0 + NS // 2).target_from_source[0, 3] == pytest.approx(2.0)
    buf.set_static("odom", "base_link", tf((5.0, 0.0, 0.0)))
    assert buf.is_static_edge("base_link")
    assert buf.lookup("odom", "base_link", T0 + 7 * NS).target_from_source[0, 3] == 5.0
    assert buf.remove_edge_into("/base_link") and not buf.has_frame("base_link")


def test_an_edge_whose_samples_agree_moves_nothing():
    """A constant edge sent on /tf now and then is looked up as a static one (any stamp, no gap); in a moving edge, a
    bracket whose two samples agree (within STILL_M, STILL_RAD) counts no gap; one that moves does."""
    buf = TfBuffer()
    fixed = Transform((1.0, 2.0, 0.0), quaternion_from_matrix(yaw(0.3)[:3, :3]))
    for k in range(3):  # 1 Hz, a 0.2 mm wobble
        wobbled = Transform((1.0 + 2e-4 * (k % 2), 2.0, 0.0), fixed.rotation)
        buf.add_sample("map", "odom", (k * 1000 + 500) * MS, wobbled)
    buf.add_sample("odom", "base_link", 0, Transform((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)))
    buf.add_sample("odom", "base_link", 3000 * MS, Transform((3.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)))
    assert buf.is_static_edge("odom") and buf.moving_edges("map", "base_link") == [("odom", "base_link")]
    look = buf.lookup("map", "odom", 100 * MS, max_gap_s=0.1)  # before the first sample: a constant has no range
    np.testing.assert_allclose(look.target_from_source, transform_matrix(fixed), atol=1e-12)
    assert look.widest_gap_s == 0.0
    with pytest.raises(TfLookupError) as err:  # the odometry's 3-s bracket does move
        buf.lookup("map", "base_link", 1500 * MS, max_gap_s=0.1)
    assert err.value.reason == GAP
    still = TfBuffer()
    for k, x in enumerate((0.0, 0.0, 0.5)):  # parked for a second, then moving
        still.add_sample("odom", "base_link", k * 1000 * MS, Transform((x, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)))
    assert not still.is_static_edge("base_link")
    assert still.lookup("odom", "base_link", 500 * MS, max_gap_s=0.1).widest_gap_s == 0.0
    with pytest.raises(TfLookupError):
        still.lookup("odom", "base_link", 1500 * MS, max_gap_s=0.1)
