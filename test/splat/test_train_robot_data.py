"""Training on what a robot records: initialisation order (depth, the dataset's point cloud, random), per-frame
pose refinement with its gauge rule, per-frame exposure compensation, their checkpoint, ``gsrmr-train``'s new
flags and its ``train.json``, and the default path left as it was.

Small synthetic scenes (a few hundred Gaussians rendered by the engine at 64×48 px, ≤ 8 views, ≤ 150 steps).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from gsrmr_common.camera import Camera, Intrinsics
from gsrmr_common.nerfstudio import DatasetFrame, dataset_point_cloud, read_dataset, write_dataset
from gsrmr_offline.deployment_survey import recorded_split
from gsrmr_splat.camera_opt import (
    EXPOSURE_DIM,
    POSE_DIM,
    FrameCorrections,
    corrected_world_to_camera,
    corrected_world_to_camera_np,
)
from gsrmr_splat.datasets import orbit_cameras, render_views
from gsrmr_splat.diffrender import render_torch
from gsrmr_splat.losses import train_loss
from gsrmr_splat.model import GaussianModel
from gsrmr_splat.render import render
from gsrmr_splat.sh import C0
from gsrmr_splat.train import Trainer
from gsrmr_splat.train_cli import train_main
from gsrmr_splat.train_config import TrainConfig

WIDTH, HEIGHT = 64, 48


def scene(n: int = 400, seed: int = 0, colour_range=(0.0, 1.0)) -> GaussianModel:
    """n Gaussians in a 0.8 m cube around the origin, flat colours drawn from ``colour_range``."""
    rng = np.random.default_rng(seed)
    sh = (rng.uniform(*colour_range, (n, 1, 3)) - 0.5) / C0
    return GaussianModel(rng.uniform(-0.4, 0.4, (n, 3)), rng.normal(size=(n, 4)),
                         np.log(rng.uniform(0.02, 0.06, (n, 3))), rng.normal(1, 1, n), sh)


def views(model: GaussianModel, n: int = 6, depth: bool = True) -> list[DatasetFrame]:
    cams = orbit_cameras(n, Intrinsics.from_fov(WIDTH, HEIGHT, math.radians(60)), radius_m=1.4,
                         heights_m=(0.3, 0.6), target_m=(0.0, 0.0, 0.0))
    return render_views(model, cams, with_depth=depth)


def moved(frame: DatasetFrame, delta: np.ndarray) -> DatasetFrame:
    """The frame with its recorded pose corrected by ``delta`` (the image stays the true one)."""
    cam = Camera(frame.camera.intrinsics, corrected_world_to_camera_np(frame.camera.world_to_camera, delta))
    return DatasetFrame(cam, frame.image, frame.depth_m, frame.pose, frame.file_path)


def perturbation(seed: int, cm: float = 2.0, deg: float = 1.0) -> np.ndarray:
    """A pose correction of exactly ``cm`` and ``deg`` in random directions: (ω rad, τ m)."""
    rng = np.random.default_rng(seed)
    w, t = rng.normal(size=3), rng.normal(size=3)
    return np.concatenate([w / np.linalg.norm(w) * math.radians(deg), t / np.linalg.norm(t) * cm / 100.0])


def frozen(**kw) -> TrainConfig:
    """The model's rates at zero (means: 1e-30): only the per-frame corrections move."""
    base = dict(lr_means=1e-30, lr_means_final=1e-30, lr_sh_dc=0.0, lr_sh_rest=0.0, lr_opacity=0.0,
                lr_scales=0.0, lr_quats=0.0, densify_from=10**6, opacity_reset_interval=10**6, final_prune=False,
                sh_degree=0)
    base.update(kw)
    return TrainConfig(**base)


def reprojection_px(model: GaussianModel, cam: Camera, truth: Camera) -> float:
    """Mean pixel distance between the Gaussians' centres projected by ``cam`` and by the true camera."""
    uv, _ = cam.project(model.means)
    uv_true, _ = truth.project(model.means)
    return float(np.nanmean(np.linalg.norm(uv - uv_true, axis=1)))


