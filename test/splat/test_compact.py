"""Compaction: contribution ranking, the tolerance it keeps, fine-tuning from a model, and gsrmr-compact."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from gsrmr_common.camera import Intrinsics
from gsrmr_common.metrics import psnr
from gsrmr_common.nerfstudio import holdout_split, read_dataset, write_dataset
from gsrmr_splat.cli import render_main
from gsrmr_splat.compact import CompactConfig, Compactor
from gsrmr_splat.contribution import blend_weights, max_blend_weight
from gsrmr_splat.datasets import orbit_cameras, render_views
from gsrmr_splat.model import GaussianModel
from gsrmr_splat.sh import C0
from gsrmr_splat.train import TrainConfig, Trainer
from gsrmr_splat.train_cli import compact_main, train_main


def scene(n: int = 600, seed: int = 0) -> GaussianModel:
    """A ground-truth scene with a few large Gaussians that carry most of the image and many faint ones."""
    rng = np.random.default_rng(seed)
    means = rng.uniform(-0.4, 0.4, (n, 3))
    sh = (rng.uniform(0, 1, (n, 1, 3)) - 0.5) / C0
    scales = np.log(rng.uniform(0.02, 0.08, (n, 3)))
    opacity_logits = np.where(rng.uniform(size=n) < 0.3, 2.0, -4.0)  # 30 % opaque, the rest nearly clear
    return GaussianModel(means, rng.normal(size=(n, 4)), scales, opacity_logits, sh)


@pytest.fixture(scope="module")
def views():
    cams = orbit_cameras(16, Intrinsics.from_fov(48, 36, math.radians(60)), radius_m=1.4, heights_m=(0.3, 0.6),
                         target_m=(0.0, 0.0, 0.0))
    truth = scene()
    return truth, holdout_split(render_views(truth, cams, with_depth=False), 4)


def test_blend_weights_sum_bounds_the_max_and_matches_the_pruning_rule(views):
    truth, (train, _) = views
    cams = [f.camera for f in train]
    total, best = blend_weights(truth, cams)
    assert total.shape == best.shape == (truth.num_gaussians,)
    assert np.all(total >= best - 1e-12) and np.all(best <= 0.99 + 1e-12)
    np.testing.assert_array_equal(best, max_blend_weight(truth, cams))
    far = truth.subset(np.arange(10))
    far.means[:] += 100.0  # behind / outside every view
    assert np.all(blend_weights(far, cams)[0] == 0.0)
    opaque = 1 / (1 + np.exp(-truth.opacity_logits)) > 0.5
    assert np.median(total[opaque]) > 10 * np.median(total[~opaque])  # the ranking sees who carries the image


def test_pruning_by_contribution_beats_pruning_at_random(views):
    """Keep the 40 % that contribute most vs a random 40 %: the ranking must be worth something."""
    truth, (train, test) = views
    comp = Compactor(train, test, TrainConfig(sh_degree=0), CompactConfig(finetune_iterations=0))
    total, _ = blend_weights(truth, [f.camera for f in train])
    k = int(0.4 * truth.num_gaussians)
    ranked = truth.subset(np.sort(np.argsort(total)[-k:]))
    random = truth.subset(np.sort(np.random.default_rng(1).choice(truth.num_gaussians, k, replace=False)))
    assert comp.evaluate(ranked) > comp.evaluate(random) + 3.0


@pytest.fixture(scope="module")
def trained(views):
    """A briefly trained SH-degree-1 model of the scene (the scene's colour is view-independent)."""
    _, (train, test) = views
    cfg = TrainConfig(iterations=200, init_points=2000, sh_degree=1, sh_increase_interval=50, densify_from=50,
                      densify_until=150, densify_interval=50, checkpoint_every=0)
    tr = Trainer(train, cfg, test)
    return tr.train(progress=False)


def test_compaction_keeps_the_tolerance_and_lowers_sh_that_does_not_pay(views, trained):
    _, (train, test) = views
    comp = Compactor(train, test, TrainConfig(sh_degree=1), CompactConfig(max_psnr_drop_db=0.5,
                                                                          finetune_iterations=30))
    result = comp.run(trained)
    assert result.gaussians_before == trained.num_gaussians and result.sh_degree_before == 1
    assert result.gaussians_after < trained.num_gaussians and result.sh_degree_after == 0
    assert result.heldout_psnr_after_db >= result.heldout_psnr_before_db - 0.5
    assert comp.evaluate(result.model) == pytest.approx(result.heldout_psnr_after_db, abs=1e-9)  # as reported
    rejected = [s for s in result.steps if not s.accepted]
    assert all(s.heldout_psnr_db < result.heldout_psnr_before_db - 0.5 for s in rejected)
    strict = Compactor(train, test, TrainConfig(sh_degree=1),
                       CompactConfig(max_psnr_drop_db=0.0, finetune_iterations=0, lower_sh=False)).run(trained)
    assert strict.heldout_psnr_after_db >= strict.heldout_psnr_before_db  # never below the model it started from


def test_finetuning_from_a_model_adds_no_gaussians_and_keeps_its_degree(views, trained):
    _, (train, test) = views
    cfg = TrainConfig(iterations=10, densify_from=10_000, sh_degree=1, opacity_reset_interval=10**9)
    tr = Trainer(train, cfg, test, initial_model=trained)
    assert tr.state.sh_active == 1 and tr.num_gaussians == trained.num_gaussians
    tr.train(progress=False)  # no densification; the final pass drops only what changes no pixel
    out = tr.model()
    assert out.num_gaussians <= trained.num_gaussians and out.sh_degree == 1
    assert np.all(max_blend_weight(out, [f.camera for f in tr.frames]) >= 1 / 255)


def test_compact_cli_prints_its_figures_as_json_and_writes_a_3dgs_ply(tmp_path, capsys):
    cams = orbit_cameras(12, Intrinsics.from_fov(48, 36, math.radians(60)), radius_m=1.4, heights_m=(0.3, 0.6),
                         target_m=(0.0, 0.0, 0.0))
    write_dataset(tmp_path / "ds", render_views(scene(), cams, with_depth=True))
    full = tmp_path / "full.ply"
    assert train_main([str(tmp_path / "ds"), "--out", str(full), "--iterations", "60", "--init-points", "1500",
                       "--holdout-every", "6", "--no-progress", "--sh-degree", "1"]) == 0
    small = tmp_path / "small.ply"
    assert compact_main([str(full), str(tmp_path / "ds"), "--out", str(small), "--holdout-every", "6",
                         "--finetune-iterations", "10", "--max-psnr-drop-db", "0.3"]) == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    figures = json.loads(last)
    assert {"gaussians_before", "gaussians_after", "sh_degree_after", "heldout_psnr_before_db",
            "heldout_psnr_after_db"} <= set(figures)
    out = GaussianModel.load_ply(small)
    assert out.num_gaussians == figures["gaussians_after"] <= figures["gaussians_before"]
    assert out.sh_degree == figures["sh_degree_after"]
    assert figures["heldout_psnr_after_db"] >= figures["heldout_psnr_before_db"] - 0.3
    # What it reports is what gsrmr-render + gsrmr_common.metrics measure on the .ply (within 0.1 dB): the
    # held-out views (every 6th frame of the dataset) rendered by the CLI as 8-bit PNGs.
    _, held_out = holdout_split(read_dataset(tmp_path / "ds"), 6)
    for name, key in ((full, "heldout_psnr_before_db"), (small, "heldout_psnr_after_db")):
        spec = [{"width": f.camera.width, "height": f.camera.height, "K": f.camera.intrinsics.k().tolist(),
                 "world_to_camera": f.camera.world_to_camera.tolist()} for f in held_out]
        (tmp_path / "cams.json").write_text(json.dumps(spec))
        out_dir = tmp_path / f"render_{name.stem}"
        assert render_main([str(name), "--cameras", str(tmp_path / "cams.json"), "--out", str(out_dir)]) == 0
        measured = [psnr(cv2.cvtColor(cv2.imread(str(out_dir / f"{i:03d}.png")), cv2.COLOR_BGR2RGB) / 255.0, f.image)
                    for i, f in enumerate(held_out)]
        assert float(np.mean(measured)) == pytest.approx(figures[key], abs=0.1), (key, measured)
    assert compact_main([str(full), str(tmp_path / "ds"), "--out", str(small), "--holdout-every", "0"]) == 2
    assert train_main([str(tmp_path / "ds"), "--out", str(full), "--max-psnr-drop-db", "0.3"]) == 2  # no held-out
