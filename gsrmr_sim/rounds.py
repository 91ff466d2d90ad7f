"""``gsrmr-demo --rounds N [--update]``: N scored rounds, the model learning between them.

Round 0 is the mapping round (:mod:`gsrmr_sim.demo`'s model and seed map); scored rounds 1…N are each a whole
closed loop in the world as it is in that round, with one channel seed. With ``--update`` the operator's procedure
of docs/model_update.md runs between rounds on what the server received, each step the deployment's own command
line (never the simulator's truth): step 1 ``gsrmr-dataset`` of the round's ``run.mcap``, step 2 ``gsrmr-update``
(the mapping round's training frames as the replay buffer), step 3 ``gsrmr-survey`` of the model in use on
:func:`survey_frames` (the next round's seed map). The rounds and their summary: docs/model_update.md, "In the
simulation".
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
import json
from pathlib import Path
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np

from gsrmr_common.nerfstudio import holdout_split, read_dataset, write_dataset
from gsrmr_offline.model_update import UpdateConfig, split_received, superseded
from gsrmr_sim.report import log
from gsrmr_sim.world.recorder import Round2Record, record_round2
from gsrmr_sim.world.scene import Scene, load_scene, scene_digest
from gsrmr_splat.model import GaussianModel
from gsrmr_splat.render import render

#: the mock camera's node name (the ``round`` parameter set per scored round)
CAMERA_NODE = "gsrmr_mock_camera"
#: the live model's held-out split of the mapping round (gsrmr_sim.models.ModelRecipe.holdout_every)
MAPPING_HOLDOUT_EVERY = 8
#: what a round's summary line keeps (its ``rounds`` list)
ROUND_KEYS = ("energy_j", "images_sent", "mean_loss", "regret", "slots_on_time", "slots")


def round_overrides(overrides: dict[str, dict], scored_round: int) -> dict[str, dict]:
    """``overrides`` with the mock camera in the world of scored round ``scored_round`` (its ``round`` k + 1)."""
    out = {node: dict(values) for node, values in overrides.items()}
    out.setdefault(CAMERA_NODE, {})["round"] = scored_round + 1
    return out


def _cli(name: str) -> str:
    """The console script ``name`` of this environment (beside the interpreter), else as found on PATH."""
    beside = Path(sys.executable).parent / name
    return str(beside) if beside.exists() else name


def run_measured(argv: Sequence[str], log_path: Path) -> tuple[str, float]:
    """Run a command to completion (stdout and stderr to ``log_path``); its last stdout line and the CPU seconds
    (user + system) it and its children spent. Raises RuntimeError with the log's tail when it fails."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    with open(log_path, "w") as out:
        proc = subprocess.run(list(argv), stdout=subprocess.PIPE, stderr=out, text=True, check=False)
        out.write(proc.stdout)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu_s = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if proc.returncode != 0:
        raise RuntimeError(f"{Path(argv[0]).name} failed ({proc.returncode}): "
                           f"{log_path.read_text()[-1500:]}")
    lines = [line for line in proc.stdout.splitlines() if line.strip()]
    return (lines[-1] if lines else ""), cpu_s


def composition_arguments(run_dir: Path, scene: Scene) -> list[str]:
    """``gsrmr-update``'s and ``gsrmr-survey``'s composition options as the round's server and scheduler ran
    (their parameter files in ``<run_dir>/params``: camera mount, route) and the scene's MR content and background."""
    return ["--camera-mount", str(run_dir / "params" / "gsrmr_server.yaml"),
            "--route-file", str(run_dir / "params" / "gsrmr_scheduler.yaml"),
            "--mr-content", scene.mr_content or scene.name,
            "--background", ",".join(f"{c:g}" for c in scene.background)]


