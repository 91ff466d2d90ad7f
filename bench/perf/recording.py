"""Cost of RunRecorder.write_slot per slot (CSV row + JPEG m̂_t + TwistStamped + JSON log) and of close().

    .venv/bin/python bench/perf/recording.py [--slots 300] [--width 320 --height 240] [--repeats 3]
"""

from __future__ import annotations

import argparse
from pathlib import Path
import statistics
import tempfile
import time

import numpy as np

from gsrmr_server.recording import RunRecorder


def run_once(out: Path, slots: int, base: np.ndarray, fsync: bool) -> tuple[float, float, int]:
    """(median ms per write_slot, close() ms, run.mcap bytes) for one recording of ``slots`` slots.

    Every slot gets a fresh noisy image (repeated images would be deduplicated by zstd chunks).
    """
    rng = np.random.default_rng(0)
    per = []
    recorder = RunRecorder(out, fsync=fsync)
    for k in range(slots):
        row = {"slot": k, "stamp_s": 0.1 * k, "x": k % 2, "power_w": 0.1, "bytes_sent": 8000, "energy_j": 1e-3,
               "loss": 0.05, "psnr_db": 30.0, "ssim": 0.95, "source": "image", "pose_a_m": 0.0,
               "pose_b_m": 0.0, "pose_theta_rad": 0.0, "latency_ms": 10.0, "faults": ""}
        image = np.rint(np.clip(base + 0.03 * rng.standard_normal(base.shape), 0, 1) * 255).astype(np.uint8)
        t0 = time.perf_counter()
        recorder.write_slot(row, image, (0.2, 0.1))
        per.append((time.perf_counter() - t0) * 1e3)
    t0 = time.perf_counter()
    path = recorder.close()
    close_ms = (time.perf_counter() - t0) * 1e3
    return statistics.median(per), close_ms, path.stat().st_size if path else 0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--slots", type=int, default=300)
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    v, u = np.mgrid[0:args.height, 0:args.width]
    base = np.stack([u / args.width, v / args.height, 0.5 + 0.5 * np.sin(u / 9.0)], axis=-1)
    print(f"# RunRecorder, {args.slots} slots of {args.width}×{args.height} RGB (JPEG q80), segments of 50 slots;"
          f" medians over {args.repeats} runs")
    print("| fsync per row | write_slot ms (median) | close()+merge ms | run.mcap kB |")
    print("|---|---:|---:|---:|")
    for fsync in (False, True):
        results = []
        for _ in range(args.repeats):
            with tempfile.TemporaryDirectory() as tmp:
                results.append(run_once(Path(tmp) / "run", args.slots, base, fsync))
        med = [statistics.median(c) for c in zip(*results, strict=True)]
        print(f"| {fsync} | {med[0]:.2f} | {med[1]:.0f} | {med[2] / 1e3:.0f} |")


if __name__ == "__main__":
    main()
