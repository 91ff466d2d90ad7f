"""The model update between rounds (gsrmr_offline/model_update.py): the split, the replay buffer, the paired verdict,
the versions, and one update on a small scene whose world changed (accepted) or did not (refused)."""

from __future__ import annotations

from dataclasses import replace
import json
import math

import numpy as np
import pytest

from gsrmr_common.camera import Camera, Intrinsics
from gsrmr_common.metrics import mr_loss
from gsrmr_offline.model_update import (
    UpdateConfig,
    in_use,
    paired_verdict,
    read_version,
    replay_buffer,
    split_received,
    superseded,
    update_model,
    version_paths,
    versions,
    write_version,
)
from gsrmr_splat.datasets import look_at, orbit_cameras, render_views
from gsrmr_splat.model import GaussianModel
from gsrmr_splat.render import render
from gsrmr_splat.sh import C0
from gsrmr_splat.train import TrainConfig


def test_the_most_recent_frames_are_held_out_and_the_replay_spans_the_mapping_round():
    frames = list(range(10))
    assert split_received(frames, 3) == (list(range(7)), [7, 8, 9])
    assert split_received(frames, 30) == ([], frames) and split_received(frames, 0) == (frames, [])
    assert replay_buffer(list(range(100)), 5) == [0, 25, 50, 74, 99]  # evenly spaced, both ends
    assert replay_buffer(frames, 50) == frames and replay_buffer(frames, 0) == [] == replay_buffer([], 3)
    assert replay_buffer(list(range(100)), 5) == replay_buffer(list(range(100)), 5)  # the same every time


def test_a_received_view_supersedes_the_mapping_frame_of_the_same_view_only(worlds):
    _, _, mapping, cams = worlds
    from gsrmr_common.nerfstudio import DatasetFrame

    same = [DatasetFrame(mapping[3].camera, mapping[3].image)]
    stale = superseded(mapping, same, 0.3, 30.0)
    assert stale[3] and stale.sum() == 1  # its neighbours on the circle are 0.37 m away
    assert not superseded(mapping, same, 0.0, 30.0)[2] and superseded(mapping, [], 0.3, 30.0).sum() == 0
    half = superseded(mapping, [DatasetFrame(c, mapping[0].image) for c in cams], 0.3, 30.0)
    ys = np.array([f.camera.camera_to_world[1, 3] for f in mapping])
    assert half[ys > 0.2].all() and not half[ys < -0.2].any()  # the round saw one half again


def test_the_verdict_needs_a_significant_paired_improvement():
    before = [0.030, 0.031, 0.029, 0.032, 0.030, 0.031, 0.030, 0.029]
    better = [b - 0.004 + 0.0005 * (i % 2) for i, b in enumerate(before)]
    v = paired_verdict(before, better)
    assert v.accepted and v.frames == 8 and v.improvement == pytest.approx(0.00375)
    assert "more than 2 standard errors" in v.reason
    noisy = [b + d for b, d in zip(before, (-0.01, 0.009, -0.008, 0.01, -0.009, 0.008, -0.01, 0.0095), strict=True)]
    refused = paired_verdict(before, noisy)  # lower on average, but by less than its spread
    assert not refused.accepted and "not a significant improvement" in refused.reason
    worse = paired_verdict(before, [b + 0.002 for b in before])
    assert not worse.accepted and "not lower" in worse.reason
    few = paired_verdict(before[:4], better[:4], min_frames=6)
    assert not few.accepted and "only 4 held-out frames" in few.reason
    with_nan = paired_verdict([*before, math.nan], [*better, 0.01])
    assert with_nan.frames == 8 and with_nan.accepted  # an unscored frame counts on neither side
    assert json.dumps(few.as_dict(), allow_nan=False)  # NaN → null
    with pytest.raises(ValueError, match="the same frames"):
        paired_verdict(before, better[:3])
    with pytest.raises(ValueError):
        UpdateConfig(holdout_frames=4, min_holdout_frames=6)


def _scene(n: int = 400, seed: int = 0) -> GaussianModel:
    rng = np.random.default_rng(seed)
    means = rng.uniform(-0.4, 0.4, (n, 3))
    sh = (rng.uniform(0, 1, (n, 1, 3)) - 0.5) / C0
    scales = np.log(rng.uniform(0.03, 0.08, (n, 3)))
    return GaussianModel(means, rng.normal(size=(n, 4)), scales, np.full(n, 2.0), sh)


def _score(model: GaussianModel, frames) -> list[float]:
    """The MR loss of the model's render against each frame (no MR content: the whole image is real)."""
    return [mr_loss(f.image, render(model, f.camera).rgb) for f in frames]


