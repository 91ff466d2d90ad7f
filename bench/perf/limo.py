"""LIMO driver benchmarks: parser throughput, residual corrupt-frame rate, command latency, and the
issue-5 acceptance run (60 s with 1 % bit flips over a real pty against the mock).

    .venv/bin/python bench/perf/limo.py [--run-s 60] [--repeats 5] [--skip-run]

Tables printed:

1. Parser throughput (pure, clean stream of 0x211/0x221/0x323 frames; median of ``--repeats``).
2. Residual corrupt frames accepted by the parser per fault model (pure simulation, 100 k frame
   triplets; a corrupt frame = accepted bytes not equal to the frame sent):
   per-frame single bit flip (``bit_flip_rate``) vs independent per-byte bit errors
   (``byte_error_rate``), the latter able to create compensating double errors in the data that the
   8-bit additive checksum cannot see.
3. Command latency: ``LimoDriver.set_command`` → the mock has received the matching 0x111 (pty,
   50 Hz streaming; median/p95/max over ``--latency-samples``).
5. Command timeout (table printed before 4): last ``set_command`` → the base stopped, the driver's 0.5 s timeout
   (min/median/max over ``--stop-samples``; the tests only check "never before 0.5 s, and it stops").
4. Acceptance run: ``--run-s`` seconds, ``bit_flip_rate=0.01`` (per frame), 2 m straight line at
   0.25 m/s then arcs until the end: corrupt frames accepted, odometry error at the end of the line
   and at the end of the run.
"""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path
import random
import statistics
import sys
import tempfile
import time

from gsrmr_robot.limo import protocol as p
from gsrmr_robot.limo.driver import LimoDriver
from gsrmr_sim.limo.mock import FaultConfig, MockLimo


def triplet(k: int) -> list[bytes]:
    """One 50 Hz tick of the mock's stream with slowly varying values."""
    yaw = math.remainder(0.01 * k, 2 * math.pi)
    return [p.encode_message(p.SystemState(0, 1, 12.3, 0, 0)),
            p.encode_message(p.MotionState(0.25 + 0.001 * (k % 50), 0.1 * math.sin(k / 100))),
            p.encode_message(p.ImuEuler(yaw))]


def bench_throughput(repeats: int, ticks: int = 20000) -> None:
    data = b"".join(b for k in range(ticks) for b in triplet(k))
    chunk = 64
    rates = []
    for _ in range(repeats):
        parser = p.FrameParser()
        t0 = time.perf_counter()
        n = 0
        for i in range(0, len(data), chunk):
            n += len(parser.feed(data[i:i + chunk], i * 1e-5))
        rates.append((time.perf_counter() - t0, n))
    dt = statistics.median(r[0] for r in rates)
    n = rates[0][1]
    print("\n## 1. Parser throughput (clean stream, 64-byte chunks, median of", repeats, "runs)")
    print("| bytes | frames | time_s | MB/s | frames/s | LIMO link 460800 Bd = frames/s |")
    print("|---|---|---|---|---|---|")
    print(f"| {len(data)} | {n} | {dt:.3f} | {len(data) / dt / 1e6:.2f} | {n / dt:,.0f} | {460800 / 10 / 14:,.0f} |")


def bench_residual(ticks: int = 100_000) -> None:
    print(f"\n## 2. Residual corrupt frames accepted (pure simulation, {3 * ticks} frames, seed 0)")
    print("| fault model | rate | frames corrupted | corrupt accepted | per frame | expected in 60 s (9000 frames) |")
    print("|---|---|---|---|---|---|")
    for model, rate in (("bit_flip_rate (1 bit per hit frame)", 0.01), ("bit_flip_rate (1 bit per hit frame)", 0.2),
                        ("byte_error_rate (independent per byte)", 0.01)):
        rng = random.Random(0)
        parser = p.FrameParser()
        sent, corrupted, bad = set(), 0, 0
        for k in range(ticks):
            buf = bytearray()
            for raw in triplet(k):
                sent.add(raw)
                b = bytearray(raw)
                if model.startswith("bit") and rng.random() < rate:
                    bit = rng.randrange(8 * len(b))
                    b[bit // 8] ^= 1 << (bit % 8)
                elif model.startswith("byte"):
                    for i in range(len(b)):
                        if rng.random() < rate:
                            b[i] ^= 1 << rng.randrange(8)
                corrupted += b != raw
                buf += b
            for fr in parser.feed(bytes(buf), 0.02 * k):
                try:
                    p.decode_message(fr)
                except p.ProtocolError:
                    continue
                bad += fr.to_bytes() not in sent
        per = bad / (3 * ticks)
        print(f"| {model} | {rate} | {corrupted} | {bad} | {per:.2e} | {per * 9000:.2f} |")


def wait_until(cond, timeout_s: float) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.0005)
    return False


def bench_latency(samples: int) -> None:
    with tempfile.TemporaryDirectory() as d:
        link = str(Path(d) / "limo")
        with MockLimo(link, cmd_timeout_s=5.0) as mock, LimoDriver(link, cmd_timeout_s=5.0) as drv:
            wait_until(lambda: drv.motion_mode() == p.MotionMode.DIFF, 3.0)
            lat = []
            rng = random.Random(0)
            for i in range(samples):
                v = 0.001 * (i % 2 + 1) * (100 + i)
                t0 = time.monotonic()
                drv.set_command(v, 0.0)
                if wait_until(lambda v=v: mock._cmd is not None and abs(mock._cmd.linear_mps - round(v, 3)) < 1e-9,
                              1.0):
                    lat.append(time.monotonic() - t0)
                time.sleep(rng.uniform(0.005, 0.045))  # random phase w.r.t. the 20 ms tx period
    lat_ms = sorted(x * 1e3 for x in lat)
    print(f"\n## 3. Command latency set_command → 0x111 received by the mock (pty, 50 Hz, {len(lat)} samples)")
    print("| median_ms | p95_ms | max_ms |")
    print("|---|---|---|")
    print(f"| {statistics.median(lat_ms):.1f} | {lat_ms[int(0.95 * (len(lat_ms) - 1))]:.1f} | {lat_ms[-1]:.1f} |")