def update_between_rounds(*, models_dir: Path, init_model: Path, mapping_dataset: Path, recordings: Sequence[Path],
                          work_dir: Path, composition: Sequence[str]) -> dict:
    """Steps 1–3 of the module docstring after the last of ``recordings`` (each a round's ``recording`` folder,
    oldest first; its round's parameter files beside it in ``params``): returns ``gsrmr-update``'s JSON record plus
    ``loss_map`` (the next round's seed map), ``update_cpu_s`` (every step's CPU) and ``wall_s``. ``composition``:
    :func:`composition_arguments`."""
    work_dir.mkdir(parents=True, exist_ok=True)
    t0, cpu_s = time.perf_counter(), 0.0
    received: list[Path] = []
    for i, recording in enumerate(recordings, start=1):
        dataset = work_dir.parent / f"received_round{i}"
        if not (dataset / "transforms.json").exists():  # made once, after its round
            _, cpu = run_measured([_cli("gsrmr-dataset"), str(recording / "run.mcap"), "--out", str(dataset),
                                   "--image-topic", "/gsrmr/received/image/compressed",
                                   "--camera-info-topic", "/gsrmr/camera_info", "--pose-topic", "/gsrmr/received/pose",
                                   "--camera-mount", str(recording.parent / "params" / "gsrmr_server.yaml"),
                                   "--blur-ratio", "0",
                                   "--min-translation-m", "0", "--min-rotation-deg", "0"],
                                  work_dir / f"dataset_round{i}.log")
            cpu_s += cpu
        received.append(dataset)
    replay_set = work_dir.parent / "mapping_train"  # the replay buffer: the mapping frames the model trained on
    if not (replay_set / "transforms.json").exists():
        write_dataset(replay_set, holdout_split(read_dataset(mapping_dataset), MAPPING_HOLDOUT_EVERY)[0])
    line, cpu = run_measured([_cli("gsrmr-update"), str(models_dir), "--init", str(init_model), "--received",
                              *map(str, received), "--mapping", str(replay_set), *composition],
                             work_dir / "update.log")
    cpu_s += cpu
    record = json.loads(line)
    loss_map = work_dir / f"loss_map_{Path(record['model']).stem}.json"
    survey_set = survey_frames(mapping_dataset, received[-1], work_dir / "survey_frames")
    _, cpu = run_measured([_cli("gsrmr-survey"), str(record["model"]), str(survey_set), "--all-frames", "--out",
                           str(loss_map), *composition], work_dir / "survey.log")
    cpu_s += cpu
    return {**record, "loss_map": str(loss_map), "update_cpu_s": round(cpu_s, 2),
            "wall_s": round(time.perf_counter() - t0, 2)}


def survey_frames(mapping_dataset: Path, received_dataset: Path, out_dir: Path,
                  holdout_every: int = MAPPING_HOLDOUT_EVERY) -> Path:
    """The frames the next seed map is surveyed on, as a dataset in ``out_dir``: the mapping round's held-out frames
    (every ``holdout_every``-th, never trained on) that no frame of the round supersedes (a received camera within
    0.3 m and 30°: the old view shows the world before a change) and the round's most recent received frames, the
    ones the update held out (the world as it is now, never trained on)."""
    config = UpdateConfig()
    _, held_mapping = holdout_split(read_dataset(mapping_dataset), holdout_every)
    received = read_dataset(received_dataset)
    stale = superseded(held_mapping, received, config.supersede_m, config.supersede_deg)
    _, held_received = split_received(received, config.holdout_frames)
    frames = [f for f, old in zip(held_mapping, stale, strict=True) if not old] + held_received
    write_dataset(out_dir, frames)
    return out_dir


def worlds_cache(cache_root: Path, scene_name: str) -> Path:
    """The folder the headless laps of ``scene_name``'s rounds are cached in (keyed by the scene file's digest)."""
    return Path(cache_root) / f"worlds-{scene_name}-{scene_digest(scene_name)}"