@pytest.fixture(scope="module")
def worlds():
    """The mapping round's world (the current model is exact there) and the world after a persistent change: the
    Gaussians on one side of the scene recoloured."""
    before = _scene()
    after = GaussianModel(before.means.copy(), before.quats.copy(), before.scales.copy(), before.opacity_logits.copy(),
                          before.sh.copy())
    side = before.means[:, 0] > 0.1
    after.sh[side, 0, :] = (np.array([0.9, 0.2, 0.1]) - 0.5) / C0
    k = Intrinsics.from_fov(40, 30, math.radians(60))
    mapping = render_views(before, orbit_cameras(24, k, radius_m=1.4, heights_m=(0.3, 0.6), target_m=(0, 0, 0)),
                           with_depth=False)
    # the round's views: one half of the circle (y > 0), so the other half's mapping frames stay in the replay
    round_cams = [c for c in orbit_cameras(60, k, radius_m=1.3, heights_m=(0.4, 0.5), target_m=(0, 0, 0))
                  if c.camera_to_world[1, 3] > 0.0]
    return before, after, mapping, round_cams


_FAST = UpdateConfig(holdout_frames=8, min_holdout_frames=6, replay_frames=48, finetune_steps=300, compact=False)
_TRAIN = TrainConfig(sh_degree=0, checkpoint_every=0)


def test_an_update_learns_a_persistent_change_and_is_accepted(worlds):
    current, changed, mapping, cams = worlds
    received = render_views(changed, cams, with_depth=False)
    lines: list[str] = []
    result = update_model(current, received, mapping, _score, _TRAIN, _FAST, log=lines.append)
    v = result.verdict
    assert result.heldout_frames == 8 and result.train_frames == len(received) - 8
    assert 0 < result.superseded_frames < len(mapping)
    assert result.replay_frames == len(mapping) - result.superseded_frames
    assert v.accepted and v.loss_after < 0.85 * v.loss_before, v.reason  # seen: 0.365 → 0.272 (3DGS colour rate)
    assert result.finetune_cpu_s > 0 and result.compact_cpu_s == 0.0
    assert any("accepted" in line for line in lines)


def test_an_update_from_an_unchanged_world_is_refused_and_says_why(worlds):
    current, _, mapping, cams = worlds
    received = render_views(current, cams, with_depth=False)  # nothing to learn: the model is the world
    result = update_model(current, received, mapping, _score, _TRAIN, _FAST)
    assert not result.verdict.accepted and "not" in result.verdict.reason


def _shifted(model: GaussianModel, offset_m) -> GaussianModel:
    return GaussianModel(model.means + np.asarray(offset_m), model.quats, model.log_scales, model.opacity_logits,
                         model.sh)


def _joined(a: GaussianModel, b: GaussianModel) -> GaussianModel:
    return GaussianModel(*(np.concatenate([getattr(a, k), getattr(b, k)])
                           for k in ("means", "quats", "log_scales", "opacity_logits", "sh")))


def test_an_update_keeps_what_its_training_views_do_not_see():
    """Two objects 3 m apart; the round's views see one (recoloured: the update learns), the mapping round also saw
    the other and none of its frames is replayed. The fine-tune and its compaction must not prune the unseen object
    (they once emptied every view an update did not train on: a sandbox update fell from 30.2 to 16.2 dB held out)."""
    seen, unseen = _shifted(_scene(200, 1), (0.0, 1.5, 0.0)), _shifted(_scene(200, 2), (0.0, -1.5, 0.0))
    current = _joined(seen, unseen)
    changed = _joined(GaussianModel(seen.means, seen.quats, seen.log_scales, seen.opacity_logits,
                                    np.full_like(seen.sh, (0.8 - 0.5) / C0)), unseen)
    k = Intrinsics.from_fov(40, 30, math.radians(60))

    def facing(target_y: float, eye_y: float, n: int) -> list[Camera]:
        return [Camera(k, look_at(np.array([x, eye_y, 0.3 + 0.1 * (i % 2)]), np.array([0.0, target_y, 0.0])))
                for i, x in enumerate(np.linspace(-0.5, 0.5, n))]

    received = render_views(changed, facing(1.5, 0.4, 20), with_depth=False)  # the other object behind the camera
    far = render_views(current, facing(-1.5, -0.4, 12), with_depth=False)
    assert not superseded(far, received, 0.3, 30.0).any()
    for compact in (False, True):
        cfg = replace(_FAST, replay_frames=0, compact=compact)
        result = update_model(current, received, far, _score, _TRAIN, cfg)
        assert result.replay_frames == 0 and result.verdict.accepted, result.verdict.reason
        before, after = np.mean(_score(current, far)), np.mean(_score(result.model, far))
        assert after < before + 0.01, (compact, before, after, result.gaussians_after)


