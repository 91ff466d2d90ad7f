"""Hindsight, after a ``gsrmr-demo --rounds N [--update]`` run: what each model version learned, against the
simulator's truth and against what the robot sent (issue 27; docs/results.md, "The memory learns … after the collapse
fix"). No live component sees any of this: it is computed after the run, from its report folder.

1. **Against the truth, at the true camera:** each version's render along a headless lap of the world of the mapping
   round (the static world: no event) and of scored round ``--round`` (its events), PSNR per window of the lap
   (``--windows`` equal spans of the slots) and pooled (``gsrmr_sim.rounds.model_psnr_now_db``'s figure).
2. **Against what the robot sent, at its pose keys:** the PSNR of each version on the received frames of round
   ``--round`` (``gsrmr-dataset`` of its ``run.mcap``, made here when missing; never trained on by a version made
   before that round's end), split into the frames inside the scene's transient events' time spans (walkers,
   flickers: ``from_s``…``to_s`` from the round's first slot, plus ``--margin-s``) and those outside.

A version that burned a transient in gains inside the spans and loses outside; one fitted to the pose keys gains at
the keys everywhere while it loses at the true camera.

    .venv/bin/python bench/acceptance/rounds_truth.py RUN_DIR --scene sandbox_transient --versions 0,3 [--round 4]
                                           [--windows 12] [--margin-s 0.5]

Renders at the scene's camera resolution (320×240 for the sandbox), background the scene's; units: dB.
"""

from __future__ import annotations

import argparse
import csv
import math
from pathlib import Path
import subprocess
import sys

import numpy as np

from gsrmr_common.nerfstudio import read_dataset
from gsrmr_sim.machine_probe import machine_line
from gsrmr_sim.rounds import worlds_cache
from gsrmr_sim.world.recorder import Round2Record, record_round2
from gsrmr_sim.world.scene import Scene, load_scene
from gsrmr_splat.model import GaussianModel
from gsrmr_splat.render import render


def psnr_db(rgb: np.ndarray, truth: np.ndarray) -> float:
    """PSNR of two images in [0, 1] (dB, MSE floored at 1e-12)."""
    return float(10.0 * math.log10(1.0 / max(float(np.mean((np.clip(rgb, 0, 1) - truth) ** 2)), 1e-12)))


def world_record(scene: Scene, world_round: int, slots: int, cache: Path) -> Round2Record:
    """The headless lap of world round ``world_round`` (1 = the mapping round), cached in ``cache``."""
    folder = cache / f"world_round{world_round}_{slots}"
    if not (folder / "index.json").exists():
        record_round2(scene, folder, slots=slots, round_index=world_round)
    return Round2Record(folder)


def truth_windows(model: GaussianModel, record: Round2Record, background: np.ndarray, windows: int
                  ) -> tuple[list[float], float]:
    """(mean PSNR per window of the lap, pooled PSNR over the lap) of ``model`` at the true cameras."""
    per_slot, sq_err, n = [], 0.0, 0
    for t in range(len(record)):
        slot = record[t]
        rgb = np.clip(render(model, slot.camera, background=background).rgb, 0.0, 1.0)
        per_slot.append(psnr_db(rgb, slot.image))
        sq_err += float(np.sum((rgb - slot.image) ** 2))
        n += slot.image.size
    spans = np.array_split(np.asarray(per_slot), windows)
    return [float(s.mean()) for s in spans], float(10.0 * math.log10(1.0 / max(sq_err / n, 1e-12)))


def received_dataset(run_dir: Path, k: int) -> Path:
    """Round ``k``'s received frames as a dataset (``gsrmr-dataset`` as ``gsrmr_sim.rounds`` makes it)."""
    out = run_dir / f"received_round{k}"
    if not (out / "transforms.json").exists():
        rec = run_dir / f"round{k}"
        exe = Path(sys.executable).parent / "gsrmr-dataset"
        subprocess.run([str(exe), str(rec / "recording" / "run.mcap"), "--out", str(out),
                        "--image-topic", "/gsrmr/received/image/compressed", "--camera-info-topic",
                        "/gsrmr/camera_info", "--pose-topic", "/gsrmr/received/pose", "--camera-mount",
                        str(rec / "params" / "gsrmr_server.yaml"), "--blur-ratio", "0", "--min-translation-m", "0",
                        "--min-rotation-deg", "0"], check=True, stdout=subprocess.DEVNULL)
    return out


