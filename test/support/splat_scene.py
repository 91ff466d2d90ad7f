"""A small random Gaussian scene and its rendered views (the training tests' data set), shared by the splatting
training tests and the model-cache tests."""

from __future__ import annotations

import math

import numpy as np

from gsrmr_common.camera import Intrinsics
from gsrmr_splat.datasets import orbit_cameras, render_views
from gsrmr_splat.model import GaussianModel
from gsrmr_splat.sh import C0


def small_scene(n: int = 300, seed: int = 0) -> GaussianModel:
    rng = np.random.default_rng(seed)
    means = rng.uniform(-0.4, 0.4, (n, 3))
    sh = ((rng.uniform(0, 1, (n, 1, 3)) - 0.5) / C0)
    return GaussianModel(means, rng.normal(size=(n, 4)), np.log(rng.uniform(0.02, 0.08, (n, 3))),
                         rng.normal(1, 1, n), sh)


def small_frames(n_views: int = 10, w: int = 48, h: int = 36, depth: bool = True):
    cams = orbit_cameras(n_views, Intrinsics.from_fov(w, h, math.radians(60)), radius_m=1.4,
                         heights_m=(0.3, 0.6), target_m=(0.0, 0.0, 0.0))
    return render_views(small_scene(), cams, with_depth=depth)