def test_versions_are_numbered_recorded_and_the_newest_accepted_is_in_use(tmp_path, worlds):
    model = worlds[0]
    assert versions(tmp_path) == [] and in_use(tmp_path) is None
    assert write_version(tmp_path, model, {"parent": None, "accepted": True, "reason": "the mapping round"}) == 0
    assert write_version(tmp_path, model, {"parent": 0, "accepted": True, "reason": "better"}) == 1
    assert write_version(tmp_path, model, {"parent": 1, "accepted": False, "reason": "not better"}) == 2
    assert versions(tmp_path) == [0, 1, 2] and in_use(tmp_path) == 1
    record = read_version(tmp_path, 2)
    assert record["parent"] == 1 and record["gaussians"] == model.num_gaussians and record["version"] == 2
    ply, _ = version_paths(tmp_path, 1)
    assert GaussianModel.load_ply(ply).num_gaussians == model.num_gaussians
    assert not list(tmp_path.glob("*.tmp.*"))


def test_update_cli_writes_a_version_and_names_the_model_to_use(tmp_path, worlds, capsys):
    """gsrmr-update on datasets as gsrmr-dataset writes them (frames with gsrmr_pose): version 0 from --init, then
    an accepted update from a changed world (the model to use is the new one) and a refused one from the same
    frames again (the model to use stays)."""
    from gsrmr_common.nerfstudio import DatasetFrame, write_dataset
    from gsrmr_offline.update_cli import main

    current, changed, mapping, cams = worlds
    posed = [DatasetFrame(f.camera, f.image, None, (float(f.camera.camera_to_world[0, 3]),
                                                     float(f.camera.camera_to_world[1, 3]), 0.0), f.file_path)
             for f in mapping]
    write_dataset(tmp_path / "mapping", posed)
    received = [DatasetFrame(f.camera, f.image, None, (float(f.camera.camera_to_world[0, 3]),
                                                       float(f.camera.camera_to_world[1, 3]), 0.0), f.file_path)
                for f in render_views(changed, cams, with_depth=False)]
    # two rounds of neighbouring views (each confirms the other's changes); round 2 ends with the 8 held out
    write_dataset(tmp_path / "round1", received[:-8:2])
    write_dataset(tmp_path / "round2", received[1:-8:2] + received[-8:])
    current.save_ply(tmp_path / "mapping.ply")
    args = ["--received", str(tmp_path / "round1"), str(tmp_path / "round2"), "--mapping", str(tmp_path / "mapping"),
            "--steps", "300",
            "--holdout", "8", "--no-compact", "--width", "40", "--train-width", "40", "--background", "0,0,0",
            "--render-threads", "1"]
    models = tmp_path / "models"
    assert main([str(models), *args]) == 2  # no version yet and no --init
    assert "start it with --init" in capsys.readouterr().err
    assert main([str(models), "--init", str(tmp_path / "mapping.ply"), *args]) == 0
    first = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert first["version"] == 1 and first["parent"] == 0 and first["accepted"], first["reason"]
    assert first["heldout_loss_after"] < first["heldout_loss_before"] and first["model"].endswith("model_v1.ply")
    confirmation = first["confirmation"]  # the change is in both rounds: confirmed, learned
    assert confirmation["confirmed_cells"] > 0.5 * confirmation["changed_cells"] > 0, confirmation
    assert read_version(models, 0)["accepted"] and in_use(models) == 1
    changed.save_ply(tmp_path / "exact.ply")  # a model that is the world already: nothing to learn
    exact = tmp_path / "exact_models"
    assert main([str(exact), "--init", str(tmp_path / "exact.ply"), *args]) == 0
    second = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert second["version"] == 1 and not second["accepted"] and "not" in second["reason"]
    assert second["model"].endswith("model_v0.ply") and in_use(exact) == 0  # the refused one is kept, not used
    assert read_version(exact, 1)["accepted"] is False


def test_the_trainer_refuses_frames_without_their_images(worlds):
    """A dataset read without its images (0×0 placeholders) trained to an empty model and then failed deep in the
    fused engine (found writing gsrmr-update); now the trainer says so up front."""
    from gsrmr_common.nerfstudio import DatasetFrame
    from gsrmr_splat.train import Trainer

    current, _, mapping, _ = worlds
    blind = [DatasetFrame(f.camera, np.zeros((0, 0, 3), np.float32), None, None, f.file_path) for f in mapping]
    with pytest.raises(ValueError, match="were the images loaded"):
        Trainer(blind, _TRAIN, initial_model=current)
