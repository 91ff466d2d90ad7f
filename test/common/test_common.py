"""Tests of the shared conventions: camera axes, pixel centres, metrics, nerfstudio datasets (pure), and the
slot-aligned timer of the nodes (one rclpy node)."""

import math
import time

import numpy as np
import pytest

from gsrmr_common.camera import (
    Camera,
    CameraMount,
    Intrinsics,
    camera_from_pose,
    opencv_w2c_to_opengl_c2w,
    opengl_c2w_to_opencv_w2c,
)
from gsrmr_common.metrics import image_quality, mr_loss, pooled_psnr_db, psnr, ssim
from gsrmr_common.nerfstudio import DatasetFrame, read_dataset, write_dataset

K = Intrinsics.from_fov(320, 240, math.radians(90))


def test_robot_at_origin_looks_along_world_x():
    cam = camera_from_pose(0.0, 0.0, 0.0, CameraMount(height_m=0.2, pitch_rad=0.0, forward_m=0.1), K)
    np.testing.assert_allclose(cam.center_world, [0.1, 0.0, 0.2], atol=1e-12)
    # A point 2 m ahead at camera height projects to the principal point (image centre).
    uv, z = cam.project(np.array([[2.1, 0.0, 0.2]]))
    np.testing.assert_allclose(uv[0], [160.0, 120.0], atol=1e-9)
    assert z[0] == pytest.approx(2.0)
    # World +y (robot's left) appears on the left of the image; world +z (up) at the top.
    uv_left, _ = cam.project(np.array([[2.1, 0.5, 0.2]]))
    uv_up, _ = cam.project(np.array([[2.1, 0.0, 0.7]]))
    assert uv_left[0, 0] < 160.0 and uv_up[0, 1] < 120.0


def test_yaw_and_pitch_conventions():
    # θ = +90°: the robot faces world +y; a point ahead along +y is at the image centre.
    cam = camera_from_pose(1.0, 2.0, math.pi / 2, CameraMount(height_m=0.0, pitch_rad=0.0, forward_m=0.0), K)
    uv, z = cam.project(np.array([[1.0, 5.0, 0.0]]))
    np.testing.assert_allclose(uv[0], [160.0, 120.0], atol=1e-9)
    assert z[0] == pytest.approx(3.0)
    # Pitch down 45°: a floor point at distance = height ahead is on the optical axis.
    cam = camera_from_pose(0.0, 0.0, 0.0, CameraMount(height_m=1.0, pitch_rad=math.pi / 4, forward_m=0.0), K)
    uv, _ = cam.project(np.array([[1.0, 0.0, 0.0]]))
    np.testing.assert_allclose(uv[0], [160.0, 120.0], atol=1e-9)


def test_pixel_centres_and_ros_k_conversion():
    cam = Camera(K, np.eye(4))
    dirs = cam.ray_directions_camera()
    # Pixel (0, 0) centre is (0.5, 0.5): its ray hits x = (0.5 - cx)/fx at z = 1.
    assert dirs[0, 0, 0] == pytest.approx((0.5 - K.cx) / K.fx)
    ros = K.ros_k()
    assert ros[0, 2] == pytest.approx(K.cx - 0.5)
    assert Intrinsics.from_ros_k(ros, 320, 240) == K


def test_opengl_opencv_roundtrip():
    cam = camera_from_pose(0.3, -1.2, 0.7, CameraMount(pitch_rad=0.2), K)
    c2w_gl = opencv_w2c_to_opengl_c2w(cam.world_to_camera)
    np.testing.assert_allclose(opengl_c2w_to_opencv_w2c(c2w_gl), cam.world_to_camera, atol=1e-12)
    # OpenGL camera looks down its -z: that must be the OpenCV +z axis in the world.
    np.testing.assert_allclose(-c2w_gl[:3, 2], cam.camera_to_world[:3, 2], atol=1e-12)


def test_bad_cameras_are_rejected():
    with pytest.raises(ValueError, match="focal"):
        Intrinsics(0.0, 1.0, 0.5, 0.5, 1, 1)
    with pytest.raises(ValueError, match="finite"):
        camera_from_pose(float("nan"), 0.0, 0.0, CameraMount(), K)
    with pytest.raises(ValueError, match="orthonormal"):
        Camera(K, np.diag([2.0, 1.0, 1.0, 1.0]))


def test_metrics_identity_and_known_values():
    rng = np.random.default_rng(0)
    img = rng.random((48, 64, 3)).astype(np.float32)
    assert ssim(img, img) == pytest.approx(1.0, abs=1e-6)
    assert mr_loss(img, img) == pytest.approx(0.0, abs=1e-6)
    assert psnr(img, img) == 100.0
    shifted = np.clip(img + 0.1, 0, 1)
    mse = float(np.mean((shifted - img) ** 2))
    assert psnr(img, shifted) == pytest.approx(-10 * math.log10(mse), rel=1e-5)
    q = image_quality(img, shifted)
    assert q["loss"] == pytest.approx(0.8 * q["l1"] + 0.2 * (1 - q["ssim"]), rel=1e-9)
    assert 0 < q["ssim"] < 1
    with pytest.raises(ValueError, match="NaN"):
        ssim(img, np.full_like(img, np.nan))
    with pytest.raises(ValueError, match="shapes differ"):
        ssim(img, img[:10])


