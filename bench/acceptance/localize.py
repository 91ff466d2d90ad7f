"""``gsrmr-localize`` on a dataset whose every pose was moved by a fixed offset: how many frames come back.

Usage: ``.venv/bin/python bench/acceptance/localize.py [--model M.ply] [--dataset DS] [--offsets 5:2,15:5] [--seed 0]
[--planar] [--background R,G,B]``.
Defaults: the ``gsrmr-demo`` cache's sandbox model and mapping round (``.cache/gsrmr/sandbox-*/``; run ``make demo``
once) and config/server.yaml's background. For each offset (cm:deg) every frame's camera is moved by that distance in
a seeded random direction and turned by that angle about a seeded random axis; ``gsrmr-localize`` (the console script,
as a user runs it) refines the copy, and the result is compared with the dataset's own poses. Prints per offset:
frames, accepted, the share within 1 cm and 0.3°, the median and p90 errors, and the seconds per frame (median and
worst, from ``localize.csv``).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
from pathlib import Path
import shutil
import subprocess
import sys
import tempfile

import cv2
import numpy as np

from gsrmr_sim.machine_probe import machine_line

SANDBOX_BACKGROUND = "0.5,0.55,0.6"  # config/server.yaml's background_rgb


def cached_inputs(cache: Path) -> tuple[Path, Path]:
    """The newest cached sandbox model and its mapping round."""
    models = sorted(cache.glob("sandbox-*/model-compact-0.3.ply"), key=lambda p: p.stat().st_mtime)
    if not models:
        raise SystemExit(f"no cached sandbox model under {cache}: run `make demo` once, or pass --model/--dataset")
    return models[-1], models[-1].parent / "round1"


def perturb(src: Path, dst: Path, dist_m: float, angle_deg: float, seed: int) -> None:
    """``src`` copied to ``dst`` with every frame's camera moved by ``dist_m`` and turned by ``angle_deg`` (seeded
    random direction and axis; nerfstudio's camera → world in the dataset's units)."""
    shutil.copytree(src, dst)
    meta = json.loads((dst / "transforms.json").read_text())
    rng = np.random.default_rng(seed)
    for frame in meta["frames"]:
        c2w = np.asarray(frame["transform_matrix"], float)
        direction = rng.normal(size=3)
        axis = rng.normal(size=3)
        c2w[:3, 3] += direction / np.linalg.norm(direction) * dist_m
        c2w[:3, :3] = cv2.Rodrigues(axis / np.linalg.norm(axis) * math.radians(angle_deg))[0] @ c2w[:3, :3]
        frame["transform_matrix"] = c2w.tolist()
    (dst / "transforms.json").write_text(json.dumps(meta, indent=1))


def errors(truth: Path, refined: Path) -> tuple[np.ndarray, np.ndarray]:
    """Per frame: camera centre error (dataset units) and rotation error (deg) of ``refined`` against ``truth``."""
    a = json.loads((truth / "transforms.json").read_text())["frames"]
    b = json.loads((refined / "transforms.json").read_text())["frames"]
    e_m, e_deg = [], []
    for fa, fb in zip(a, b, strict=True):
        ma, mb = np.asarray(fa["transform_matrix"]), np.asarray(fb["transform_matrix"])
        e_m.append(float(np.linalg.norm(ma[:3, 3] - mb[:3, 3])))
        r = ma[:3, :3].T @ mb[:3, :3]
        e_deg.append(math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(r) - 1) / 2)))))
    return np.array(e_m), np.array(e_deg)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", type=Path)
    ap.add_argument("--dataset", type=Path)
    ap.add_argument("--cache", type=Path, default=Path(".cache/gsrmr"))
    ap.add_argument("--offsets", default="5:2,15:5", help="cm:deg, comma-separated")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--planar", action="store_true", help="gsrmr-localize --planar (x, y, yaw; needs gsrmr_pose)")
    ap.add_argument("--background", default=SANDBOX_BACKGROUND)
    args = ap.parse_args()
    model, dataset = (args.model, args.dataset) if args.model and args.dataset else cached_inputs(args.cache)
    exe = Path(sys.executable).parent / "gsrmr-localize"
    print(f"# bench/acceptance/localize.py: {model} on {dataset}, seed {args.seed}, "
          f"{'planar' if args.planar else '6 DoF'} ({machine_line()})", flush=True)
    print("| offset | frames | accepted | within 1 cm & 0.3° | median cm | median ° | p90 cm | p90 ° | s/frame median "
          "| s/frame worst |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for item in args.offsets.split(","):
        cm, deg = (float(v) for v in item.split(":"))
        with tempfile.TemporaryDirectory(prefix="gsrmr-localize-bench-") as tmp:
            moved, out = Path(tmp) / "moved", Path(tmp) / "out"
            perturb(dataset, moved, cm / 100.0, deg, args.seed)
            cmd = [str(exe), str(model), str(moved), "--out", str(out), "--background", args.background]
            subprocess.run(cmd + (["--planar"] if args.planar else []), check=True, stdout=subprocess.DEVNULL)
            e_m, e_deg = errors(dataset, out)
            with open(out / "localize.csv", newline="") as f:
                rows = list(csv.DictReader(f))
        seconds = [float(r["seconds"]) for r in rows]
        accepted = sum(r["status"] == "accepted" for r in rows)
        within = float(np.mean((e_m < 0.01) & (e_deg < 0.3)))
        print(f"| {cm:g} cm / {deg:g}° | {len(e_m)} | {accepted} | {100 * within:.1f} % | {100 * np.median(e_m):.2f} "
              f"| {np.median(e_deg):.3f} | {100 * np.percentile(e_m, 90):.2f} | {np.percentile(e_deg, 90):.3f} "
              f"| {np.median(seconds):.2f} | {max(seconds):.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
