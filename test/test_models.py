"""The model pipeline's cache (:mod:`gsrmr_sim.models`): what a cached call returns is what was built."""

from __future__ import annotations

import json

import numpy as np

from gsrmr_server.splatting.model import GaussianModel
from gsrmr_sim.models import BuiltModel, ModelRecipe, compact_built


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
