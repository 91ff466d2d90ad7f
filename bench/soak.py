"""Soak benchmark: 10,000 slots through one ServerNode, faster than real time; resident-memory growth.

A :class:`~gsrmr_server.server_node.ServerNode` (rclpy, in this process, recording CSV + MCAP to a temp
dir) is driven slot by slot without waiting for the slot clock: for slot k the robot's pose key (a slow
circle in ``map``) and, in every ``--image-every``-th slot, a 160×120 JPEG go through the uplink fault
injector of :mod:`gsrmr_sim.fault_relay` (default rates: 10 % drops, 3 % each other fault) into the
node's :class:`~gsrmr_server.uplink.UplinkAssembler`, then :meth:`ServerNode.process_slot` composes,
publishes and records the slot. Resident set size (psutil, MiB) is sampled every ``--sample-every``
slots; growth is measured from the sample after ``--warmup`` slots to the end (the acceptance bound
is 5 %).

    .venv/bin/python bench/soak.py                  # 10,000 slots
    .venv/bin/python bench/soak.py --slots 2000
"""

from __future__ import annotations

import argparse
import gc
import math
import os
from pathlib import Path
import random
import sys
import tempfile
import time

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "test"))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--slots", type=int, default=10_000)
    p.add_argument("--warmup", type=int, default=1000, help="slots before the baseline RSS sample")
    p.add_argument("--sample-every", type=int, default=1000)
    p.add_argument("--image-every", type=int, default=2, help="upload the JPEG every n-th slot")
    p.add_argument("--width", type=int, default=160)
    p.add_argument("--height", type=int, default=120)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--gaussians", type=int, default=300, help="size of the (untrained) GS model; the soak "
                   "measures memory, so a small model keeps 10,000 slots short")
    args = p.parse_args()
    os.environ["ROS_DOMAIN_ID"] = str(random.Random(os.getpid()).randrange(1, 101))
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

    import psutil
    import rclpy
    from rclpy.parameter import Parameter
    from stack_harness import make_point_model

    from gsrmr_common.camera import Intrinsics
    from gsrmr_common.jpeg import encode_jpeg
    from gsrmr_common.ros_wire import camera_info_from_intrinsics
    from gsrmr_common.wire import PoseKey
    from gsrmr_server.server_node import ServerNode
    from gsrmr_sim.fault_relay import FaultInjector, FaultRates, Upload

    tmp = Path(tempfile.mkdtemp(prefix="gsrmr-soak-"))
    model = make_point_model(tmp, n=args.gaussians)
    rclpy.init()
    node = ServerNode(parameter_overrides=[Parameter("model_path", value=str(model)),
                                           Parameter("record_dir", value=str(tmp / "rec"))])
    node.use_camera_info(camera_info_from_intrinsics(Intrinsics.from_fov(args.width, args.height, math.radians(70)),
                                                     0, "camera_optical_frame"))  # what the robot relays
    rng = np.random.default_rng(args.seed)
    yy, xx = np.mgrid[0:args.height, 0:args.width]
    frame = np.stack([xx * 255 // args.width, yy * 255 // args.height, (xx + yy) % 256], axis=2)
    jpegs = [encode_jpeg(np.clip(frame + rng.integers(0, 30, frame.shape), 0, 255).astype(np.uint8), 80)
             for _ in range(8)]
    slot_ns = node._slot_len_ns
    injector = FaultInjector(FaultRates(), seed=args.seed, slot_s=slot_ns / 1e9)
    k0 = time.time_ns() // slot_ns
    node._t0_slot = k0
    proc = psutil.Process()
    samples: list[tuple[int, float, float]] = []  # (slots done, rss MiB, seconds)

    def deliver(uploads: list[Upload], now_ns: int) -> None:
        now_slot = now_ns // slot_ns
        for up in uploads:
            slot = (up.stamp_ns + slot_ns // 2) // slot_ns
            if up.kind == "key":
                node.uplink.on_key(PoseKey(slot, *up.data), now_slot, now_ns)
            else:
                node.uplink.on_image(slot, up.data, now_slot, now_ns)

    print(f"# soak: {args.slots} slots, image every {args.image_every}, {args.width}×{args.height}, "
          f"{args.gaussians} Gaussians, recording to {tmp / 'rec'}, fault rates {FaultRates()}")
    t0 = time.perf_counter()
    for i in range(args.slots):
        k = k0 + i
        t = 0.1 * i
        pose = (2.0 * math.cos(0.05 * t), 2.0 * math.sin(0.05 * t), 0.05 * t + math.pi / 2)
        t_send = k * slot_ns + 1_000_000
        deliver(injector.due(t_send), t_send)
        deliver(injector.push(Upload("key", k * slot_ns, pose, "map"), t_send), t_send)
        if i % args.image_every == 0:
            deliver(injector.push(Upload("image", k * slot_ns, jpegs[i % len(jpegs)]), t_send), t_send)
        t_compose = k * slot_ns + 30_000_000
        deliver(injector.due(t_compose), t_compose)
        node.process_slot(k)
        done = i + 1
        if done == args.warmup or done % args.sample_every == 0 or done == args.slots:
            gc.collect()
            samples.append((done, proc.memory_info().rss / 2**20, time.perf_counter() - t0))
            print(f"#   {done:6d} slots  rss {samples[-1][1]:7.1f} MiB  {samples[-1][2]:6.1f} s", flush=True)
    node.on_shutdown()
    base = next(s for s in samples if s[0] >= args.warmup)
    final = samples[-1]
    growth = (final[1] - base[1]) / base[1]
    faults = dict(node.uplink.faults)
    print("| slots | composed | rss after warm-up MiB | rss end MiB | growth % | slots/s | faults counted |")
    print("|---|---|---|---|---|---|---|")
    print(f"| {args.slots} | {node.slots_done} | {base[1]:.1f} | {final[1]:.1f} | {100 * growth:+.2f} | "
          f"{args.slots / final[2]:.0f} | {sum(faults.values())} |")
    print(f"# faults: {faults}")
    print(f"# injected: {dict(sorted(injector.injected.items()))}")
    print(f"# acceptance (growth <= 5 %): {'PASS' if growth <= 0.05 else 'FAIL'}")
    node.destroy_node()
    rclpy.try_shutdown()
    return 0 if growth <= 0.05 else 1


if __name__ == "__main__":
    sys.exit(main())
