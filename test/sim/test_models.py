"""The model pipeline's cache (:mod:`gsrmr_sim.models`): what a cached call returns is what was built."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
from support.splat_scene import small_frames
import torch

from gsrmr_sim.models import BuiltModel, ModelRecipe, compact_built, live_recipe
from gsrmr_sim.world.scene import REPO_SCENES_DIR
from gsrmr_splat.model import GaussianModel
from gsrmr_splat.train import TrainConfig, Trainer


def _points(n: int, seed: int) -> GaussianModel:
    rng = np.random.default_rng(seed)
    return GaussianModel.from_points(rng.uniform(-1, 1, (n, 3)), rng.uniform(0, 1, (n, 3)), scales_m=0.05,
                                     opacities=0.5)


def test_a_cached_compacted_model_is_the_compacted_ply_not_the_trained_one(tmp_path):
    """Regression: a cache hit once returned the compacted model's figures with the *trained* model's path,
    so the live demo rendered the uncompacted model while reporting the compacted count."""
    trained, small = _points(300, 0), _points(40, 1)
    trained.save_ply(tmp_path / "model.ply")
    small.save_ply(tmp_path / "model-compact-0.3.ply")
    (tmp_path / "compact-0.3.json").write_text(json.dumps({"gaussians_after": 40, "heldout_psnr_db": 30.0}))
    built = BuiltModel(trained, tmp_path, {"heldout_psnr_db": 30.2})
    cached = compact_built(built, ModelRecipe(), 0.3, log=lambda _msg: None)
    assert cached.path == tmp_path / "model-compact-0.3.ply"
    assert cached.model.num_gaussians == 40
    assert GaussianModel.load_ply(cached.path).num_gaussians == cached.model.num_gaussians
    assert cached.heldout_psnr_db == 30.0


def test_every_scene_trains_its_live_model_for_a_step_count_not_a_wall_time():
    """The live model (and every figure built on it) must not depend on the machine's load: each scene's recipe
    counts steps, and the learning-rate decay and densification follow that count."""
    scenes = sorted(p.stem for p in REPO_SCENES_DIR.glob("*.yaml"))
    assert "sandbox" in scenes and "garden" in scenes
    for name in scenes:
        recipe = live_recipe(name)
        assert recipe.time_budget_s is None, name
        assert recipe.iterations == recipe.config.iterations and recipe.iterations < 100_000, name
        assert recipe.config.densify_until <= recipe.iterations < recipe.config.opacity_reset_interval, name
    assert live_recipe("sandbox").iterations == 2000  # config/scenes/sandbox.yaml
    assert live_recipe("sandbox", train_seconds=5.0).time_budget_s == 5.0  # a wall time only when asked for


def test_a_step_count_trains_the_same_model_with_a_busy_process_beside_it():
    """Same frames, same config, same seed: bit-identical parameters whether the machine is idle or a busy
    process competes for the cores (numba's parallel kernels split their work in fixed chunks)."""
    frames = small_frames(n_views=6, w=40, h=30)
    cfg = TrainConfig(iterations=30, densify_from=10, densify_until=20, densify_interval=10, init_points=800,
                      sh_degree=0, opacity_reset_interval=1000, seed=3)

    def train() -> dict:
        trainer = Trainer(frames[:5], cfg, frames[5:])
        trainer.train(progress=False)
        return trainer.state.params

    idle = train()
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        loaded = train()
    finally:
        busy.kill()
        busy.wait()
    assert loaded.keys() == idle.keys()
    for name, value in idle.items():
        torch.testing.assert_close(loaded[name], value, rtol=0, atol=0)
