"""gsrmr-align: similarity estimation (Umeyama, RANSAC), SH rotation, model transform, pose readers, the CLI."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gsrmr_common.camera import Camera, CameraMount, Intrinsics, camera_from_pose, opencv_w2c_to_opengl_c2w
from gsrmr_common.nerfstudio import DatasetFrame, write_dataset
from gsrmr_splat.align import (
    Similarity,
    align_poses,
    quaternion_multiply,
    quaternion_wxyz,
    ransac_umeyama,
    rotate_sh,
    sh_rotation_matrix,
    transform_model,
    umeyama,
)
from gsrmr_splat.align_cli import main as align_main
from gsrmr_splat.external_poses import (
    NERFSTUDIO_LEGACY_APPLIED_TRANSFORM,
    PoseFileError,
    detect_format,
    image_key,
    read_3dgs_cameras_json,
    read_colmap_images_txt,
    read_map_dataset,
    read_model_poses,
    read_nerfstudio_exported_cameras,
    read_nerfstudio_transforms,
    shift_frame_numbers,
)
from gsrmr_splat.model import GaussianModel
from gsrmr_splat.render import render
from gsrmr_splat.sh import C0, num_coeffs, sh_basis


def random_similarity(seed: int, scale: float) -> Similarity:
    rng = np.random.default_rng(seed)
    return Similarity(scale, Rotation.random(random_state=seed).as_matrix(), rng.uniform(-3.0, 3.0, 3))


def invert_rigid(pose: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = pose[:3, :3].T
    out[:3, 3] = -pose[:3, :3].T @ pose[:3, 3]
    return out


def look_at(eye, target) -> np.ndarray:
    """Camera→world (OpenCV axes) at ``eye`` looking at ``target``, world z up."""
    forward = np.asarray(target, float) - np.asarray(eye, float)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([right, np.cross(forward, right), forward], axis=1)
    c2w[:3, 3] = eye
    return c2w


def random_poses(seed: int, n: int) -> list[np.ndarray]:
    """n camera→world poses (OpenCV) with random orientations and centres in a 6 m box."""
    rng = np.random.default_rng(seed)
    poses = []
    for rot in Rotation.random(n, random_state=seed).as_matrix():
        c2w = np.eye(4)
        c2w[:3, :3] = rot
        c2w[:3, 3] = rng.uniform(-3.0, 3.0, 3)
        poses.append(c2w)
    return poses


def psnr_db(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return math.inf if mse == 0.0 else 10.0 * math.log10(1.0 / mse)


# ---------------------------------------------------------------------------------------- Similarity, Umeyama

def test_similarity_validates_and_composes():
    sim = random_similarity(1, 1.7)
    np.testing.assert_allclose(sim.compose(sim.inverse()).matrix(), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(sim.inverse().matrix(), np.linalg.inv(sim.matrix()), atol=1e-12)
    other = random_similarity(2, 0.4)
    pts = np.random.default_rng(0).normal(size=(5, 3))
    np.testing.assert_allclose(sim.compose(other).apply_points(pts), sim.apply_points(other.apply_points(pts)),
                               atol=1e-12)
    np.testing.assert_allclose(sim.apply_points(pts), pts @ (sim.matrix()[:3, :3]).T + sim.matrix()[:3, 3])
    reflection = np.diag([1.0, 1.0, -1.0])
    for bad in [dict(scale=0.0), dict(scale=-1.0), dict(scale=math.nan), dict(rotation=reflection),
                dict(rotation=2.0 * np.eye(3)), dict(translation=[0.0, math.inf, 0.0]), dict(translation=[0.0])]:
        kwargs = {"scale": 1.0, "rotation": np.eye(3), "translation": np.zeros(3), **bad}
        with pytest.raises(ValueError):
            Similarity(**kwargs)
    with pytest.raises(ValueError):  # read-only: frozen means frozen
        sim.rotation[0, 0] = 2.0


def test_umeyama_recovers_a_known_similarity_exactly():
    truth = random_similarity(3, 0.37)
    src = np.random.default_rng(3).normal(size=(25, 3)) * 2.0
    est = umeyama(src, truth.apply_points(src))
    assert est.scale == pytest.approx(truth.scale, rel=1e-12)
    np.testing.assert_allclose(est.rotation, truth.rotation, atol=1e-12)
    np.testing.assert_allclose(est.translation, truth.translation, atol=1e-12)
    # three coplanar (non-collinear) points are enough
    est3 = umeyama(src[:3], truth.apply_points(src[:3]))
    np.testing.assert_allclose(est3.matrix(), truth.matrix(), atol=1e-10)


def test_umeyama_never_returns_a_reflection():
    src = np.random.default_rng(4).normal(size=(10, 3))
    mirrored = src * np.array([1.0, 1.0, -1.0])  # only a reflection maps src onto this exactly
    est = umeyama(src, mirrored)
    assert np.linalg.det(est.rotation) == pytest.approx(1.0)
    assert np.allclose(est.rotation @ est.rotation.T, np.eye(3))


def test_umeyama_refuses_degenerate_input():
    with pytest.raises(ValueError, match="at least 3"):
        umeyama(np.zeros((2, 3)), np.zeros((2, 3)))
    line = np.outer(np.arange(6.0), [1.0, 2.0, 0.5])
    with pytest.raises(ValueError, match="collinear"):
        umeyama(line, line * 2.0)
    with pytest.raises(ValueError, match="collinear"):
        umeyama(np.ones((4, 3)), np.random.default_rng(0).normal(size=(4, 3)))
    with pytest.raises(ValueError, match="N×3"):
        umeyama(np.zeros((4, 2)), np.zeros((4, 2)))


def robot_route_pairs(seed: int, n: int, outlier_fraction: float, noise_m: float):
    """Map-frame camera centres on a robot route (0.15 m high, a 6 m × 4 m area), their model-frame centres
    under a known similarity with ``noise_m`` noise per axis, and ``outlier_fraction`` of the model-side
    centres moved 1–3 m away (mis-registered images)."""
    rng = np.random.default_rng(seed)
    truth = random_similarity(seed, 2.3)  # model → map
    dst = np.column_stack([rng.uniform(-3, 3, n), rng.uniform(-2, 2, n), np.full(n, 0.15)])
    src = truth.inverse().apply_points(dst + rng.normal(0.0, noise_m, (n, 3)))
    outliers = np.zeros(n, bool)
    outliers[rng.choice(n, round(outlier_fraction * n), replace=False)] = True
    push = rng.normal(size=(int(outliers.sum()), 3))
    push *= rng.uniform(1.0, 3.0, (len(push), 1)) / np.linalg.norm(push, axis=1, keepdims=True)
    src[outliers] += push / truth.scale  # 1–3 m in the map frame
    return truth, src, dst, outliers


def test_ransac_recovers_the_similarity_and_the_inliers_despite_30_percent_outliers():
    truth, src, dst, outliers = robot_route_pairs(5, 40, 0.3, 0.01)
    fit = ransac_umeyama(src, dst, seed=0)
    np.testing.assert_array_equal(fit.inliers, ~outliers)
    assert fit.similarity.scale == pytest.approx(truth.scale, rel=5e-3)
    angle = Rotation.from_matrix(fit.similarity.rotation @ truth.rotation.T).magnitude()
    assert math.degrees(angle) < 0.5
    centres = dst[~outliers]
    err = np.linalg.norm(fit.similarity.apply_points(src[~outliers]) - centres, axis=1)
    assert np.sqrt(np.mean(err ** 2)) < 0.03  # 1 cm per axis: ~1.7 cm RMS
    again = ransac_umeyama(src, dst, seed=0)
    np.testing.assert_array_equal(again.similarity.matrix(), fit.similarity.matrix())  # deterministic
    plain = umeyama(src, dst)  # the same data without RANSAC is visibly wrong: the test can fail
    assert abs(plain.scale / truth.scale - 1.0) > 0.01


def test_ransac_explicit_threshold_min_inliers_and_rotation_test():
    truth, src, dst, _ = robot_route_pairs(6, 12, 0.0, 0.002)
    with pytest.raises(ValueError, match="agree"):
        ransac_umeyama(src, dst, min_inliers=13)
    rots = Rotation.random(12, random_state=6).as_matrix()
    dst_rots = truth.rotation @ rots
    dst_rots[3] = Rotation.from_rotvec([0.0, 0.0, math.radians(30.0)]).as_matrix() @ dst_rots[3]
    fit = ransac_umeyama(src, dst, threshold_m=0.05, src_rotations=rots, dst_rotations=dst_rots,
                         rotation_threshold_deg=5.0)
    assert fit.threshold_m == 0.05
    assert not fit.inliers[3] and fit.inliers.sum() == 11
    assert ransac_umeyama(src, dst, threshold_m=0.05, src_rotations=rots, dst_rotations=dst_rots).inliers.all()


def test_align_poses_pairs_by_name_and_reports_residuals():
    truth = random_similarity(7, 0.8)
    map_poses = {f"frame_{i:05d}": p for i, p in enumerate(random_poses(7, 12))}
    model_poses = {k: truth.inverse().apply_camera_to_world(p) for k, p in map_poses.items()}
    model_poses["frame_00004"] = model_poses["frame_00004"].copy()
    model_poses["frame_00004"][:3, 3] += 2.0  # a mis-registered image
    model_poses["only_model"] = np.eye(4)
    report = align_poses(model_poses, {**map_poses, "only_map": np.eye(4)})
    assert (report.pairs, report.inliers, report.outlier_names) == (12, 11, ("frame_00004",))
    assert report.rms_center_error_m < 1e-9 and report.max_rotation_error_deg < 1e-6
    np.testing.assert_allclose(report.similarity.matrix(), truth.matrix(), atol=1e-9)
    data = json.loads(json.dumps(report.to_dict()))
    assert data["similarity"]["scale"] == pytest.approx(0.8) and data["outlier_names"] == ["frame_00004"]
    with pytest.raises(ValueError, match="no image name is in both"):
        align_poses({"a": np.eye(4)}, {"b": np.eye(4)})
    with pytest.raises(ValueError, match="only 2 image"):
        align_poses({k: model_poses[k] for k in ("frame_00000", "frame_00001")}, map_poses)


# ----------------------------------------------------------------------------------------- SH and the model

def raw_sh(coeffs: np.ndarray, dirs: np.ndarray, degree: int) -> np.ndarray:
    """Σ_k c_k·Y_k(d) of one degree's block (no +0.5, no clamp): N directions × 3 channels."""
    lo, hi = degree * degree, (degree + 1) ** 2
    basis = np.stack(sh_basis(dirs[:, 0], dirs[:, 1], dirs[:, 2], degree, np)[lo:hi], axis=1)
    return basis @ coeffs


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_sh_rotation_matches_direct_evaluation(degree):
    rng = np.random.default_rng(degree)
    dirs = rng.normal(size=(200, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    lo, hi = degree * degree, (degree + 1) ** 2
    for seed in range(5):
        rot = Rotation.random(random_state=100 * degree + seed).as_matrix()
        sh = rng.normal(size=(1, num_coeffs(3), 3))
        rotated = rotate_sh(sh, rot)
        np.testing.assert_array_equal(rotated[:, 0], sh[:, 0])  # DC is rotation invariant
        before = raw_sh(sh[0, lo:hi], dirs, degree)
        after = raw_sh(rotated[0, lo:hi], dirs @ rot.T, degree)  # new SH at R·d
        assert np.max(np.abs(after - before)) < 1e-5
        assert np.max(np.abs(raw_sh(sh[0, lo:hi], dirs @ rot.T, degree) - before)) > 1e-2  # it does move
        m = sh_rotation_matrix(rot, degree)
        np.testing.assert_allclose(m @ m.T, np.eye(hi - lo), atol=1e-10)  # orthonormal basis: orthogonal


def test_quaternion_helpers_follow_the_model_convention():
    rot_a, rot_b = Rotation.random(2, random_state=9)
    qa, qb = quaternion_wxyz(rot_a.as_matrix()), quaternion_wxyz(rot_b.as_matrix())
    prod = quaternion_multiply(qa, qb)
    expected = (rot_a * rot_b).as_matrix()
    np.testing.assert_allclose(Rotation.from_quat(prod[[1, 2, 3, 0]]).as_matrix(), expected, atol=1e-12)


SCENE_CENTER = np.array([0.0, 0.0, 1.0])


def scene_model(seed: int = 11, n: int = 1500) -> GaussianModel:
    """Gaussians in a 1.4 m cube around SCENE_CENTER with random SH to degree 3 (a view-dependent colour)."""
    rng = np.random.default_rng(seed)
    sh = rng.normal(0.0, 0.25, (n, num_coeffs(3), 3))
    sh[:, 0] = (rng.uniform(0.1, 0.9, (n, 3)) - 0.5) / C0
    return GaussianModel(SCENE_CENTER + rng.uniform(-0.7, 0.7, (n, 3)), rng.normal(size=(n, 4)),
                         np.log(rng.uniform(0.01, 0.06, (n, 3))), rng.normal(0.5, 1.0, n), sh)


def scene_cameras() -> list[Camera]:
    """Three cameras 3 m from the scene centre: the nearest Gaussian is ≥ 2 m deep, so even at scale 0.5
    (≥ 1 m) nothing comes near the renderer's fixed 0.2 m near plane."""
    k = Intrinsics.from_fov(64, 48, math.radians(60.0))
    eyes = [SCENE_CENTER + 3.0 * np.array([math.cos(a), math.sin(a), 0.3]) / math.hypot(1.0, 0.3)
            for a in (0.2, 2.3, 4.2)]
    return [Camera(k, invert_rigid(look_at(eye, SCENE_CENTER))) for eye in eyes]


def moved_camera(cam: Camera, sim: Similarity) -> Camera:
    return Camera(cam.intrinsics, invert_rigid(sim.apply_camera_to_world(cam.camera_to_world)))


def test_round_trip_gives_back_the_model():
    model = scene_model()
    sim = random_similarity(12, 2.7)
    back = transform_model(transform_model(model, sim), sim.inverse())
    np.testing.assert_allclose(back.means, model.means, atol=2e-5)
    np.testing.assert_allclose(back.log_scales, model.log_scales, atol=1e-5)
    np.testing.assert_array_equal(back.opacity_logits, model.opacity_logits)
    np.testing.assert_allclose(back.sh, model.sh, atol=1e-5)
    signs = np.sign(np.sum(back.quats * model.quats, axis=1, keepdims=True))  # q and −q: one rotation
    np.testing.assert_allclose(back.quats * signs, model.quats, atol=1e-5)
    for cam in scene_cameras():
        a, b = render(model, cam, (0.2, 0.3, 0.4)), render(back, cam, (0.2, 0.3, 0.4))
        assert a.alpha.mean() > 0.2  # the scene covers a third of the view
        assert psnr_db(a.rgb, b.rgb) >= 50.0


@pytest.mark.parametrize("scale", [0.5, 1.0, 2.0])
def test_transformed_model_at_transformed_cameras_looks_the_same(scale):
    model = scene_model()
    sim = random_similarity(13, scale)
    moved = transform_model(model, sim)
    unrotated_sh = GaussianModel(moved.means, moved.quats, moved.log_scales, moved.opacity_logits, model.sh)
    for cam in scene_cameras():
        ref = render(model, cam, (0.2, 0.3, 0.4))
        cam2 = moved_camera(cam, sim)
        assert psnr_db(render(moved, cam2, (0.2, 0.3, 0.4)).rgb, ref.rgb) >= 40.0
        # the SH rotation matters: without it the view-dependent colour is wrong (the check can fail)
        assert psnr_db(render(unrotated_sh, cam2, (0.2, 0.3, 0.4)).rgb, ref.rgb) < 35.0


# ------------------------------------------------------------------------------------------------- readers

def test_image_key_rule():
    assert image_key("images/frame_0001.png") == image_key("frame_0001.jpg") == image_key("frame_0001") \
        == image_key("C:\\data\\frame_0001.JPG") == "frame_0001"
    assert image_key("frame.0001") == "frame.0001"
    assert image_key("scan.v2.jpeg") == "scan.v2"
    shifted = shift_frame_numbers({"frame_00001": 1, "frame_00010": 2, "frame_00000": 3, "x": 4}, -1)
    assert shifted == {"frame_00000": 1, "frame_00009": 2, "x": 4}


def write_transforms_json(path: Path, poses: list[np.ndarray], **extra) -> Path:
    frames = [{"file_path": f"images/frame_{i:05d}.png",
               "transform_matrix": opencv_w2c_to_opengl_c2w(invert_rigid(p)).tolist()} for i, p in enumerate(poses)]
    path.write_text(json.dumps({"fl_x": 100.0, "fl_y": 100.0, "cx": 50, "cy": 40, "w": 100, "h": 80,
                                "frames": frames, **extra}))
    return path


def assert_same_poses(read: dict[str, np.ndarray], poses: list[np.ndarray], names: list[str]) -> None:
    assert sorted(read) == sorted(names)
    for name, pose in zip(names, poses, strict=True):
        np.testing.assert_allclose(read[name], pose, atol=1e-9)


def test_nerfstudio_transforms_reader(tmp_path):
    poses = random_poses(20, 5)
    names = [f"frame_{i:05d}" for i in range(5)]
    path = write_transforms_json(tmp_path / "transforms.json", poses)
    assert detect_format(path) == "nerfstudio"
    assert_same_poses(read_nerfstudio_transforms(path), poses, names)
    assert_same_poses(read_model_poses(tmp_path), poses, names)  # the folder works too


@pytest.mark.parametrize("applied", ["none", "key", "legacy"])
def test_nerfstudio_dataparser_transform_carries_poses_into_the_model_frame(tmp_path, applied):
    """Cameras the splatfacto model trained with: s_o·(T_o·pose) of the transforms.json poses; the run saves
    T_o·A and s_o·applied_scale (nerfstudio_dataparser.py)."""
    poses = random_poses(21, 6)
    orient = np.eye(4)  # T_o: auto_orient_and_center_poses' rigid transform
    orient[:3, :3] = Rotation.random(random_state=21).as_matrix()
    orient[:3, 3] = [0.3, -1.2, 0.5]
    scale_o, applied_scale = 0.21, 1.0
    extra: dict = {}
    a = np.eye(4)
    if applied == "key":
        a[:3] = np.array([[0.0, 0.0, 1.0, 2.0], [1.0, 0.0, 0.0, -1.0], [0.0, 1.0, 0.0, 0.5]])
        applied_scale = 1.5
        extra = {"applied_transform": a[:3].tolist(), "applied_scale": applied_scale}
    elif applied == "legacy":
        a[:3] = np.array(NERFSTUDIO_LEGACY_APPLIED_TRANSFORM)
        (tmp_path / "colmap" / "sparse" / "0").mkdir(parents=True)
    path = write_transforms_json(tmp_path / "transforms.json", poses, **extra)
    dataparser = tmp_path / "dataparser_transforms.json"
    dataparser.write_text(json.dumps({"transform": (orient @ a)[:3].tolist(), "scale": scale_o * applied_scale}))
    expected = []
    for p in poses:
        q = orient @ p
        q[:3, 3] *= scale_o
        expected.append(q)
    assert_same_poses(read_model_poses(path, dataparser), expected, [f"frame_{i:05d}" for i in range(6)])


def test_ns_export_cameras_reader(tmp_path):
    poses = random_poses(22, 4)
    path = tmp_path / "transforms_train.json"
    path.write_text(json.dumps([{"file_path": f"/data/run/images/frame_{i:05d}.jpg",
                                 "transform": opencv_w2c_to_opengl_c2w(invert_rigid(p))[:3].tolist()}
                                for i, p in enumerate(poses)]))
    assert detect_format(path) == "ns-export"
    assert_same_poses(read_nerfstudio_exported_cameras(path), poses, [f"frame_{i:05d}" for i in range(4)])
    with pytest.raises(PoseFileError, match="dataparser"):
        read_model_poses(path, tmp_path / "dataparser_transforms.json")


def test_colmap_images_txt_reader(tmp_path):
    poses = random_poses(23, 4)
    lines = ["# Image list with two lines of data per image:", "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, "
             "CAMERA_ID, NAME", "#   POINTS2D[] as (X, Y, POINT3D_ID)", "# Number of images: 4"]
    for i, p in reversed(list(enumerate(poses))):  # COLMAP's order need not be the names' order
        w2c = invert_rigid(p)
        q_xyzw = Rotation.from_matrix(w2c[:3, :3]).as_quat()
        numbers = " ".join(repr(float(v)) for v in (q_xyzw[3], *q_xyzw[:3], *w2c[:3, 3]))
        lines.append(f"{i + 7} {numbers} 1 frame_{i:05d}.jpg")
        lines.append("" if i % 2 else "12.5 33.1 -1 40.0 2.5 17")  # the points line may be empty
    path = tmp_path / "images.txt"
    path.write_text("\n".join(lines) + "\n")
    assert detect_format(path) == "colmap"
    assert_same_poses(read_colmap_images_txt(path), poses, [f"frame_{i:05d}" for i in range(4)])
    path.write_text("1 1 0 0 0 0 0 0 1\n")
    with pytest.raises(PoseFileError, match="line 1"):
        read_colmap_images_txt(path)


def camera_to_json_3dgs(i: int, name: str, c2w: np.ndarray) -> dict:
    """What graphdeco-inria 3DGS ``utils/camera_utils.camera_to_JSON`` writes for a camera whose COLMAP pose
    is ``w2c``: it keeps R = w2c_rotᵀ and T = w2c_translation, builds Rt = [Rᵀ | T] and stores inv(Rt)."""
    w2c = invert_rigid(c2w)
    r_3dgs, t_3dgs = w2c[:3, :3].T, w2c[:3, 3]
    rt = np.zeros((4, 4))
    rt[:3, :3] = r_3dgs.transpose()
    rt[:3, 3] = t_3dgs
    rt[3, 3] = 1.0
    inv = np.linalg.inv(rt)
    return {"id": i, "img_name": name, "width": 100, "height": 80, "position": inv[:3, 3].tolist(),
            "rotation": [row.tolist() for row in inv[:3, :3]], "fy": 90.0, "fx": 90.0}


def test_3dgs_cameras_json_reader(tmp_path):
    poses = random_poses(24, 4)
    path = tmp_path / "cameras.json"
    path.write_text(json.dumps([camera_to_json_3dgs(i, f"frame_{i:05d}", p) for i, p in enumerate(poses)]))
    assert detect_format(path) == "3dgs"
    assert_same_poses(read_3dgs_cameras_json(path), poses, [f"frame_{i:05d}" for i in range(4)])


def test_readers_refuse_what_they_cannot_pair(tmp_path):
    path = tmp_path / "cameras.json"
    path.write_text(json.dumps([camera_to_json_3dgs(0, "left/0001.png", np.eye(4)),
                                camera_to_json_3dgs(1, "right/0001.png", np.eye(4))]))
    with pytest.raises(PoseFileError, match="share the matching key '0001'"):
        read_3dgs_cameras_json(path)
    (tmp_path / "images.bin").write_bytes(b"\0")
    with pytest.raises(PoseFileError, match="model_converter"):
        detect_format(tmp_path / "images.bin")
    (tmp_path / "other.json").write_text(json.dumps({"poses": []}))
    with pytest.raises(PoseFileError, match="not a pose file"):
        detect_format(tmp_path / "other.json")


# ------------------------------------------------------------------------------------------------- the CLI

ROUTE = [(0.0, 0.0, 0.0), (0.8, 0.1, 0.3), (1.5, 0.5, 0.8), (2.0, 1.2, 1.4), (1.9, 2.0, 2.0), (1.2, 2.6, 2.6),
         (0.4, 2.7, 3.1), (-0.4, 2.3, 3.7), (-0.9, 1.6, 4.3), (-1.0, 0.8, 4.9), (-0.6, 0.1, 5.6), (0.1, -0.3, 6.1)]


def write_map_dataset(root: Path, route=ROUTE) -> list[np.ndarray]:
    """A gsrmr dataset of tiny frames along ``route``; returns the map-frame camera→world poses."""
    k = Intrinsics.from_fov(8, 6, 1.2)
    cams = [camera_from_pose(a, b, th, CameraMount(), k) for a, b, th in route]
    write_dataset(root, [DatasetFrame(c, np.zeros((6, 8, 3), np.float32), pose=p) for c, p in zip(cams, route,
                                                                                                   strict=True)])
    return [c.camera_to_world for c in cams]


def write_colmap(path: Path, poses: dict[str, np.ndarray]) -> Path:
    lines = []
    for i, (name, p) in enumerate(poses.items()):
        w2c = invert_rigid(p)
        q_xyzw = Rotation.from_matrix(w2c[:3, :3]).as_quat()
        numbers = " ".join(repr(float(v)) for v in (q_xyzw[3], *q_xyzw[:3], *w2c[:3, 3]))
        lines += [f"{i + 1} {numbers} 1 {name}", ""]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_map_dataset_reader(tmp_path):
    map_c2w = write_map_dataset(tmp_path / "map")
    assert_same_poses(read_map_dataset(tmp_path / "map"), map_c2w, [f"frame_{i:05d}" for i in range(len(ROUTE))])


def test_cli_aligns_a_model_end_to_end(tmp_path, capsys):
    map_c2w = write_map_dataset(tmp_path / "map")
    truth = random_similarity(30, 3.5)  # model → map
    model_c2w = [truth.inverse().apply_camera_to_world(p) for p in map_c2w]
    model_c2w[5][:3, 3] += 1.0  # one mis-registered image (3.5 m off in map)
    poses_3dgs = tmp_path / "cameras.json"
    poses_3dgs.write_text(json.dumps([camera_to_json_3dgs(i, f"frame_{i:05d}", p) for i, p in enumerate(model_c2w)]))
    model = scene_model(31, 50)
    model.save_ply(tmp_path / "model.ply")
    out, report = tmp_path / "aligned.ply", tmp_path / "report.json"
    code = align_main([str(tmp_path / "model.ply"), "--model-poses", str(poses_3dgs), "--map-dataset",
                       str(tmp_path / "map"), "--out", str(out), "--report", str(report)])
    captured = capsys.readouterr()
    assert code == 0 and captured.err == "", captured.err
    line = captured.out.strip()
    assert "\n" not in line and "12 pairs, 11 inliers" in line and "scale 3.5" in line
    aligned = GaussianModel.load_ply(out)
    np.testing.assert_allclose(aligned.means, truth.apply_points(model.means), atol=2e-4)
    data = json.loads(report.read_text())
    assert data["outlier_names"] == ["frame_00005"] and data["rms_center_error_m"] < 1e-5
    assert data["max_rotation_error_deg"] < 1e-4
    np.testing.assert_allclose(data["similarity"]["matrix"], truth.matrix(), atol=1e-6)

    # COLMAP names renumbered from frame_00001 (ns-process-data): --model-frame-offset -1 pairs them
    write_colmap(tmp_path / "images.txt", {f"frame_{i + 1:05d}.jpg": p for i, p in enumerate(model_c2w)})
    code = align_main([str(tmp_path / "model.ply"), "--model-poses", str(tmp_path / "images.txt"),
                       "--map-dataset", str(tmp_path / "map"), "--out", str(out), "--model-frame-offset", "-1"])
    assert code == 0 and "12 pairs, 11 inliers" in capsys.readouterr().out

    # camera→world in OpenCV axes where nerfstudio expects OpenGL: the centres still fit, the warning says why
    # the orientations do not (180° about the camera x axis)
    bad = tmp_path / "transforms.json"
    bad.write_text(json.dumps({"frames": [{"file_path": f"images/frame_{i:05d}.png", "transform_matrix": p.tolist()}
                                          for i, p in enumerate(model_c2w)]}))
    code = align_main([str(tmp_path / "model.ply"), "--model-poses", str(bad), "--map-dataset", str(tmp_path / "map"),
                       "--out", str(out)])
    captured = capsys.readouterr()
    assert code == 0 and "disagree by 180.0° RMS" in captured.err and "OpenGL for nerfstudio" in captured.err


def run_expecting_exit_2(capsys, argv: list[str]) -> str:
    assert align_main(argv) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("gsrmr-align: "), captured.err
    return lines[0]


def test_cli_bad_input_exits_2_with_one_line(tmp_path, capsys):
    map_c2w = write_map_dataset(tmp_path / "map")
    scene_model(32, 20).save_ply(tmp_path / "model.ply")
    base = [str(tmp_path / "model.ply"), "--map-dataset", str(tmp_path / "map"), "--out", str(tmp_path / "o.ply")]

    write_colmap(tmp_path / "names.txt", {f"IMG_{i:04d}.JPG": p for i, p in enumerate(map_c2w)})
    msg = run_expecting_exit_2(capsys, [*base, "--model-poses", str(tmp_path / "names.txt")])
    assert "no image name is in both" in msg and "'IMG_0000'" in msg and "'frame_00000'" in msg

    write_colmap(tmp_path / "few.txt", {f"frame_{i:05d}.png": map_c2w[i] for i in range(2)})
    msg = run_expecting_exit_2(capsys, [*base, "--model-poses", str(tmp_path / "few.txt")])
    assert "only 2 image(s)" in msg and "at least 3" in msg

    line_route = [(0.5 * i, 0.0, 0.0) for i in range(6)]  # a straight drive: centres on one line
    line_c2w = write_map_dataset(tmp_path / "line", line_route)
    write_colmap(tmp_path / "line.txt", {f"frame_{i:05d}.png": p for i, p in enumerate(line_c2w)})
    msg = run_expecting_exit_2(capsys, [str(tmp_path / "model.ply"), "--map-dataset", str(tmp_path / "line"),
                                        "--out", str(tmp_path / "o.ply"), "--model-poses", str(tmp_path / "line.txt")])
    assert "collinear" in msg

    write_colmap(tmp_path / "ok.txt", {f"frame_{i:05d}.png": p for i, p in enumerate(map_c2w)})
    msg = run_expecting_exit_2(capsys, [*base, "--model-poses", str(tmp_path / "ok.txt"), "--dataparser-transforms",
                                        str(tmp_path / "dp.json")])
    assert "drop --dataparser-transforms" in msg
    msg = run_expecting_exit_2(capsys, [str(tmp_path / "missing.ply"), *base[1:], "--model-poses",
                                        str(tmp_path / "ok.txt")])
    assert "missing.ply" in msg
    assert not (tmp_path / "o.ply").exists()
