"""Cost of the robot's scene-change test per slot (:class:`gsrmr_robot.scene_change.SceneChangeDetector`).

Usage: ``.venv/bin/python bench/perf/scene_change.py [--repeats 5] [--frames 300] [--width 320 --height 240]``.
Each repeat feeds ``--frames`` uint8 RGB frames (a textured view panning sideways, as when the robot turns, with
sensor noise) through a fresh detector, one call per slot, on one thread. Prints a table: the per-frame time,
median and worst of the repeats, the thumbnail width and the machine's load.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np

from gsrmr_robot.scene_change import SceneChangeDetector


def frames(n: int, width: int, height: int, seed: int = 0) -> list[np.ndarray]:
    """``n`` frames of a blocky panorama panning 3 px a frame, with noise (σ 4 of 255)."""
    rng = np.random.default_rng(seed)
    pano = np.kron(rng.uniform(30, 220, (height // 16 + 1, (width + 3 * n) // 16 + 1, 3)), np.ones((16, 16, 1)))
    return [np.clip(pano[:height, 3 * k:3 * k + width] + rng.normal(0, 4, (height, width, 3)), 0, 255)
            .astype(np.uint8) for k in range(n)]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    args = ap.parse_args()
    clip = frames(args.frames, args.width, args.height)
    per_frame_ms = []
    for _ in range(args.repeats):
        det = SceneChangeDetector()
        t0 = time.perf_counter()
        for stamp, frame in enumerate(clip):
            det.update(frame, stamp)
        per_frame_ms.append(1e3 * (time.perf_counter() - t0) / len(clip))
    print(f"# bench/perf/scene_change.py: {args.repeats} repeats × {args.frames} frames of {args.width}×{args.height}, "
          f"thumbnail {det.thumbnail_width_px} px, shifts ±{det._max_shift_x}/±{det._max_shift_y} px "
          f"({os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}); changes found in the last repeat: "
          f"{det.changes}")
    print("| ms per frame, median | worst |")
    print("|---|---|")
    print(f"| {statistics.median(per_frame_ms):.2f} | {max(per_frame_ms):.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
