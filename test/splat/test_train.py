"""Training path: torch SSIM, a short training run, checkpoint/resume, and the two CLIs."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
from support.splat_scene import small_frames
import torch

from gsrmr_common.camera import CameraMount, Intrinsics, camera_from_pose
from gsrmr_common.metrics import ssim
from gsrmr_common.nerfstudio import write_dataset
from gsrmr_splat.cli import render_main
from gsrmr_splat.datasets import look_at
from gsrmr_splat.model import GaussianModel
from gsrmr_splat.render import render
from gsrmr_splat.train import TrainConfig, Trainer, max_blend_weight, ssim_torch
from gsrmr_splat.train_cli import train_main


@pytest.mark.parametrize("shape", [(40, 30, 3), (23, 57, 1)])
def test_torch_ssim_equals_metrics_ssim(shape):
    rng = np.random.default_rng(0)
    a = rng.uniform(size=shape).astype(np.float32)
    b = np.clip(a + rng.normal(0, 0.2, shape), 0, 1).astype(np.float32)
    got = float(ssim_torch(torch.from_numpy(a).double(), torch.from_numpy(b).double()))
    assert got == pytest.approx(ssim(a, b), abs=1e-5)
    assert float(ssim_torch(torch.from_numpy(a), torch.from_numpy(a))) == pytest.approx(1.0, abs=1e-6)


def test_look_at_uses_opencv_axes():
    w2c = look_at(np.array([0.0, 0, 0]), np.array([1.0, 0, 0]))
    # looking along world +x with z up: camera x (right) = world −y, camera y (down) = world −z
    np.testing.assert_allclose(w2c[:3, :3], [[0, -1, 0], [0, 0, -1], [1, 0, 0]], atol=1e-12)


def test_short_training_reduces_loss_and_resume_is_exact(tmp_path):
    frames = small_frames()
    cfg = TrainConfig(iterations=60, densify_from=20, densify_until=50, densify_interval=20, init_points=2000,
                      sh_degree=1, sh_increase_interval=30, opacity_reset_interval=1000, final_prune=False)
    full = Trainer(frames[:8], cfg, frames[8:])
    psnr0 = full.evaluate()
    losses = [full.step()[0] for _ in range(60)]
    assert np.mean(losses[-10:]) < 0.7 * np.mean(losses[:10])
    assert full.evaluate() > psnr0 + 2.0
    assert full.state.sh_active == 1
    # Same run interrupted at 30 iterations and resumed from the checkpoint in a new Trainer.
    part = Trainer(frames[:8], cfg, frames[8:])
    for _ in range(30):
        part.step()
    ck = part.save_checkpoint(tmp_path / "run.ckpt")
    resumed = Trainer(frames[:8], cfg, frames[8:])
    resumed.load_checkpoint(ck)
    for _ in range(30):
        resumed.step()
    assert resumed.num_gaussians == full.num_gaussians
    for name, v in full.state.params.items():
        torch.testing.assert_close(resumed.state.params[name], v, rtol=0, atol=0)


def test_budget_is_respected_and_unused_gaussians_are_pruned():
    frames = small_frames(depth=False)
    cfg = TrainConfig(iterations=40, densify_from=10, densify_until=40, densify_interval=10, init_points=1500,
                      budget=1700, grad_threshold=1e-7, sh_degree=0)
    tr = Trainer(frames, cfg)
    for _ in range(40):
        tr.step()
        assert tr.num_gaussians <= 1700
    # random init fills a big box: many Gaussians are outside every view or hidden
    weights = max_blend_weight(tr.model(), [f.camera for f in tr.frames])
    n_useless = int(np.sum(weights < 1 / 255))
    before = tr.num_gaussians
    removed = tr.prune_unused()
    assert removed == n_useless > 0 and tr.num_gaussians == before - removed
    assert np.all(max_blend_weight(tr.model(), [f.camera for f in tr.frames]) >= 1 / 255)


def test_train_cli_writes_a_model_that_render_cli_reproduces(tmp_path, capsys):
    frames = small_frames(12)
    write_dataset(tmp_path / "ds", frames)
    out = tmp_path / "model.ply"
    assert train_main([str(tmp_path / "ds"), "--out", str(out), "--iterations", "30", "--init-points", "1500",
                       "--holdout-every", "6", "--no-progress", "--sh-degree", "0", "--resolution", "32"]) == 0
    text = capsys.readouterr().out
    assert "Gaussians" in text and "held-out PSNR" in text
    model = GaussianModel.load_ply(out)
    assert 0 < model.num_gaussians <= 200_000
    # resume continues the saved run
    assert train_main([str(tmp_path / "ds"), "--out", str(out), "--iterations", "40", "--init-points", "1500",
                       "--no-progress", "--resume", "--resolution", "32"]) == 0
    assert " 40 iterations" in capsys.readouterr().out
    cams = [f.camera for f in frames[:2]]
    spec = [{"width": c.width, "height": c.height, "K": c.intrinsics.k().tolist(),
             "world_to_camera": c.world_to_camera.tolist()} for c in cams]
    (tmp_path / "cams.json").write_text(json.dumps(spec))
    assert render_main([str(out), "--cameras", str(tmp_path / "cams.json"), "--out", str(tmp_path / "r")]) == 0
    model = GaussianModel.load_ply(out)
    for i, cam in enumerate(cams):
        png = cv2.cvtColor(cv2.imread(str(tmp_path / "r" / f"{i:03d}.png")), cv2.COLOR_BGR2RGB)
        expect = np.round(render(model, cam).rgb * 255).astype(np.uint8)
        np.testing.assert_array_equal(png, expect)
    assert not (tmp_path / "r" / "002.png").exists()


def test_render_cli_pose_mode_and_errors(tmp_path, capsys):
    model = GaussianModel.from_points(np.array([[2.0, 0.0, 0.2]]), np.array([[1.0, 0.0, 0.0]]), scales_m=0.1,
                                      opacities=0.9)
    model.save_ply(tmp_path / "m.ply")
    args = [str(tmp_path / "m.ply"), "--out", str(tmp_path / "o"), "--pose", "0,0,0", "--pose", "0,0,3.14159",
            "--width", "32", "--height", "24", "--mount-height-m", "0.2", "--mount-forward-m", "0.0"]
    assert render_main(args) == 0
    ahead = cv2.imread(str(tmp_path / "o" / "000.png"))
    behind = cv2.imread(str(tmp_path / "o" / "001.png"))
    assert ahead[12, 16, 2] > 150 and behind.max() == 0  # red blob ahead; nothing when turned around
    mount = CameraMount(height_m=0.2, forward_m=0.0)
    cam = camera_from_pose(0, 0, 0, mount, Intrinsics.from_fov(32, 24, math.radians(70)))
    np.testing.assert_array_equal(cv2.cvtColor(ahead, cv2.COLOR_BGR2RGB),
                                  np.round(render(model, cam).rgb * 255).astype(np.uint8))
    (tmp_path / "bad.json").write_text(json.dumps([{"width": 4, "height": 4, "K": [[1, 0], [0, 1]],
                                                    "world_to_camera": np.eye(4).tolist()}]))
    assert render_main([str(tmp_path / "m.ply"), "--cameras", str(tmp_path / "bad.json"),
                        "--out", str(tmp_path / "x")]) == 2
    assert "camera 0" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        render_main([str(tmp_path / "m.ply"), "--pose", "1,2", "--out", str(tmp_path / "x")])
