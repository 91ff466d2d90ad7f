"""gsrmr_offline/change_confirmation.py: an update learns a change two rounds saw, not one only one round saw."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gsrmr_common.camera import Intrinsics
from gsrmr_offline.change_confirmation import ConfirmConfig, confirm_changes
from gsrmr_splat.datasets import orbit_cameras, render_views
from gsrmr_splat.model import GaussianModel
from gsrmr_splat.render import render
from gsrmr_splat.sh import C0


def _cloud(n: int, centre, half_m: float, colour, seed: int) -> GaussianModel:
    rng = np.random.default_rng(seed)
    means = np.asarray(centre, np.float64) + rng.uniform(-half_m, half_m, (n, 3))
    sh = np.broadcast_to((np.asarray(colour, np.float64) - 0.5) / C0, (n, 1, 3)).copy()
    sh += rng.normal(0.0, 0.3, sh.shape)
    return GaussianModel(means, rng.normal(size=(n, 4)), np.log(rng.uniform(0.03, 0.06, (n, 3))), np.full(n, 2.0), sh)


def _joined(*models: GaussianModel) -> GaussianModel:
    return GaussianModel(*(np.concatenate([getattr(m, k) for m in models])
                           for k in ("means", "quats", "log_scales", "opacity_logits", "sh")))


@pytest.fixture(scope="module")
def rounds():
    """The model (a cloud), the world after a persistent change (a red box beside it, in both rounds) and a transient
    (a blue box on the other side, in round 0's frames only); two rounds of nearby views of both sides."""
    model = _cloud(500, (0.0, 0.0, 0.0), 0.35, (0.5, 0.5, 0.5), 0)
    persistent = _cloud(150, (0.0, 0.45, 0.0), 0.08, (0.9, 0.1, 0.1), 1)
    transient = _cloud(150, (0.0, -0.45, 0.0), 0.08, (0.1, 0.2, 0.9), 2)
    k = Intrinsics.from_fov(80, 60, math.radians(60))
    cams = orbit_cameras(24, k, radius_m=1.5, heights_m=(0.3, 0.35), target_m=(0.0, 0.0, 0.0))
    round0 = render_views(_joined(model, persistent, transient), cams[0::2], with_depth=False)
    round1 = render_views(_joined(model, persistent), cams[1::2], with_depth=False)  # 15° apart from round 0's
    truth_no_transient = render_views(_joined(model, persistent), cams[0::2], with_depth=False)
    truth_model = render_views(model, cams[0::2], with_depth=False)
    return model, round0, round1, truth_no_transient, truth_model


def test_a_change_two_rounds_saw_is_kept_and_one_only_one_round_saw_is_left_to_the_model(rounds):
    model, round0, round1, no_transient, model_views = rounds
    frames = round0 + round1
    cfg = ConfirmConfig(cell_px=4, threshold=0.08, near_m=0.5, near_deg=30.0)
    out = confirm_changes(model, frames, [0] * len(round0) + [1] * len(round1), (0.0, 0.0, 0.0), cfg)
    assert out.changed_cells > 0 and 0 < out.confirmed_cells < out.changed_cells
    transient_px = persistent_px = replaced_transient = kept_persistent = 0
    for f, new, clean, old in zip(round0, out.frames, no_transient, model_views, strict=False):
        transient = np.abs(f.image - clean.image).max(axis=2) > 0.1  # where only the transient differs
        persistent = (np.abs(clean.image - old.image).max(axis=2) > 0.1) & ~transient
        replaced = np.any(new.image != f.image, axis=2)
        transient_px += int(transient.sum())
        persistent_px += int(persistent.sum())
        replaced_transient += int((replaced & transient).sum())
        kept_persistent += int((~replaced & persistent).sum())
    assert transient_px > 200 and persistent_px > 200
    assert replaced_transient > 0.8 * transient_px, (replaced_transient, transient_px)  # not learned
    assert kept_persistent > 0.8 * persistent_px, (kept_persistent, persistent_px)  # learned
    # where replaced, a frame shows the model's render: the fine-tune has nothing to learn there
    f, new = round0[0], out.frames[0]
    replaced = np.any(new.image != f.image, axis=2)
    assert replaced.any()
    np.testing.assert_allclose(new.image[replaced], np.clip(render(model, f.camera).rgb, 0, 1)[replaced], atol=1e-6)


def test_one_round_alone_confirms_nothing_and_an_unchanged_frame_is_passed_on_as_is(rounds):
    model, round0, _, _, model_views = rounds
    out = confirm_changes(model, round0, [0] * len(round0), (0.0, 0.0, 0.0), ConfirmConfig(cell_px=4))
    assert out.changed_cells > 0 and out.confirmed_cells == 0
    same = confirm_changes(model, model_views[:3], [0, 1, 2], (0.0, 0.0, 0.0), ConfirmConfig(cell_px=4))
    assert same.changed_cells == 0 and all(a is b for a, b in zip(same.frames, model_views[:3], strict=True))
    with pytest.raises(ValueError, match="round indices"):
        confirm_changes(model, round0, [0], (0.0, 0.0, 0.0))
    for bad in ({"cell_px": 0}, {"threshold": 0.0}, {"threshold": math.nan}, {"near_deg": 200.0}):
        with pytest.raises(ValueError):
            ConfirmConfig(**bad)
