"""Renderer correctness: an independent brute-force numpy reference, gradients, extremes, .ply IO."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement
import pytest
from scipy.spatial.transform import Rotation
import torch

from gsrmr_common.camera import Camera, CameraMount, Intrinsics, camera_from_pose
from gsrmr_sim.shared_data import garden_model, load_garden
from gsrmr_splat.diffrender import render_torch
from gsrmr_splat.model import GaussianModel, PlyFormatError
from gsrmr_splat.render import render
from gsrmr_splat.sh import C0, eval_sh_numpy, num_coeffs

NEAR = 0.2


def reference_render(model: GaussianModel, cam: Camera, bg) -> tuple[np.ndarray, np.ndarray]:
    """Brute force, float64, written from the 3DGS description: every Gaussian against every pixel."""
    k = cam.intrinsics
    w, h = k.width, k.height
    rot_w, t_w = cam.world_to_camera[:3, :3], cam.world_to_camera[:3, 3]
    q = model.quats.astype(np.float64)
    rots = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()  # scipy wants (x, y, z, w)
    s2 = np.exp(2.0 * model.log_scales.astype(np.float64))
    p_cam = model.means.astype(np.float64) @ rot_w.T + t_w
    opac = 1.0 / (1.0 + np.exp(-model.opacity_logits.astype(np.float64)))
    dirs = model.means.astype(np.float64) - cam.center_world
    with np.errstate(invalid="ignore", divide="ignore"):  # a Gaussian at the camera centre: culled anyway
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    colors = eval_sh_numpy(model.sh.astype(np.float64), dirs, model.sh_degree)
    tanx, tany = w / (2 * k.fx), h / (2 * k.fy)
    order = np.lexsort((np.arange(len(model)), p_cam[:, 2]))
    uu, vv = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    trans = np.ones((h, w))
    color = np.zeros((h, w, 3))
    active = np.ones((h, w), bool)
    for i in order:
        x, y, z = p_cam[i]
        if z < NEAR:
            continue
        xc = np.clip(x / z, -(k.cx / k.fx + 0.3 * tanx), (w - k.cx) / k.fx + 0.3 * tanx) * z
        yc = np.clip(y / z, -(k.cy / k.fy + 0.3 * tany), (h - k.cy) / k.fy + 0.3 * tany) * z
        jac = np.array([[k.fx / z, 0, -k.fx * xc / z**2], [0, k.fy / z, -k.fy * yc / z**2]])
        sigma3 = rots[i] @ np.diag(s2[i]) @ rots[i].T
        cov = jac @ rot_w @ sigma3 @ rot_w.T @ jac.T + 0.3 * np.eye(2)
        conic = np.linalg.inv(cov)
        mid = 0.5 * (cov[0, 0] + cov[1, 1])
        lam = mid + math.sqrt(max(0.1, mid * mid - np.linalg.det(cov)))
        radius = math.ceil(3 * math.sqrt(lam))
        mx, my = k.fx * x / z + k.cx, k.fy * y / z + k.cy
        dx, dy = uu - mx, vv - my
        sig = 0.5 * (conic[0, 0] * dx**2 + conic[1, 1] * dy**2) + conic[0, 1] * dx * dy
        alpha = np.minimum(0.99, opac[i] * np.exp(-sig))
        ok = active & (np.abs(dx) <= radius) & (np.abs(dy) <= radius) & (alpha >= 1 / 255) & (sig >= 0)
        t_next = trans * (1 - alpha)
        stop = ok & (t_next < 1e-4)
        active &= ~stop
        blend = ok & ~stop
        color[blend] += (trans * alpha)[blend][:, None] * colors[i]
        trans[blend] = t_next[blend]
    return np.clip(color + trans[..., None] * np.asarray(bg), 0, 1), 1 - trans


def random_model(rng: np.random.Generator, n: int, degree: int = 0, center=(0.0, 0.0, 2.5),
                 spread=1.2) -> GaussianModel:
    means = np.asarray(center) + rng.uniform(-spread, spread, (n, 3))
    sh = rng.normal(0, 0.3, (n, num_coeffs(degree), 3))
    sh[:, 0] = (rng.uniform(0, 1, (n, 3)) - 0.5) / C0
    return GaussianModel(means, rng.normal(size=(n, 4)), np.log(rng.uniform(0.02, 0.35, (n, 3))),
                         rng.normal(0, 2, n), sh)


def front_camera(w=64, h=48, fov_deg=70.0, cx=None, cy=None) -> Camera:
    k = Intrinsics.from_fov(w, h, math.radians(fov_deg))
    if cx is not None:
        k = Intrinsics(k.fx, k.fy * 1.1, cx, cy, w, h)
    return Camera(k, np.eye(4))


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_fast_renderer_matches_brute_force(degree):
    rng = np.random.default_rng(degree)
    model = random_model(rng, 160, degree)
    for cam, bg in [(front_camera(), (0.2, 0.5, 0.9)), (front_camera(50, 37, 90, cx=20.3, cy=21.7), (0, 0, 0))]:
        out = render(model, cam, bg)
        ref_rgb, ref_alpha = reference_render(model, cam, bg)
        assert np.mean(np.abs(out.rgb - ref_rgb)) <= 1e-4
        assert np.mean(np.abs(out.alpha - ref_alpha)) <= 1e-4
        assert out.alpha.max() > 0.5  # the scene is actually visible


def test_vectorised_exp_is_accurate_clamped_and_finite():
    from gsrmr_splat.fastexp import EXP_ARG_MIN, exp_neg_array

    x = np.linspace(float(EXP_ARG_MIN), 0.0, 200_001).astype(np.float32)
    out = np.empty_like(x)
    exp_neg_array(x, out)
    ref = np.exp(x.astype(np.float64))
    assert np.max(np.abs(out - ref) / ref) <= 4e-6
    extremes = np.array([-1e30, -1e4, -31.0, 1e-3, 5.0, 1e30], np.float32)
    out = np.empty_like(extremes)
    exp_neg_array(extremes, out)
    assert np.all(np.isfinite(out)) and np.all(out > 0)
    np.testing.assert_allclose(out[:3], np.exp(float(EXP_ARG_MIN)), rtol=4e-6)  # clamped below
    np.testing.assert_allclose(out[3:], 1.0, rtol=4e-6)  # σ < 0 is treated as σ = 0


def test_display_rasterizer_matches_the_float64_training_kernel_on_the_garden():
    """The float32 vectorised display path against the float64 kernel training uses (tile 8 selects it)."""
    model = garden_model()
    cam = load_garden()[2][0]
    for w, h in ((320, 240), (648, 420)):
        c = Camera(cam.intrinsics.scaled(w, h), cam.world_to_camera)
        fast, slow = render(model, c, (0.1, 0.2, 0.3)), render(model, c, (0.1, 0.2, 0.3), tile=8)
        assert np.mean(np.abs(fast.rgb - slow.rgb)) <= 1e-6
        # a lone pixel may flip at a threshold (α = 1/255 or T = 1e-4) between float32 and float64
        assert np.max(np.abs(fast.rgb - slow.rgb)) <= 5e-3
        assert np.mean(np.abs(fast.alpha - slow.alpha)) <= 1e-6
        assert fast.num_visible == slow.num_visible > 10_000


def test_tile_size_does_not_change_the_image():
    model = random_model(np.random.default_rng(7), 120)
    cam = front_camera(70, 45)
    a, b = render(model, cam, tile=16), render(model, cam, tile=8)
    np.testing.assert_allclose(a.rgb, b.rgb, atol=1e-6)
    c = render(model, cam, threads=1)
    np.testing.assert_array_equal(a.rgb, c.rgb)


def test_duplicated_gaussians_tie_break_by_index():
    # Two Gaussians with identical geometry and different colours: the lower index is in front.
    model = GaussianModel.from_points(np.array([[0, 0, 2.0], [0, 0, 2.0]]), np.array([[1.0, 0, 0], [0, 0, 1.0]]),
                                      scales_m=0.3, opacities=0.9)
    out = render(model, front_camera(32, 24))
    centre = out.rgb[12, 16]
    assert centre[0] > 0.8 and centre[2] < 0.2
    ref, _ = reference_render(model, front_camera(32, 24), (0, 0, 0))
    assert np.mean(np.abs(out.rgb - ref)) <= 1e-4


def test_pose_camera_sees_point_ahead_at_the_image_centre():
    # Robot at (1, 2) facing +y (θ = π/2): a blob 3 m ahead at camera height lands at the centre.
    mount = CameraMount(height_m=0.3, pitch_rad=0.0, forward_m=0.1)
    cam = camera_from_pose(1.0, 2.0, math.pi / 2, mount, Intrinsics.from_fov(40, 30, math.radians(60)))
    model = GaussianModel.from_points(np.array([[1.0, 5.1, 0.3]]), np.array([[0, 1.0, 0]]), scales_m=0.05,
                                      opacities=0.99)
    out = render(model, cam)
    v, u = np.unravel_index(np.argmax(out.alpha), out.alpha.shape)
    assert (u, v) in {(19, 14), (20, 14), (19, 15), (20, 15)}
    assert out.depth[v, u] == pytest.approx(3.0, abs=1e-3)


def test_torch_path_matches_fast_render():
    model = random_model(np.random.default_rng(3), 100, degree=2)
    cam = front_camera(48, 40)
    out = render(model, cam, (0.1, 0.2, 0.3))
    params = [torch.from_numpy(a.copy()) for a in (model.means, model.quats, model.log_scales,
                                                   model.opacity_logits, model.sh)]
    t_out = render_torch(*params, cam, (0.1, 0.2, 0.3), sh_degree=2)
    np.testing.assert_allclose(np.clip(t_out.rgb.numpy(), 0, 1), out.rgb, atol=2e-4)


def test_gradients_match_finite_differences():
    rng = np.random.default_rng(11)
    model = random_model(rng, 6, degree=1, spread=0.5)
    model.log_scales[:] = np.log(rng.uniform(0.1, 0.3, (6, 3)))
    model.opacity_logits[:] = rng.normal(0, 1, 6)
    cam = front_camera(24, 18)
    params = [torch.tensor(a, dtype=torch.float64, requires_grad=True)
              for a in (model.means, model.quats, model.log_scales, model.opacity_logits, model.sh)]
    w_rgb = torch.from_numpy(rng.normal(size=(18, 24, 3)))
    w_a = torch.from_numpy(rng.normal(size=(18, 24)))

    def loss_fn(ps):
        o = render_torch(*ps, cam, (0.3, 0.6, 0.1), sh_degree=1)
        return (o.rgb * w_rgb).sum() + (o.alpha * w_a).sum()

    loss = loss_fn(params)
    loss.backward()
    eps = 1e-6
    for p in params:
        analytic = p.grad.numpy().ravel()
        numeric = np.zeros_like(analytic)
        flat = p.data.view(-1)
        for j in range(flat.numel()):
            old = flat[j].item()
            flat[j] = old + eps
            lp = loss_fn(params).item()
            flat[j] = old - eps
            lm = loss_fn(params).item()
            flat[j] = old
            numeric[j] = (lp - lm) / (2 * eps)
        scale = max(1.0, np.abs(numeric).max())
        assert np.max(np.abs(analytic - numeric)) / scale < 1e-5, (p.shape, analytic, numeric)
        assert np.abs(analytic).max() > 0  # every parameter group really receives gradient


def _finite(out):
    for arr in (out.rgb, out.alpha, out.depth):
        assert np.all(np.isfinite(arr))
    assert out.rgb.min() >= 0 and out.rgb.max() <= 1


def test_extremes_never_produce_nan():
    cam = front_camera(40, 30)
    pts = np.array([[0, 0, 2.0], [0.3, 0, 1.0], [0, 0, 0.0], [0, 0, -1.0], [0, 0, 0.1], [0.2, 0.2, 3.0],
                    [1e4, 0, 1.0], [0, 0, 1e6]])
    model = GaussianModel.from_points(pts, np.full((8, 3), 0.7), scales_m=0.05, opacities=0.5)
    model.log_scales[0] = -40.0  # scale ≈ 0: only the 0.3 px² dilation remains
    model.log_scales[1] = 12.0   # enormous
    model.opacity_logits[4] = 60.0  # opacity 1 (clamped to 0.99)
    model.opacity_logits[5] = -60.0  # opacity 0
    out = render(model, cam, (0.5, 0.5, 0.5))
    _finite(out)
    # The z = 0, z < 0 and z = 0.1 (< near plane) Gaussians are culled; the huge one (opacity 0.5)
    # covers the whole view.
    assert out.alpha.min() >= 0.49
    ref, _ = reference_render(model, cam, (0.5, 0.5, 0.5))
    assert np.mean(np.abs(out.rgb - ref)) <= 1e-4


def test_nan_parameters_are_culled_and_ply_refuses_them(tmp_path):
    model = random_model(np.random.default_rng(5), 20)
    model.means[3] = np.nan
    model.quats[4] = 0.0
    model.sh[5, 0, 1] = np.inf
    model.opacity_logits[6] = np.nan
    model.log_scales[7, 1] = np.nan
    _finite(render(model, front_camera()))
    _finite(render(model.with_degree(2), front_camera()))
    with pytest.raises(ValueError, match="NaN"):
        model.save_ply(tmp_path / "bad.ply")


def test_empty_model_and_image_sizes():
    bg = (0.25, 0.5, 0.75)
    out = render(GaussianModel.empty(), front_camera(16, 9), bg)
    np.testing.assert_allclose(out.rgb, np.broadcast_to(bg, (9, 16, 3)), atol=1e-7)
    assert np.all(out.alpha == 0) and np.all(out.depth == 0)
    model = random_model(np.random.default_rng(1), 50)
    tiny = render(model, front_camera(1, 1), bg)
    assert tiny.rgb.shape == (1, 1, 3)
    _finite(tiny)
    ref, _ = reference_render(model, front_camera(1, 1), bg)
    assert np.abs(tiny.rgb - ref).max() <= 1e-4
    big = render(model, front_camera(1920, 1080), bg)
    assert big.rgb.shape == (1080, 1920, 3)
    _finite(big)
    with pytest.raises(ValueError, match="background"):
        render(model, front_camera(), (np.nan, 0, 0))


def test_ply_round_trip_all_degrees(tmp_path):
    rng = np.random.default_rng(2)
    for degree in range(4):
        model = random_model(rng, 30, degree)
        path = model.save_ply(tmp_path / f"m{degree}.ply")
        back = GaussianModel.load_ply(path)
        assert back.sh_degree == degree
        for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
            np.testing.assert_array_equal(getattr(back, name), getattr(model, name))


def _write_3dgs_style(path: Path, xyz, f_dc, f_rest_nk3, opac, scale, rot) -> None:
    """Mimics graphdeco-inria GaussianModel.save_ply: features_rest (N, K−1, 3) → transpose(1, 2) → flatten."""
    n = xyz.shape[0]
    f_rest = np.transpose(f_rest_nk3, (0, 2, 1)).reshape(n, -1)
    attrs = ["x", "y", "z", "nx", "ny", "nz", *[f"f_dc_{i}" for i in range(3)],
             *[f"f_rest_{i}" for i in range(f_rest.shape[1])], "opacity", *[f"scale_{i}" for i in range(3)],
             *[f"rot_{i}" for i in range(4)]]
    elements = np.empty(n, dtype=[(a, "f4") for a in attrs])
    cols = np.concatenate([xyz, np.zeros_like(xyz), f_dc, f_rest, opac[:, None], scale, rot], axis=1)
    elements[:] = list(map(tuple, cols))
    PlyData([PlyElement.describe(elements, "vertex")]).write(str(path))


def test_loads_a_degree_3_file_written_like_original_3dgs(tmp_path):
    rng = np.random.default_rng(4)
    n = 12
    xyz, f_dc = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    f_rest = rng.normal(size=(n, 15, 3))
    opac, scale, rot = rng.normal(size=n), rng.normal(size=(n, 3)), rng.normal(size=(n, 4))
    _write_3dgs_style(tmp_path / "orig.ply", xyz, f_dc, f_rest, opac, scale, rot)
    model = GaussianModel.load_ply(tmp_path / "orig.ply")
    assert model.sh_degree == 3
    np.testing.assert_allclose(model.sh[:, 0], f_dc, rtol=1e-6)
    np.testing.assert_allclose(model.sh[:, 1:], f_rest, rtol=1e-6)
    np.testing.assert_allclose(model.quats, rot, rtol=1e-6)
    # Our writer produces the same property order and values as the original.
    model.save_ply(tmp_path / "ours.ply")
    a = PlyData.read(str(tmp_path / "orig.ply"))["vertex"].data
    b = PlyData.read(str(tmp_path / "ours.ply"))["vertex"].data
    assert a.dtype.names == b.dtype.names
    for name in a.dtype.names:
        np.testing.assert_array_equal(a[name], b[name])


def test_malformed_ply_files_raise_clear_errors(tmp_path):
    (tmp_path / "garbage.ply").write_bytes(b"this is not a ply file\n")
    with pytest.raises(PlyFormatError):
        GaussianModel.load_ply(tmp_path / "garbage.ply")
    pts = np.zeros(3, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    PlyData([PlyElement.describe(pts, "vertex")]).write(str(tmp_path / "points.ply"))
    with pytest.raises(PlyFormatError, match="missing"):
        GaussianModel.load_ply(tmp_path / "points.ply")
    rng = np.random.default_rng(0)
    _write_3dgs_style(tmp_path / "odd.ply", rng.normal(size=(2, 3)), rng.normal(size=(2, 3)),
                      rng.normal(size=(2, 2, 3)), rng.normal(size=2), rng.normal(size=(2, 3)), rng.normal(size=(2, 4)))
    with pytest.raises(PlyFormatError, match="degree"):
        GaussianModel.load_ply(tmp_path / "odd.ply")
    xyz = rng.normal(size=(2, 3))
    xyz[1, 2] = np.nan
    _write_3dgs_style(tmp_path / "nan.ply", xyz, rng.normal(size=(2, 3)), np.zeros((2, 0, 3)), rng.normal(size=2),
                      rng.normal(size=(2, 3)), rng.normal(size=(2, 4)))
    with pytest.raises(PlyFormatError, match="NaN"):
        GaussianModel.load_ply(tmp_path / "nan.ply")
    with pytest.raises(FileNotFoundError):
        GaussianModel.load_ply(tmp_path / "missing.ply")


def test_sh_basis_is_orthonormal_on_the_sphere():
    # Independent check of the SH constants: ∫ Y_i Y_j dΩ = δ_ij (Monte Carlo on 100k directions).
    rng = np.random.default_rng(0)
    d = rng.normal(size=(100_000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    basis = np.empty((d.shape[0], 16))
    for i in range(16):
        basis[:, i] = _raw_basis(d, i)
    gram = basis.T @ basis * (4 * np.pi / d.shape[0])
    np.testing.assert_allclose(gram, np.eye(16), atol=0.03)


def _raw_basis(d, i):
    sh = np.zeros((d.shape[0], 16, 3))
    sh[:, i, 0] = 1.0
    # eval_sh_numpy returns max(0, SH + 0.5): a coefficient of 0.01 keeps it above the clamp.
    return (eval_sh_numpy(sh * 0.01, d, 3)[:, 0] - 0.5) / 0.01


def test_garden_model_is_reproducible_and_renders_the_real_view():
    model = garden_model()
    again = garden_model()
    assert model.num_gaussians > 100_000
    np.testing.assert_array_equal(model.log_scales, again.log_scales)
    assert np.all(np.abs(model.means) <= 2.0)
    _, _, cams = load_garden()
    cam = Camera(cams[0].intrinsics.scaled(160, 104), cams[0].world_to_camera)
    out = render(model, cam)
    _finite(out)
    assert out.alpha.mean() > 0.5 and out.num_visible > 10_000


def test_stability_at_the_extremes_of_scale_shape_position_and_count(tmp_path):
    """No NaN or inf reaches a pixel: scales 1e-6 m … 1e3 m, near-degenerate and needle covariances, a camera
    inside a Gaussian and one exactly at the near plane, opacities 0 and 1, 10^6 Gaussians in one tile."""
    from gsrmr_splat.model import PlyFormatError
    from gsrmr_splat.project import NEAR_M

    cam = front_camera(64, 48)
    bg = (0.2, 0.3, 0.4)

    def one(mean, scales, opacity_logit=0.0):
        return GaussianModel(np.array([mean], float), np.array([[1.0, 0.0, 0.0, 0.0]]), np.log([scales]),
                             np.array([opacity_logit]), np.full((1, 1, 3), 1.0))

    for s in (1e-6, 1e-3, 1.0, 1e3):
        _finite(render(one((0.0, 0.0, 2.0), (s, s, s)), cam, bg))
    for scales in ((1e-9, 0.5, 0.5), (1e-7, 1e-7, 2.0), (1e3, 1e-6, 1e3)):  # flat disc, needle, wall
        _finite(render(one((0.0, 0.0, 2.0), scales), cam, bg))
    inside = render(one((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)), cam, bg)  # the camera centre inside it
    _finite(inside)
    _finite(render(one((0.0, 0.0, NEAR_M), (0.1, 0.1, 0.1)), cam, bg))  # centre exactly on the near plane
    for logit in (-60.0, 60.0):  # opacity 0 and 1
        out = render(one((0.0, 0.0, 2.0), (0.2, 0.2, 0.2), logit), cam, bg)
        _finite(out)
        assert (out.alpha.max() < 1e-6) if logit < 0 else (out.alpha.max() <= 0.99 + 1e-6)
    n = 1_000_000  # all in the one 16×16 tile around the image centre
    rng = np.random.default_rng(0)
    crowd = GaussianModel.from_points(np.column_stack([rng.uniform(-0.01, 0.01, (n, 2)), np.full(n, 2.0)]),
                                      rng.uniform(0, 1, (n, 3)), scales_m=0.003, opacities=0.5)
    out = render(crowd, cam, bg)
    _finite(out)
    assert out.alpha[24, 32] > 0.99  # saturated where they pile up, early termination or not

    good = GaussianModel.from_points(np.array([[0.0, 0.0, 2.0], [0.1, 0.0, 2.0]]), np.full((2, 3), 0.5),
                                     scales_m=0.1, opacities=0.5, degree=1)
    good.save_ply(tmp_path / "good.ply")
    from plyfile import PlyData, PlyElement

    for prop in ("x", "scale_0", "opacity", "rot_2", "f_dc_1", "f_rest_4"):
        data = PlyData.read(str(tmp_path / "good.ply"))["vertex"].data.copy()
        data[prop][1] = np.inf if prop == "opacity" else np.nan
        PlyData([PlyElement.describe(data, "vertex")]).write(str(tmp_path / "bad.ply"))
        with pytest.raises(PlyFormatError, match=rf"'{prop}' holds NaN/inf \(first at vertex 1\)"):
            GaussianModel.load_ply(tmp_path / "bad.ply")