# ------------------------------------------------------------------ the point cloud and the initialisation order


def test_dataset_names_its_point_cloud_and_reads_it_back(tmp_path):
    frames = views(scene(), 3, depth=False)
    rng = np.random.default_rng(1)
    pts, cols = rng.uniform(-1, 1, (50, 3)), rng.integers(0, 256, (50, 3)).astype(np.uint8)
    write_dataset(tmp_path / "with", frames, point_cloud=(pts, cols))
    meta = json.loads((tmp_path / "with" / "transforms.json").read_text())
    assert meta["ply_file_path"] == "sparse_pc.ply"
    got_pts, got_cols = dataset_point_cloud(tmp_path / "with")
    np.testing.assert_array_equal(got_pts, pts.astype(np.float32).astype(np.float64))
    np.testing.assert_array_equal(np.round(got_cols * 255).astype(np.uint8), cols)
    assert len(read_dataset(tmp_path / "with")) == 3  # the frame list as before
    write_dataset(tmp_path / "without", frames)
    assert dataset_point_cloud(tmp_path / "without") is None
    assert "ply_file_path" not in json.loads((tmp_path / "without" / "transforms.json").read_text())
    # nerfstudio's COLMAP export writes an ASCII .ply (float x y z, uint8 red green blue)
    (tmp_path / "with" / "ascii.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
        "property uint8 red\nproperty uint8 green\nproperty uint8 blue\nend_header\n"
        "0.5 -1.25 2 255 0 128\n1 2 3 0 255 0\n")
    meta["ply_file_path"] = "ascii.ply"
    (tmp_path / "with" / "transforms.json").write_text(json.dumps(meta))
    got_pts, got_cols = dataset_point_cloud(tmp_path / "with" / "transforms.json")
    np.testing.assert_array_equal(got_pts, [[0.5, -1.25, 2.0], [1.0, 2.0, 3.0]])
    np.testing.assert_allclose(got_cols, [[1.0, 0.0, 128 / 255], [0.0, 1.0, 0.0]])
    meta["ply_file_path"] = "missing.ply"
    (tmp_path / "with" / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(FileNotFoundError, match=r"missing\.ply"):
        dataset_point_cloud(tmp_path / "with")


def test_points_init_puts_the_initial_means_on_the_cloud_subsampled_by_the_seed(tmp_path):
    frames = views(scene(), 4, depth=False)
    rng = np.random.default_rng(2)
    pts, cols = rng.uniform(-0.5, 0.5, (500, 3)), rng.integers(0, 256, (500, 3)).astype(np.uint8)
    write_dataset(tmp_path / "ds", frames, point_cloud=(pts, cols))
    file_pts = pts.astype(np.float32)

    def initial(seed: int, n: int) -> Trainer:
        return Trainer.from_dataset(tmp_path / "ds", TrainConfig(init_points=n, seed=seed, sh_degree=0))

    a, b, c = initial(0, 200), initial(0, 200), initial(1, 200)
    assert a.init_source == "points" and a.num_gaussians == 200
    means = a.state.params["means"].numpy()
    # every initial mean is exactly one of the file's points, each at most once, with that point's colour
    index = {tuple(p): i for i, p in enumerate(file_pts)}
    hits = [index.get(tuple(m)) for m in means]
    assert None not in hits and len(set(hits)) == 200
    rgb = a.state.params["sh_dc"].numpy()[:, 0] * C0 + 0.5
    np.testing.assert_allclose(rgb, cols[hits] / 255.0, atol=1e-6)
    torch.testing.assert_close(b.state.params["means"], a.state.params["means"], rtol=0, atol=0)  # same seed
    assert not torch.equal(c.state.params["means"], a.state.params["means"])  # another seed, another subset
    whole = initial(0, 10_000)  # fewer points than asked: all of them, in file order
    np.testing.assert_array_equal(whole.state.params["means"].numpy(), file_pts)


def test_auto_init_order_depth_then_points_then_random(tmp_path):
    model = scene()
    cloud = (np.random.default_rng(3).uniform(-0.5, 0.5, (300, 3)), np.full((300, 3), 128, np.uint8))
    cases = {"rgbd+cloud": (True, cloud), "rgb+cloud": (False, cloud), "rgb": (False, None)}
    for name, (depth, pc) in cases.items():
        write_dataset(tmp_path / name, views(model, 3, depth=depth), point_cloud=pc)

    def source(name: str, init: str = "auto") -> str:
        return Trainer.from_dataset(tmp_path / name, TrainConfig(init=init, init_points=300)).init_source

    assert [source(n) for n in cases] == ["depth", "points", "random"]
    assert source("rgbd+cloud", "points") == "points" and source("rgbd+cloud", "random") == "random"
    with pytest.raises(ValueError, match="depth"):
        source("rgb+cloud", "depth")
    with pytest.raises(ValueError, match="ply_file_path"):
        source("rgb", "points")
    with pytest.raises(ValueError, match="init must be one of"):
        Trainer(views(model, 2), TrainConfig(init="colmap"))


# ------------------------------------------------------------------ pose refinement


def test_corrected_pose_enters_the_differentiable_render():
    """The pose as a tensor: the same image as the camera's own pose, and the gradient of a smooth image loss
    with respect to δ equal to central differences (six large Gaussians, SH degree 1: the camera centre's path
    through the view directions counts too; the test_splatting gradient check's setting)."""
    rng = np.random.default_rng(11)
    n = 6
    sh = rng.normal(0, 0.4, (n, 4, 3))
    params = [torch.from_numpy(a) for a in (rng.uniform(-0.3, 0.3, (n, 3)), rng.normal(size=(n, 4)),
                                           np.log(rng.uniform(0.1, 0.3, (n, 3))), rng.normal(0, 1, n), sh)]
    cam = orbit_cameras(3, Intrinsics.from_fov(24, 18, math.radians(60)), radius_m=1.4, heights_m=(0.3,),
                        target_m=(0.0, 0.0, 0.0))[1]
    recorded = torch.as_tensor(cam.world_to_camera)
    plain = render_torch(*params, cam, (0.3, 0.6, 0.1), sh_degree=1)
    via_tensor = render_torch(*params, cam, (0.3, 0.6, 0.1), sh_degree=1, world_to_camera=recorded)
    torch.testing.assert_close(via_tensor.rgb, plain.rgb, rtol=0, atol=1e-12)
    w_rgb = torch.from_numpy(rng.normal(size=(18, 24, 3)))
    delta0 = torch.from_numpy(perturbation(6, cm=0.5, deg=0.3))

    def loss_at(delta: torch.Tensor) -> torch.Tensor:
        out = render_torch(*params, cam, (0.3, 0.6, 0.1), sh_degree=1,
                           world_to_camera=corrected_world_to_camera(recorded, delta))
        return (out.rgb * w_rgb).sum()

    d = delta0.clone().requires_grad_(True)
    loss_at(d).backward()
    h = 1e-6
    numeric = torch.stack([(loss_at(delta0 + h * e) - loss_at(delta0 - h * e)) / (2 * h)
                           for e in torch.eye(6, dtype=torch.float64)])
    assert float(d.grad.abs().min()) > 1e-2  # every component of the pose reaches the image
    scale = max(1.0, float(numeric.abs().max()))
    assert float((d.grad - numeric).abs().max()) / scale < 1e-5, (d.grad, numeric)


def test_pose_opt_recovers_known_perturbations_and_keeps_the_gauge():
    """Two views' recorded poses are moved by +d and −d (2 cm, 1°); the model is the true one, frozen. The true
    corrections are −d and +d, whose mean is zero: the gauge rule allows them. The learned ones come close,
    the other views stay near zero, and the corrections' mean stays zero."""
    model = scene()
    frames = views(model, 6)
    d = perturbation(7)
    recorded = list(frames)
    recorded[1], recorded[4] = moved(frames[1], d), moved(frames[4], -d)
    tr = Trainer(recorded, frozen(iterations=150, pose_opt=True, lr_pose=3e-3, lr_pose_final=1e-3),
                 initial_model=model)
    for _ in range(150):
        tr.step()
    learned = tr.state.pose.values.numpy()
    cams = tr.training_cameras()
    for view, truth in ((1, -d), (4, d)):
        err = learned[view] - truth
        err_cm, err_deg = np.linalg.norm(err[3:]) * 100, math.degrees(np.linalg.norm(err[:3]))
        before_px = reprojection_px(model, recorded[view].camera, frames[view].camera)
        after_px = reprojection_px(model, cams[view], frames[view].camera)
        print(f"view {view}: pose error 2.00 cm / 1.00° → {err_cm:.2f} cm / {err_deg:.2f}°, "
              f"reprojection {before_px:.2f} → {after_px:.2f} px")
        assert err_cm < 1.0 and err_deg < 0.5
        assert after_px < 0.3 * before_px
    others = np.delete(learned, [1, 4], axis=0)
    assert np.linalg.norm(others[:, 3:], axis=1).max() < 0.01 and np.degrees(
        np.linalg.norm(others[:, :3], axis=1)).max() < 0.5
    assert np.abs(learned.mean(axis=0)).max() < 1e-12  # the gauge rule
    summary = tr.corrections_summary()
    assert summary["pose_delta_max_cm"] == pytest.approx(np.linalg.norm(learned[:, 3:], axis=1).max() * 100)
    assert tr.state.exposure is None and "exposure_gain_min" not in summary


def test_refined_model_still_renders_right_at_the_unrefined_poses():
    """Noise of 2 cm / 1° on every training pose (held-out poses true), model trained from depth: with pose
    refinement (mean held at zero) the held-out PSNR at the recorded poses is not worse than without it, and
    test-time pose refinement of a held-out view moved by 2 cm / 1° finds most of it back."""
    model = scene(seed=8)
    frames = views(model, 8)
    train = [moved(f, perturbation(10 + i)) for i, f in enumerate(frames[:7])]
    held = frames[7:]
    psnr = {}
    for on in (False, True):
        cfg = TrainConfig(iterations=150, densify_from=50, densify_until=120, densify_interval=50, init_points=2000,
                          sh_degree=0, final_prune=False, pose_opt=on)
        tr = Trainer(train, cfg, held)
        tr.train(progress=False)
        psnr[on] = tr.evaluate()
        if on:
            assert np.abs(tr.state.pose.values.numpy().mean(axis=0)).max() < 1e-12
            assert tr.corrections_summary()["pose_delta_max_cm"] > 0.1
            assert len(tr.state.correction_history) == len(tr.state.history)
            # a held-out view recorded 2 cm / 1° off: 30 steps of test-time refinement, model frozen
            off = [moved(held[0], perturbation(30))]
            at_recorded = tr.evaluate(off)
            refined_db, deltas = tr.evaluate_pose_refined(30, lr_pose=2e-3, frames=off)
            print(f"test-time pose refinement: {at_recorded:.2f} → {refined_db:.2f} dB")
            assert refined_db > at_recorded + 1.0 and len(deltas) == 1
    print(f"held-out PSNR at the recorded poses: without pose-opt {psnr[False]:.2f} dB, with {psnr[True]:.2f} dB")
    assert psnr[True] > psnr[False] - 0.3


# ------------------------------------------------------------------ exposure


def test_exposure_opt_recovers_a_known_gain_and_the_model_keeps_the_average_exposure():
    """View 2 of 6 recorded 1.3× brighter (dark scene: nothing clips). Model initialised at the truth and
    trained: the learned gain of view 2 over the others' is 1.3 and the model renders view 2 like every other
    view — all at the geometric-mean exposure 1.3^(1/6) of the truth (the gauge rule); without exposure
    optimisation the model renders view 2 brighter than the rest."""
    model = scene(colour_range=(0.1, 0.6))
    frames = views(model, 6)
    recorded = list(frames)
    f = frames[2]
    recorded[2] = DatasetFrame(f.camera, (np.round(f.image * 1.3 * 255) / 255).astype(np.float32), f.depth_m,
                               None, f.file_path)
    assert recorded[2].image.max() < 1.0

    def brightness(tr: Trainer) -> np.ndarray:
        """Per view: mean rendered colour / mean true colour, over the pixels the scene covers."""
        m = tr.model()
        out = []
        for fr in frames:
            mask = fr.image.sum(axis=-1) > 0.1
            out.append(render(m, fr.camera).rgb[mask].mean() / fr.image[mask].mean())
        return np.array(out)

    ratios = {}
    for on in (False, True):
        cfg = TrainConfig(iterations=150, densify_from=10**6, opacity_reset_interval=10**6, final_prune=False,
                          sh_degree=0, exposure_opt=on, lr_exposure=5e-2, lr_exposure_final=5e-3)
        tr = Trainer(recorded, cfg, initial_model=model)
        for _ in range(150):
            tr.step()
        ratios[on] = brightness(tr)
        if on:
            v = tr.state.exposure.values.numpy()
            gain = np.exp(v[2, :3] - np.delete(v, 2, axis=0)[:, :3].mean(axis=0))
            print(f"learned gain of the brightened view over the others: {gain.round(3)}; biases {v[2, 3:].round(4)}")
            np.testing.assert_allclose(gain, 1.3, atol=0.04)
            assert np.abs(v.mean(axis=0)).max() < 1e-12
            summary = tr.corrections_summary()
            assert summary["exposure_gain_max"] == pytest.approx(float(np.exp(v[:, :3]).max()))
            assert tr.state.pose is None
            # the exposure model maps the recorded image back to the model's exposure
            assert brightness_of(tr.refined_frames()[2].image) == pytest.approx(
                brightness_of(frames[2].image) * 1.3 ** (1 / 6), rel=0.03)
    print(f"render / truth per view, exposure-opt off: {ratios[False].round(3)}, on: {ratios[True].round(3)}")
    others_on = np.delete(ratios[True], 2)
    assert abs(ratios[True][2] - others_on.mean()) < 0.015
    np.testing.assert_allclose(ratios[True], 1.3 ** (1 / 6), atol=0.02)
    assert ratios[False][2] - np.delete(ratios[False], 2).mean() > 0.04


def brightness_of(image: np.ndarray) -> float:
    mask = image.sum(axis=-1) > 0.1
    return float(image[mask].mean())


# ------------------------------------------------------------------ checkpoint, CLI, the default path


def test_checkpoint_round_trip_with_pose_and_exposure(tmp_path):
    frames = views(scene(), 6)
    cfg = TrainConfig(iterations=30, densify_from=10, densify_until=30, densify_interval=10, init_points=1500,
                      sh_degree=0, pose_opt=True, exposure_opt=True)
    full = Trainer(frames[:5], cfg, frames[5:])
    full.train(30, progress=False, eval_every=15)
    part = Trainer(frames[:5], cfg, frames[5:])
    part.train(15, progress=False, eval_every=15)
    ck = part.save_checkpoint(tmp_path / "run.ckpt")
    resumed = Trainer(frames[:5], cfg, frames[5:])
    resumed.load_checkpoint(ck)
    torch.testing.assert_close(resumed.state.pose.values, part.state.pose.values, rtol=0, atol=0)
    resumed.train(30, progress=False, eval_every=15)
    for name, v in full.state.params.items():
        torch.testing.assert_close(resumed.state.params[name], v, rtol=0, atol=0)
    for name in ("pose", "exposure"):
        a, b = getattr(full.state, name), getattr(resumed.state, name)
        for key in ("values", "exp_avg", "exp_avg_sq", "steps"):
            torch.testing.assert_close(getattr(b, key), getattr(a, key), rtol=0, atol=0)
    assert float(full.state.pose.values.abs().max()) > 0 and float(full.state.exposure.values.abs().max()) > 0
    assert [r["iteration"] for r in resumed.state.correction_history] == [15, 15, 30, 30]
    # a checkpoint with corrections does not load into a run without them, nor the reverse
    with pytest.raises(ValueError, match="pose corrections present"):
        Trainer(frames[:5], TrainConfig(init_points=1500, exposure_opt=True), frames[5:]).load_checkpoint(ck)
    plain = Trainer(frames[:5], TrainConfig(init_points=1500), frames[5:])
    plain.save_checkpoint(tmp_path / "plain.ckpt")
    with pytest.raises(ValueError, match="missing"):
        Trainer(frames[:5], cfg, frames[5:]).load_checkpoint(tmp_path / "plain.ckpt")


def head_step(self: Trainer) -> tuple[float, float]:
    """``Trainer.step`` as it was before pose and exposure optimisation (commit bf99c0f), verbatim."""
    cfg, st = self.config, self.state
    it = st.step + 1
    view = self._next_view()
    frame, target = self.frames[view], self.targets[view]
    p = st.params
    for v in p.values():
        v.requires_grad_(True)
        v.grad = None
    sh = torch.cat([p["sh_dc"], p["sh_rest"]], dim=1)
    out = render_torch(p["means"], p["quats"], p["log_scales"], p["opacity_logits"], sh, frame.camera,
                       cfg.background, sh_degree=st.sh_active, near_m=cfg.near_m)
    loss = train_loss(out.rgb, target)
    loss.backward()
    with torch.no_grad():
        idx = torch.from_numpy(out.index)
        if out.means2d.grad is not None and len(idx):
            k = frame.camera.intrinsics
            g = out.means2d.grad * torch.tensor([0.5 * k.width, 0.5 * k.height])
            st.grad_accum.index_add_(0, idx, g.norm(dim=1))
            st.grad_count.index_add_(0, idx, torch.ones(len(idx)))
            st.max_radius[idx] = torch.maximum(st.max_radius[idx],
                                               torch.from_numpy(out.radius_px.astype(np.float32)))
        st.last_seen[idx] = it
        self._adam(it)
        mse = float(((out.rgb.clamp(0, 1) - target) ** 2).mean())
    st.step = it
    if it % cfg.sh_increase_interval == 0 and st.sh_active < cfg.sh_degree:
        st.sh_active += 1
    if cfg.densify_from <= it <= cfg.densify_until and it % cfg.densify_interval == 0:
        self.densify_and_prune(it)
    if it % cfg.opacity_reset_interval == 0 and it <= cfg.densify_until:
        self.reset_opacity()
    return float(loss.detach()), -10.0 * math.log10(max(mse, 1e-10))


@pytest.mark.parametrize("depth", [True, False])
def test_options_off_leave_training_bit_identical(tmp_path, depth):
    """With pose and exposure optimisation off (the defaults) there is no new state, the checkpoint holds the
    keys it held before, and 20 steps (densifying at 10 and 20) of the torch engine equal 20 steps of the step as
    it was (the fused engine, the default, has its own tests: test_fused.py)."""
    frames = views(scene(), 6, depth=depth)
    cfg = TrainConfig(iterations=20, densify_from=10, densify_until=20, densify_interval=10, init_points=1500,
                      sh_degree=1, sh_increase_interval=10, engine="torch")
    new, old = Trainer(frames, cfg), Trainer(frames, cfg)
    assert new.state.pose is None and new.state.exposure is None and new.init_source == ("depth" if depth else
                                                                                          "random")
    for _ in range(20):
        loss_new, psnr_new = new.step()
        loss_old, psnr_old = head_step(old)
        assert (loss_new, psnr_new) == (loss_old, psnr_old)
    for name, v in old.state.params.items():
        torch.testing.assert_close(new.state.params[name], v, rtol=0, atol=0)
    ck = torch.load(new.save_checkpoint(tmp_path / "c.ckpt"), weights_only=True)
    assert set(ck) == {"config", "params", "exp_avg", "exp_avg_sq", "step", "grad_accum", "grad_count",
                       "max_radius", "last_seen", "sh_active", "history", "rng", "torch_rng", "extent", "perm"}
    assert new.training_cameras() == [f.camera for f in new.frames] and new.corrections_summary() == {}


def test_frame_corrections_update_one_row_and_hold_the_mean():
    table = FrameCorrections.zeros(4, POSE_DIM)
    table.adam_update(2, torch.tensor([1.0, -1.0, 0.0, 2.0, 0.0, -3.0], dtype=torch.float64), lr=0.01)
    # first Adam step: lr × sign(g) on the row's non-zero entries, nothing elsewhere
    np.testing.assert_allclose(table.values[2].numpy(), [-0.01, 0.01, 0.0, -0.01, 0.0, 0.01])
    assert float(table.values[[0, 1, 3]].abs().max()) == 0.0 and table.steps.tolist() == [0, 0, 1, 0]
    table.remove_mean()
    np.testing.assert_allclose(table.values.mean(dim=0).numpy(), 0.0, atol=1e-18)
    np.testing.assert_allclose((table.values[2] - table.values[0]).numpy(), [-0.01, 0.01, 0, -0.01, 0, 0.01])
    assert FrameCorrections.zeros(3, EXPOSURE_DIM).values.shape == (3, 6)


def test_train_cli_new_flags_write_train_json_that_the_survey_reads(tmp_path, capsys):
    model = scene()
    frames = views(model, 8, depth=False)
    for i, f in enumerate(frames):
        f.pose = (0.1 * i, 0.0, 0.0)
    cloud = (model.means.astype(np.float64), np.full((model.num_gaussians, 3), 0.5))
    write_dataset(tmp_path / "ds", frames, point_cloud=cloud)
    out = tmp_path / "m" / "model.ply"
    assert train_main([str(tmp_path / "ds"), "--out", str(out), "--iterations", "20", "--init", "points",
                       "--init-points", "300", "--pose-opt", "--exposure-opt", "--holdout-every", "4",
                       "--sh-degree", "0", "--test-pose-steps", "2", "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "init: points" in text and "pose_delta_max_cm" in text and "test-time pose refinement" in text
    info = json.loads((out.parent / "train.json").read_text())
    assert info["holdout_every"] == 4 and info["train_frames"] == 6 and info["heldout_frames"] == 2
    assert info["heldout_files"] == ["images/frame_00003.png", "images/frame_00007.png"]
    assert len(info["train_files"]) == 6 and info["init"] == "points" and info["iterations"] == 20
    assert info["config"]["pose_opt"] is True and info["config"]["exposure_opt"] is True
    assert math.isfinite(info["heldout_psnr_db"]) and math.isfinite(info["heldout_psnr_test_pose_refined_db"])
    assert {"pose_delta_mean_cm", "pose_delta_max_deg", "exposure_gain_min"} <= set(info["corrections"])
    assert len(info["corrections_per_frame"]) == 6 and "pose_delta_cm" in info["corrections_per_frame"][0]
    split = recorded_split(out)
    assert (split.holdout_every, split.train_frames, split.heldout_frames) == (4, 6, 2)
    # bad combinations are one line on stderr and exit code 2
    assert train_main([str(tmp_path / "ds"), "--out", str(out), "--iterations", "2", "--init", "depth",
                       "--no-progress"]) == 2
    assert "depth" in capsys.readouterr().err
