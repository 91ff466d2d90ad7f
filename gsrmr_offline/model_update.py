"""Between rounds the model learns from what the robot paid to send (pure, no ROS): :func:`update_model` holds out the
round's most recent received frames, fine-tunes the model in use on the others plus a replay buffer of the mapping
round (learning only the changes another round confirms), compacts it again, validates it on the held-out frames
(:func:`paired_verdict`) and :func:`write_version` writes it. The steps and why: docs/model_update.md, "3. Update".
Losses are the MR loss 0.8·L1 + 0.2·(1 − SSIM) of images in [0, 1]; times are CPU seconds of this process.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
import json
import math
from pathlib import Path
import re
import time

import numpy as np

from gsrmr_common.nerfstudio import DatasetFrame
from gsrmr_offline.change_confirmation import ConfirmConfig, confirm_changes
from gsrmr_splat.compact import CompactConfig, Compactor
from gsrmr_splat.model import GaussianModel
from gsrmr_splat.train import TrainConfig, Trainer

#: ``model_v<N>.ply`` / ``model_v<N>.json`` in a models folder.
VERSION_RE = re.compile(r"^model_v(\d+)\.ply$")

#: Scores a model on frames: one MR loss per frame, in order (lower is better).
Scorer = Callable[[GaussianModel, Sequence[DatasetFrame]], Sequence[float]]


@dataclass(frozen=True)
class UpdateConfig:
    """How an update trains and decides (docs/model_update.md, "3. Update")."""

    holdout_frames: int = 16  # the round's most recent received frames, held out to validate
    min_holdout_frames: int = 6  # fewer held out: no verdict (refused)
    replay_frames: int = 48  # mapping-round frames trained beside the received ones
    supersede_m: float = 0.3  # a received frame this close (camera centre) …
    supersede_deg: float = 30.0  # … and looking this nearly the same way supersedes a mapping frame
    finetune_steps: int = 600  # fine-tuning steps of the current model
    growth: float = 0.5  # densification adds at most this share of the current model's Gaussians
    significance_z: float = 2.0  # the mean improvement must exceed this many standard errors
    compact: bool = True  # compact the fine-tuned model again
    max_psnr_drop_db: float = 0.3  # compaction's tolerance on the held-out frames
    confirm_changes: bool = True  # learn a change only where another round's frame saw it too
    confirm: ConfirmConfig = field(default_factory=ConfirmConfig)
    seed: int = 0

    def __post_init__(self) -> None:
        if self.min_holdout_frames < 2 or self.holdout_frames < self.min_holdout_frames:
            raise ValueError("update: need 2 ≤ min_holdout_frames ≤ holdout_frames (a verdict needs a spread)")
        if self.replay_frames < 0 or self.finetune_steps < 1:
            raise ValueError("update: replay_frames ≥ 0 and finetune_steps ≥ 1")
        if not (math.isfinite(self.growth) and self.growth >= 0):
            raise ValueError("update: growth must be a finite number ≥ 0")
        if not (self.supersede_m >= 0 and 0 <= self.supersede_deg <= 180):
            raise ValueError("update: supersede_m ≥ 0 and supersede_deg in [0, 180]")
        if not (math.isfinite(self.significance_z) and self.significance_z >= 0):
            raise ValueError("update: significance_z must be a finite number ≥ 0")


@dataclass(frozen=True)
class Verdict:
    """The paired comparison of the old and the new model on the same held-out frames."""

    accepted: bool
    reason: str
    frames: int
    loss_before: float  # mean MR loss of the old model
    loss_after: float  # … of the new one
    improvement: float  # mean of (before − after) per frame
    stderr: float  # its standard error

    def as_dict(self) -> dict:
        """JSON-able (NaN → None)."""
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in self.__dict__.items()}


@dataclass
class UpdateResult:
    """What an update made: the candidate model, its verdict, the frames it used and what it cost."""

    model: GaussianModel
    verdict: Verdict
    train_frames: int
    replay_frames: int
    superseded_frames: int
    heldout_frames: int
    finetune_cpu_s: float  # confirmation included
    compact_cpu_s: float
    gaussians_before: int
    gaussians_after: int
    notes: list[str] = field(default_factory=list)
    confirmation: dict | None = None  # changed / confirmed cells (None: not run)


def split_received(frames: Sequence[DatasetFrame], holdout: int) -> tuple[list[DatasetFrame], list[DatasetFrame]]:
    """(train, held out): the last ``holdout`` frames (the most recent, in recording order) held out."""
    frames = list(frames)
    n = max(0, min(int(holdout), len(frames)))
    return frames[:len(frames) - n], frames[len(frames) - n:]


def superseded(mapping: Sequence[DatasetFrame], received: Sequence[DatasetFrame], distance_m: float,
               angle_deg: float) -> np.ndarray:
    """For each mapping frame: whether some received frame's camera is within ``distance_m`` of its camera centre
    and its optical axis within ``angle_deg`` of its own (the same view, seen later)."""
    if not mapping:
        return np.zeros(0, bool)
    if not received:
        return np.zeros(len(mapping), bool)
    centres_m = np.array([f.camera.camera_to_world[:3, 3] for f in mapping])
    axes = np.array([f.camera.camera_to_world[:3, 2] for f in mapping])  # OpenCV: +z looks forward
    rx_centres_m = np.array([f.camera.camera_to_world[:3, 3] for f in received])
    rx_axes = np.array([f.camera.camera_to_world[:3, 2] for f in received])
    near = np.linalg.norm(centres_m[:, None, :] - rx_centres_m[None, :, :], axis=2) <= distance_m
    aligned = axes @ rx_axes.T >= math.cos(math.radians(angle_deg))
    return np.any(near & aligned, axis=1)


def replay_buffer(frames: Sequence[DatasetFrame], n: int) -> list[DatasetFrame]:
    """At most ``n`` of ``frames``, evenly spaced over them (first and last included; deterministic)."""
    frames = list(frames)
    if n <= 0 or not frames:
        return []
    if n >= len(frames):
        return frames
    picks = np.unique(np.round(np.linspace(0, len(frames) - 1, n)).astype(int))
    return [frames[i] for i in picks]


def paired_verdict(before: Sequence[float], after: Sequence[float], *, significance_z: float = 2.0,
                   min_frames: int = 6) -> Verdict:
    """Accept the new model when its per-frame losses ``after`` are lower than ``before`` (same frames, same order)
    by more than ``significance_z`` standard errors of the differences, on at least ``min_frames`` finite pairs."""
    b, a = np.asarray(before, np.float64), np.asarray(after, np.float64)
    if b.shape != a.shape:
        raise ValueError(f"{b.size} losses before, {a.size} after: the same frames must be scored")
    ok = np.isfinite(b) & np.isfinite(a)
    b, a = b[ok], a[ok]
    n = int(b.size)
    if n < max(2, min_frames):
        return Verdict(False, f"only {n} held-out frames scored (at least {min_frames} needed for a verdict)", n,
                       float(b.mean()) if n else math.nan, float(a.mean()) if n else math.nan, math.nan, math.nan)
    diff = b - a
    gain, se = float(diff.mean()), float(diff.std(ddof=1) / math.sqrt(n))
    before_m, after_m = float(b.mean()), float(a.mean())
    margin = significance_z * se
    if gain > margin and gain > 0.0:
        reason = (f"held-out MR loss {before_m:.5f} → {after_m:.5f} on {n} frames: lower by {gain:.5f}, more than "
                  f"{significance_z:g} standard errors ({margin:.5f})")
        return Verdict(True, reason, n, before_m, after_m, gain, se)
    change = "lower" if gain > 0 else "not lower"
    reason = (f"held-out MR loss {before_m:.5f} → {after_m:.5f} on {n} frames: {change} by {gain:.5f}, within "
              f"{significance_z:g} standard errors ({margin:.5f}) — not a significant improvement")
    return Verdict(False, reason, n, before_m, after_m, gain, se)


def update_train_config(base: TrainConfig, steps: int, sh_degree: int, budget: int | None = None) -> TrainConfig:
    """The fine-tuning settings of an update: ``base``'s rates and background, the position rate at its final
    value, the SH degree fixed, no opacity reset; densification from a tenth to two thirds of the ``steps`` (a new
    object needs Gaussians where the model has none) within ``budget`` Gaussians (default ``base``'s); nothing
    pruned for being unseen by the training views (``prune_unseen``, ``final_prune`` off): an update's views show
    part of the scene, and pruning the rest emptied the views it did not train on (a held-out PSNR of 30.2 dB fell
    to 16.2 dB; docs/results.md)."""
    steps = max(1, int(steps))
    return replace(base, iterations=steps, lr_means=base.lr_means_final, sh_degree=sh_degree,
                   sh_increase_interval=10 ** 9, opacity_reset_interval=10 ** 9, checkpoint_every=0,
                   densify_from=max(1, steps // 10), densify_until=max(2, (2 * steps) // 3),
                   budget=base.budget if budget is None else min(base.budget, int(budget)),
                   prune_unseen=False, final_prune=False)


def update_model(current: GaussianModel, received: Sequence[DatasetFrame], mapping: Sequence[DatasetFrame],
                 score: Scorer, train_config: TrainConfig, config: UpdateConfig | None = None,
                 log: Callable[[str], None] = lambda _line: None,
                 received_rounds: Sequence[int] | None = None) -> UpdateResult:
    """One update (docs/model_update.md, "3. Update", steps 1–3): the candidate and its verdict.
    ``received_rounds[i]``: the round received frame ``i`` came from (for the change confirmation; None: not
    confirmed, every received pixel trained on). ValueError when nothing can be trained."""
    cfg = config or UpdateConfig()
    if received_rounds is not None and len(received_rounds) != len(received):
        raise ValueError(f"update: {len(received)} received frames but {len(received_rounds)} round indices")
    train_rx, heldout = split_received(received, cfg.holdout_frames)
    stale = superseded(mapping, train_rx, cfg.supersede_m, cfg.supersede_deg)
    replay = replay_buffer([f for f, old in zip(mapping, stale, strict=True) if not old], cfg.replay_frames)
    cpu0 = time.process_time()
    confirmation = None
    if cfg.confirm_changes and received_rounds is not None and train_rx:
        confirmed = confirm_changes(current, train_rx, list(received_rounds)[:len(train_rx)],
                                    train_config.background, cfg.confirm)
        log(f"update: {confirmed.summary()}")
        train_rx = confirmed.frames
        confirmation = {"cells": confirmed.cells, "changed_cells": confirmed.changed_cells,
                        "confirmed_cells": confirmed.confirmed_cells,
                        "frames_with_changes": confirmed.frames_with_changes}
    train = train_rx + replay
    if not train:
        raise ValueError("update: no frame to train on (no received frame beside the held-out ones, no replay)")
    log(f"update: {len(train_rx)} received frames + {len(replay)} replayed mapping frames to train "
        f"({int(stale.sum())} of {len(mapping)} superseded by a received view), {len(heldout)} received frames held "
        "out")
    tune = update_train_config(train_config, cfg.finetune_steps, current.sh_degree,
                               budget=math.ceil((1.0 + cfg.growth) * current.num_gaussians))
    trainer = Trainer(train, tune, initial_model=current)
    trainer.train(progress=False)
    tuned = trainer.model()
    finetune_cpu_s = time.process_time() - cpu0
    log(f"update: fine-tuned {cfg.finetune_steps} steps ({current.num_gaussians} → {tuned.num_gaussians} "
        f"Gaussians) in {finetune_cpu_s:.1f} CPU s")
    notes: list[str] = []
    compact_cpu_s = 0.0
    candidate = tuned
    if cfg.compact:
        if heldout:
            cpu0 = time.process_time()
            result = Compactor(train, heldout, replace(train_config, prune_unseen=False, final_prune=False),
                               CompactConfig(max_psnr_drop_db=cfg.max_psnr_drop_db),
                               coverage_cameras=[f.camera for f in [*train_rx, *mapping]]).run(tuned)
            candidate, compact_cpu_s = result.model, time.process_time() - cpu0
            log(f"update: compacted {result.gaussians_before} → {result.gaussians_after} Gaussians in "
                f"{compact_cpu_s:.1f} CPU s")
        else:
            notes.append("not compacted: no held-out frame to measure what compaction loses")
    before = list(score(current, heldout)) if heldout else []
    after = list(score(candidate, heldout)) if heldout else []
    verdict = paired_verdict(before, after, significance_z=cfg.significance_z, min_frames=cfg.min_holdout_frames)
    log(f"update: {'accepted' if verdict.accepted else 'refused'}: {verdict.reason}")
    return UpdateResult(candidate, verdict, len(train_rx), len(replay), int(stale.sum()), len(heldout), finetune_cpu_s,
                        compact_cpu_s, current.num_gaussians, candidate.num_gaussians, notes, confirmation)


# ---------------------------------------------------------------------------------------------------- versions
def versions(models_dir: str | Path) -> list[int]:
    """The version numbers in ``models_dir`` (``model_vN.ply``), ascending."""
    folder = Path(models_dir)
    if not folder.is_dir():
        return []
    return sorted(int(m.group(1)) for p in folder.iterdir() if (m := VERSION_RE.match(p.name)))


def version_paths(models_dir: str | Path, version: int) -> tuple[Path, Path]:
    """(``model_vN.ply``, ``model_vN.json``) of ``version`` in ``models_dir``."""
    folder = Path(models_dir)
    return folder / f"model_v{int(version)}.ply", folder / f"model_v{int(version)}.json"


def read_version(models_dir: str | Path, version: int) -> dict:
    """The record of ``version`` (its JSON)."""
    return json.loads(version_paths(models_dir, version)[1].read_text())


def in_use(models_dir: str | Path) -> int | None:
    """The newest accepted version (version 0, the mapping round's model, counts as accepted); None without any."""
    for v in reversed(versions(models_dir)):
        if read_version(models_dir, v).get("accepted", False):
            return v
    return None


def write_version(models_dir: str | Path, model: GaussianModel, record: dict) -> int:
    """Save ``model`` as the next version with ``record`` (plus ``version``, ``gaussians``, ``sh_degree``); the
    ``.ply`` and ``.json`` are written under temporary names and renamed (a crash leaves no half version).
    Returns the version number."""
    folder = Path(models_dir)
    folder.mkdir(parents=True, exist_ok=True)
    version = (versions(folder) or [-1])[-1] + 1
    ply, meta = version_paths(folder, version)
    tmp_ply, tmp_meta = ply.with_name(ply.stem + ".tmp.ply"), meta.with_name(meta.stem + ".tmp.json")
    model.save_ply(tmp_ply)
    tmp_meta.write_text(json.dumps({"version": version, "gaussians": model.num_gaussians,
                                    "sh_degree": model.sh_degree, **record}, indent=1, allow_nan=False))
    tmp_meta.replace(meta)
    tmp_ply.replace(ply)
    return version