def model_psnr_now_db(model: GaussianModel, scene: Scene, scored_round: int, slots: int,
                      cache_dir: Path | None = None) -> float:
    """PSNR (dB, pooled over the lap) of ``model``'s render against the world of scored round ``scored_round`` at
    the ``slots`` slot poses of a headless lap (the simulator's truth: a figure for the report, after the round)."""
    folder = (cache_dir / f"world_round{scored_round + 1}_{slots}") if cache_dir is not None else None
    if folder is None or not (folder / "index.json").exists():
        folder = record_round2(scene, folder or Path(tempfile.mkdtemp(prefix="gsrmr-world-")), slots=slots,
                               round_index=scored_round + 1)
    record = Round2Record(folder)
    background = np.asarray(scene.background, np.float32)
    sq_err, n = 0.0, 0
    for t in range(len(record)):
        slot = record[t]
        rgb = render(model, slot.camera, background=background).rgb
        sq_err += float(np.sum((np.clip(rgb, 0.0, 1.0) - slot.image) ** 2))
        n += slot.image.size
    return float(10.0 * np.log10(1.0 / max(sq_err / n, 1e-12)))


def version_of(model_path: Path) -> int:
    """``model_v3.ply`` → 3; the mapping round's model (any other name) → 0."""
    stem = model_path.stem
    return int(stem.split("_v", 1)[1]) if stem.startswith("model_v") and stem.split("_v", 1)[1].isdigit() else 0


def run_rounds(args: argparse.Namespace, *, scene_name: str, slots: int, slot_s: float, model: Path, loss_map: Path,
               mapping_dataset: Path, out: Path, run_round: Callable[..., dict], cache_dir: Path) -> list[dict]:
    """Scored rounds 1…``args.rounds`` (module docstring). ``run_round(round_k, model, loss_map, run_dir,
    overrides)`` runs one round and returns its summary (``gsrmr_sim.demo``'s); returns the per-round records."""
    scene = load_scene(scene_name)
    models_dir = out / "models"
    rounds: list[dict] = []
    recordings: list[Path] = []
    update: dict | None = None
    init_model = model  # version 0 of the models folder
    for k in range(1, args.rounds + 1):
        run_dir = out / f"round{k}"
        log(f"round {k} of {args.rounds}: model {model.name} (version {version_of(model)}), loss map {loss_map.name}")
        summary = run_round(k, model, loss_map, run_dir, round_overrides(args.overrides, k))
        recordings.append(run_dir / "recording")
        psnr_now = model_psnr_now_db(GaussianModel.load_ply(str(model)), scene, k, slots, cache_dir)
        record = {"round": k, **{key: summary.get(key) for key in ROUND_KEYS}, "model_version": version_of(model),
                  "model_psnr_now_db": round(psnr_now, 3),
                  "update_cpu_s": 0.0 if update is None else update["update_cpu_s"],
                  "update": None if update is None else {key: update.get(key) for key in (
                      "version", "accepted", "reason", "heldout_loss_before", "heldout_loss_after",
                      "finetune_cpu_s", "compact_cpu_s", "wall_s")},
                  "report_dir": str(run_dir)}
        rounds.append(record)
        log(f"round {k}: {record['images_sent']} images, {record['energy_j']:.4g} J, mean loss "
            f"{record['mean_loss']:.4f}, regret {record['regret']:.2f}, on time {record['slots_on_time']}/"
            f"{record['slots']}; the model against this round's world {psnr_now:.2f} dB")
        if args.update and k < args.rounds:
            log(f"update after round {k} (the robot stopped): gsrmr-dataset, gsrmr-update, gsrmr-survey")
            update = update_between_rounds(models_dir=models_dir, init_model=init_model,
                                           mapping_dataset=mapping_dataset, recordings=recordings,
                                           work_dir=out / f"update{k}",
                                           composition=composition_arguments(run_dir, scene))
            log(f"update {k}: version {update['version']} {'accepted' if update['accepted'] else 'refused'} "
                f"({update['reason']}); held-out loss {update['heldout_loss_before']:.4f} → "
                f"{update['heldout_loss_after']:.4f}; {update['update_cpu_s']:.0f} CPU-s "
                f"({update['wall_s']:.0f} s wall)")
            model, loss_map = Path(update["model"]), Path(update["loss_map"])
    return rounds