def test_ssim_matches_direct_window_computation():
    """SSIM equals a direct 11×11 Gaussian-window evaluation at an interior pixel."""
    from gsrmr_common.metrics import gaussian_window_1d, ssim_map

    rng = np.random.default_rng(1)
    a = rng.random((30, 30)).astype(np.float64)
    b = np.clip(a + rng.normal(0, 0.05, a.shape), 0, 1)
    w = np.outer(gaussian_window_1d(), gaussian_window_1d())
    pa, pb = a[10:21, 10:21], b[10:21, 10:21]
    mu_a, mu_b = (w * pa).sum(), (w * pb).sum()
    va = (w * pa * pa).sum() - mu_a**2
    vb = (w * pb * pb).sum() - mu_b**2
    cab = (w * pa * pb).sum() - mu_a * mu_b
    c1, c2 = 0.01**2, 0.03**2
    direct = ((2 * mu_a * mu_b + c1) * (2 * cab + c2)) / ((mu_a**2 + mu_b**2 + c1) * (va + vb + c2))
    assert ssim_map(a, b)[15, 15, 0] == pytest.approx(direct, abs=1e-5)


def test_nerfstudio_roundtrip(tmp_path):
    rng = np.random.default_rng(2)
    frames = []
    for i in range(3):
        k = Intrinsics.from_fov(32, 24, 1.2)
        cam = camera_from_pose(0.5 * i, 0.1, 0.3 * i, CameraMount(pitch_rad=0.1), k)
        img = rng.random((24, 32, 3)).astype(np.float32)
        depth = rng.uniform(0.2, 5.0, (24, 32)).astype(np.float32)
        frames.append(DatasetFrame(cam, img, depth, (0.5 * i, 0.1, 0.3 * i)))
    write_dataset(tmp_path, frames)
    back = read_dataset(tmp_path)
    assert len(back) == 3
    for a, b in zip(frames, back, strict=True):
        np.testing.assert_allclose(b.camera.world_to_camera, a.camera.world_to_camera, atol=1e-9)
        assert b.camera.intrinsics == a.camera.intrinsics
        np.testing.assert_allclose(b.image, a.image, atol=0.5 / 255 + 1e-6)
        np.testing.assert_allclose(b.depth_m, a.depth_m, atol=0.5e-3 + 1e-6)
        assert b.pose == pytest.approx(a.pose)


def test_nerfstudio_errors_name_the_problem(tmp_path):
    with pytest.raises(FileNotFoundError):
        read_dataset(tmp_path)
    (tmp_path / "transforms.json").write_text('{"fl_x": 10, "fl_y": 10, "cx": 5, "cy": 5, "w": 10, "h": 10, '
                                              '"frames": [{"file_path": "x.png"}]}')
    with pytest.raises(ValueError, match="transform_matrix"):
        read_dataset(tmp_path)


def test_pooled_psnr_is_the_psnr_of_the_mean_mse_not_the_mean_psnr():
    rng = np.random.default_rng(3)
    a = rng.uniform(0, 1, (4, 16, 16, 3))
    b = np.clip(a + rng.normal(0, [0.01, 0.02, 0.05, 0.2], (16, 16, 3, 4)).transpose(3, 0, 1, 2), 0, 1)
    per_slot = [psnr(a[i], b[i]) for i in range(4)]
    pooled = pooled_psnr_db(per_slot)
    assert pooled == pytest.approx(-10 * np.log10(np.mean((a - b) ** 2)), abs=1e-6)  # one image size: exact
    assert pooled < np.mean(per_slot)  # the bad slot weighs more than in the mean of PSNRs
    assert pooled_psnr_db([30.0, 30.0]) == pytest.approx(30.0)
    assert np.isnan(pooled_psnr_db([])) and pooled_psnr_db([float("nan"), 20.0]) == pytest.approx(20.0)


def test_aligned_timer_fires_at_its_phase_of_every_period():
    """The robot runs each slot 1 ms after it starts, the simulated radio 39 ms before: one wake-up per slot
    at a fixed phase, never before it.

    Load-proof (a loaded CI machine delays any wake-up by tens of ms): a 0.5 s slot, the phase 0.1 s into it, the
    timer created at 0.35 s into a slot. An aligned timer then fires just after 0.1 s; one that ignored the phase
    would fire 0.35 s in or later — 0.25 s apart, far more than any wake-up delay."""
    from conftest import ros_env
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor

    from gsrmr_common.ros_node import aligned_timer
    from gsrmr_common.slot_clock import SlotClock

    slot_ns, phase_ns = 500_000_000, 100_000_000
    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(ros_env()["ROS_DOMAIN_ID"]))
    try:
        node = rclpy.create_node("aligned_timer_test", context=ctx)
        calls: list[int] = []
        time.sleep(((350_000_000 - node.get_clock().now().nanoseconds) % slot_ns) / 1e9)  # 0.35 s into a slot
        aligned_timer(node, SlotClock(slot_ns / 1e9), phase_ns / 1e9,
                      lambda: calls.append(node.get_clock().now().nanoseconds))
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        end = time.monotonic() + 20.0
        while len(calls) < 6 and time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
        late_ms = [((t - phase_ns) % slot_ns) / 1e6 for t in calls]  # after the phase of its slot
        slots = [(t - phase_ns) // slot_ns for t in calls]
        assert len(calls) >= 4, calls
        assert slots == sorted(set(slots)), slots  # at most one call per slot
        assert all((t % slot_ns) >= phase_ns for t in calls), late_ms  # at/after the phase, never before
        assert np.median(late_ms) < 200.0, late_ms  # at the phase, not where the timer was created (≥ 250 ms)
        executor.shutdown()
        node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