def bench_stop_latency(samples: int) -> None:
    """The driver's command timeout (0.5 s): last ``set_command`` → the mock's true velocity is zero (the mock's own
    watchdog set to 10 s, so the stop is the driver's)."""
    after_s = []
    with tempfile.TemporaryDirectory() as d:
        link = str(Path(d) / "limo")
        with MockLimo(link, cmd_timeout_s=10.0) as mock, LimoDriver(link, cmd_timeout_s=0.5) as drv:
            wait_until(lambda: drv.motion_mode() == p.MotionMode.DIFF, 3.0)
            for _ in range(samples):
                end = time.monotonic() + 0.5
                while time.monotonic() < end:
                    drv.set_command(0.4, 0.0)
                    last = time.monotonic()
                    time.sleep(0.02)
                if wait_until(lambda: mock.true_velocity().vx_mps == 0.0, 5.0):
                    after_s.append(time.monotonic() - last)
                time.sleep(0.2)
    ms = sorted(x * 1e3 for x in after_s)
    print(f"\n## 5. Command timeout: last set_command → base stopped (driver cmd_timeout 0.5 s, {len(ms)} of "
          f"{samples} stopped; load {' '.join(f'{v:.2f}' for v in os.getloadavg())})")
    print("| min_ms | median_ms | max_ms |")
    print("|---|---|---|")
    print(f"| {ms[0]:.1f} | {statistics.median(ms):.1f} | {ms[-1]:.1f} |")


def bench_acceptance(run_s: float, seed: int) -> None:
    accepted: list[bytes] = []
    with tempfile.TemporaryDirectory() as d:
        link = str(Path(d) / "limo")
        faults = FaultConfig(bit_flip_rate=0.01, seed=seed)
        with MockLimo(link, faults=faults, record=True) as mock, \
                LimoDriver(link, frame_observer=lambda f, m: accepted.append(f.to_bytes())) as drv:
            wait_until(lambda: drv.motion_mode() == p.MotionMode.DIFF, 3.0)
            time.sleep(0.3)
            t_start = time.monotonic()
            while mock.true_pose()[0] < 2.0:
                drv.set_command(0.25, 0.0)
                time.sleep(0.02)
            drv.stop_motion()
            wait_until(lambda: mock.true_velocity().vx_mps == 0.0, 1.0)
            time.sleep(0.3)
            x, y, yaw = mock.true_pose()
            o = drv.snapshot().pose
            line_err = math.hypot(o.x_m - x, o.y_m - y)
            line_yaw_err = abs(o.theta_rad - yaw)
            k = 0
            while time.monotonic() - t_start < run_s:
                drv.set_command(0.3, 0.6 * math.sin(0.5 * k * 0.02))
                time.sleep(0.02)
                k += 1
            drv.stop_motion()
            wait_until(lambda: mock.true_velocity().vx_mps == 0.0, 1.0)
            time.sleep(0.3)
            x2, y2, _yaw2 = mock.true_pose()
            snap = drv.snapshot()
            elapsed = time.monotonic() - t_start
            accepted = list(accepted)  # before the sent frames: every frame accepted so far was sent
            sent = [raw for _, raw, _ in mock.sent_frames]
            n_corrupted = mock.frames_corrupted
    bad, j = 0, 0
    for raw in accepted:
        kk = j
        while kk < len(sent) and sent[kk] != raw:
            kk += 1
        if kk == len(sent):
            bad += 1
        else:
            j = kk + 1
    o2 = snap.pose
    end_err = math.hypot(o2.x_m - x2, o2.y_m - y2)
    print(f"\n## 4. Acceptance run: {elapsed:.1f} s, bit_flip_rate 0.01 per frame (seed {seed}), heading from IMU")
    print("| frames sent | corrupted | accepted | corrupt accepted | rejected (checksum/length/count/id/unconfirmed/"
          "implausible) | odom err after 2 m line [mm] | yaw err [mrad] | path | odom err at end [mm] |")
    print("|---|---|---|---|---|---|---|---|---|")
    s = snap.parser
    rej = (f"{s['bad_checksum']}/{s['bad_length']}/{s['count_mismatch']}/{s['unknown_id']}/"
           f"{s['unconfirmed_id']}/{snap.implausible_frames}")
    print(f"| {len(sent)} | {n_corrupted} | {len(accepted)} | {bad} | {rej} | {line_err * 1e3:.2f} | "
          f"{line_yaw_err * 1e3:.2f} | {x:.2f} m line + arcs | {end_err * 1e3:.2f} |")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run-s", type=float, default=60.0)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--latency-samples", type=int, default=100)
    ap.add_argument("--stop-samples", type=int, default=20)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--skip-run", action="store_true", help="skip the pty runs (tables 3 and 4)")
    args = ap.parse_args(argv)
    print(f"# LIMO bench (python {sys.version.split()[0]})")
    bench_throughput(args.repeats)
    bench_residual()
    if not args.skip_run:
        bench_latency(args.latency_samples)
        bench_stop_latency(args.stop_samples)
        bench_acceptance(args.run_s, args.seed)
    return 0


if __name__ == "__main__":
    sys.exit(main())
