"""The LIMO that slips: the error model, its seeded draw, the offline twin's pose errors and the caches it leaves."""

from __future__ import annotations

import math
import shutil

import numpy as np
import pytest

from gsrmr_common.pose2d import Pose2D
from gsrmr_sim.limo.odometry_errors import OdometryErrorDraw, OdometryErrors
from gsrmr_sim.world.kinematics import drive_route, start_pose
from gsrmr_sim.world.reported_pose import reported_poses
from gsrmr_sim.world.scene import load_scene, resolve_scene_path, scene_digest


def errors_of(reported: np.ndarray, true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d = np.hypot(reported[:, 0] - true[:, 0], reported[:, 1] - true[:, 1])
    h = np.abs(np.remainder(reported[:, 2] - true[:, 2] + math.pi, 2 * math.pi) - math.pi)
    return d, h


@pytest.fixture(scope="module")
def sandbox():
    scene = load_scene("sandbox")
    return scene, drive_route(scene.route, scene.slots, scene.slot_s, pose0=start_pose(scene.route))


def test_the_model_is_checked_and_scales():
    with pytest.raises(ValueError):
        OdometryErrors(imu_bias_radps=-1.0)
    with pytest.raises(ValueError):
        OdometryErrors(scale_error=-1.0)
    with pytest.raises(ValueError):
        OdometryErrors(start_error_m=math.nan)
    e = OdometryErrors(scale_error=0.03, turn_slip_per_radps=0.1, start_error_m=0.02)
    assert e.scaled(0.0).perfect and not e.perfect and e.scaled(2.0).scale_error == pytest.approx(0.06)
    assert e.reported_speed(0.3, 0.0) == pytest.approx(0.309) and e.reported_speed(0.3, -1.5) == pytest.approx(0.354)


def test_a_draw_is_the_seed_s_and_grows_its_imu_offset():
    e = OdometryErrors(imu_bias_radps=1e-3, imu_random_walk_rad_per_sqrt_s=1e-3, start_error_m=0.02,
                       start_error_rad=0.02)
    a, b, c = OdometryErrorDraw(e, 5), OdometryErrorDraw(e, 5), OdometryErrorDraw(e, 6)
    assert a.start_error == b.start_error != c.start_error and a.imu_bias_radps == b.imu_bias_radps
    offsets = [a.advance(0.02) for _ in range(500)]
    assert offsets == [b.advance(0.02) for _ in range(500)]
    assert abs(offsets[-1]) > 0 and a.true_start(Pose2D(1.0, 0.0, 0.0)).distance_m((1.0, 0.0)) < 0.2
    assert OdometryErrorDraw(OdometryErrors(), 1).advance(10.0) == 0.0


def test_with_the_scene_s_errors_a_round_s_key_error_p95_is_over_5_cm(sandbox):
    """The floor the localizer has to fix: the offline twin of the mock base, with the sandbox's errors and no
    localization, is off by ≥ 5 cm at its 95th percentile in every seed; perfect odometry is off by the wire's
    quantisation only."""
    scene, drive = sandbox
    assert not scene.odometry.perfect
    for seed in (1, 2, 3):
        d, _ = errors_of(reported_poses(drive, scene.slot_s, OdometryErrorDraw(scene.odometry, seed)), drive.poses)
        assert np.percentile(d, 95) >= 0.05, seed
    d, h = errors_of(reported_poses(drive, scene.slot_s), drive.poses)
    assert d.max() < 0.01 and h.max() < math.radians(0.2)


def test_the_odometry_section_changes_no_cache_key(tmp_path):
    """The mapping round keeps true poses: the scene's digest (headless laps, models, loss maps) ignores it."""
    copy = tmp_path / "sandbox.yaml"
    shutil.copy(resolve_scene_path("sandbox"), copy)
    before = scene_digest(str(copy))
    copy.write_text(copy.read_text().replace("scale_error: 0.03", "scale_error: 0.05"))
    assert scene_digest(str(copy)) == before and load_scene(str(copy)).odometry.scale_error == 0.05
    copy.write_text(copy.read_text().replace("slots: 288", "slots: 287"))
    assert scene_digest(str(copy)) != before
