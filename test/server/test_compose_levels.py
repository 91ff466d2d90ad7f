"""The deadline-aware composition levels: the choice from the time left, the learned times, and the composer's
render at a fraction of the size."""

from __future__ import annotations

import math

import numpy as np
import pytest
from support.stack_harness import make_point_model

from gsrmr_common.camera import CameraMount, Intrinsics
from gsrmr_common.jpeg import encode_jpeg
from gsrmr_common.wire import PoseKey, RealSource
from gsrmr_server.compose import MRComposer
from gsrmr_server.compose_levels import LEVEL_NAMES, PRIOR_COST_RATIOS, DeadlineLevels
from gsrmr_server.mr.content import AgentsView, load_mr_content
from gsrmr_server.slot_core import ServerCore
from gsrmr_server.uplink import SlotUploads
from gsrmr_splat.model import GaussianModel


def test_the_best_level_that_fits_is_chosen_and_the_cheapest_when_none_does():
    levels = DeadlineLevels(margin_ms=5.0)
    assert levels.choose(1.0).level == 0  # nothing measured yet: full size (predicted 0)
    levels.observe(0, 40.0)
    assert [levels.predicted_ms(k) for k in range(3)] == pytest.approx([40.0 * r for r in PRIOR_COST_RATIOS])
    assert levels.choose(60.0).name == "full"
    assert levels.choose(44.0).name == "half"  # 40 + 5 > 44 ≥ 28 + 5
    choice = levels.choose(10.0)  # nothing fits: the cheapest, still composed (missing is the last resort)
    assert (choice.name, choice.degraded, choice.render_scale) == ("quarter", True, 0.25)
    assert choice.time_left_ms == 10.0 and choice.predicted_ms == pytest.approx(26.0)
    assert levels.choose(-30.0).level == 2  # already late
    assert DeadlineLevels(max_level=0).choose(-30.0).level == 0  # the selection off: always full size


def test_a_slower_slot_of_one_level_slows_every_level_and_nonsense_is_ignored():
    levels = DeadlineLevels(alpha=0.5)
    levels.observe(0, 40.0)
    levels.observe(1, 18.0)  # its own time replaces the prior (28)
    assert levels.predicted_ms(1) == 18.0 and levels.predicted_ms(0) == 40.0
    levels.observe(1, 36.0)  # the CPU share halved: half's mean 18 → 27 (×1.5), full's follows
    assert levels.predicted_ms(1) == pytest.approx(27.0) and levels.predicted_ms(0) == pytest.approx(60.0)
    for nonsense in (math.nan, -1.0, 0.0, math.inf):
        levels.observe(0, nonsense)
    assert levels.predicted_ms(0) == pytest.approx(60.0)
    with pytest.raises(ValueError):
        DeadlineLevels(alpha=0.0)
    with pytest.raises(ValueError):
        DeadlineLevels(max_level=len(LEVEL_NAMES))


@pytest.fixture(scope="module")
def composer(tmp_path_factory) -> MRComposer:
    model = GaussianModel.load_ply(make_point_model(tmp_path_factory.mktemp("levels") / "m.ply", n=1500, seed=0))
    return MRComposer(model, AgentsView(load_mr_content("sandbox")), Intrinsics.from_fov(64, 48, 1.2),
                      CameraMount(height_m=0.15), (0.5, 0.55, 0.6), render_threads=1)


def test_a_render_at_a_fraction_of_the_size_is_enlarged_to_the_full_size_and_close_to_it(composer):
    key = PoseKey(1, -0.5, -1.1, 0.3)
    full = composer.compose(SlotUploads(1, key=key), None, 0.0)
    for scale, within in ((0.5, 0.08), (0.25, 0.15)):
        small = composer.compose(SlotUploads(1, key=key), None, 0.0, render_scale=scale)
        assert small.mr.shape == full.mr.shape and small.mask.shape == full.mask.shape
        assert small.source == RealSource.RENDER
        assert 0.0 < float(np.abs(small.mr - full.mr).mean()) < within


def test_a_degraded_image_slot_measures_no_loss_sample_and_the_row_says_its_level(composer):
    core = ServerCore(composer)
    jpeg = encode_jpeg(np.random.default_rng(0).integers(0, 255, (48, 64, 3), np.uint8), 80)
    uploads = SlotUploads(3, key=PoseKey(3, -0.5, -1.1, 0.3), jpeg=jpeg)
    levels = DeadlineLevels()
    levels.observe(0, 80.0)
    full, short = levels.choose(95.0), levels.choose(30.0)
    out = core.process(uploads, None, time_s=0.0, stamp_s=0.3, level=full)
    assert (out.row.level, out.row.time_left_ms, out.row.predicted_ms) == (0, 95.0, 80.0)
    assert out.composed.source == RealSource.IMAGE and out.loss_sample is not None
    out = core.process(uploads, None, time_s=0.0, stamp_s=0.3, level=short)
    assert (out.row.level, out.row.time_left_ms) == (2, 30.0) and out.row.predicted_ms == pytest.approx(52.0)
    assert out.composed.source == RealSource.IMAGE and out.loss_sample is None  # shed: a coarse Φ would bias L_t