def transient_spans(scene: Scene, margin_s: float, scored_round: int) -> list[tuple[float, float]]:
    """The scene's transient events' time spans in scored round ``scored_round`` (s from the round's first slot; each
    shifted by its ``round_shift_s``), widened by ``margin_s``."""
    spans = [ev.span_s(scored_round) for ev in scene.events if not ev.from_round and math.isfinite(ev.to_s)]
    return [(a - margin_s, b + margin_s) for a, b in spans]


def _mean(values: list[float]) -> str:
    return f"{np.mean(values):.2f}" if values else "–"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run_dir", type=Path, help="the --out folder of gsrmr-demo --rounds N")
    ap.add_argument("--scene", required=True)
    ap.add_argument("--versions", default="0", help="comma-separated model versions (models/model_vN.ply)")
    ap.add_argument("--round", type=int, default=4, help="the scored round whose world and received frames are used")
    ap.add_argument("--windows", type=int, default=12)
    ap.add_argument("--margin-s", type=float, default=0.5)
    ap.add_argument("--slots", type=int, default=0, help="slots of the headless lap (0 = the scene's)")
    ap.add_argument("--cache", type=Path, default=Path(".cache/gsrmr"))
    args = ap.parse_args()
    scene = load_scene(args.scene)
    slots = args.slots or scene.slots
    background = np.asarray(scene.background, np.float32)
    versions = [int(v) for v in args.versions.split(",")]
    models = {v: GaussianModel.load_ply(str(args.run_dir / "models" / f"model_v{v}.ply")) for v in versions}
    cache = worlds_cache(args.cache, args.scene)
    print(f"# bench/acceptance/rounds_truth.py {args.run_dir} --scene {args.scene} --round {args.round} (hindsight; "
          f"before: {machine_line()} (gsrmr_sim.machine_probe))")
    print(f"\n## Against the truth at the true camera: PSNR per {args.windows} windows of the lap, pooled\n")
    print("| world | version | " + " | ".join(f"w{i + 1}" for i in range(args.windows)) + " | pooled |")
    print("|---|---|" + "---|" * (args.windows + 1))
    for label, world_round in (("static (mapping round)", 1), (f"scored round {args.round}", args.round + 1)):
        record = world_record(scene, world_round, slots, cache)
        for v, model in models.items():
            per, pooled = truth_windows(model, record, background, args.windows)
            print(f"| {label} | v{v} | " + " | ".join(f"{p:.1f}" for p in per) + f" | {pooled:.2f} |", flush=True)
    spans = transient_spans(scene, args.margin_s, args.round)
    dataset = received_dataset(args.run_dir, args.round)
    frames = read_dataset(dataset)
    with open(dataset / "frames.csv") as f:
        rows = [r for r in csv.DictReader(f) if r["status"] == "kept"]
    with open(args.run_dir / f"round{args.round}" / "slots.csv") as f:
        t0_s = float(next(csv.DictReader(f))["stamp_s"])
    inside = [any(a <= float(r["stamp_s"]) - t0_s <= b for a, b in spans) for r in rows]
    print(f"\n## Against round {args.round}'s received frames at their pose keys (transient spans "
          f"{', '.join(f'{a:g}–{b:g} s' for a, b in spans) or 'none'})\n")
    print("| version | inside: frames | PSNR | outside: frames | PSNR |")
    print("|---|---|---|---|---|")
    for v, model in models.items():
        vals = [psnr_db(render(model, f.camera, background=background).rgb, f.image) for f in frames]
        ins = [p for p, i in zip(vals, inside, strict=True) if i]
        outs = [p for p, i in zip(vals, inside, strict=True) if not i]
        print(f"| v{v} | {len(ins)} | {_mean(ins)} | {len(outs)} | {_mean(outs)} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
