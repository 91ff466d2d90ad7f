"""Soak benchmark: 10,000 slots through the slot cores (or one ServerNode), faster than real time; RSS growth.

Every slot k (without waiting for the slot clock) the robot's uplink core
(:meth:`UplinkCore.run_slot <gsrmr_robot.uplink_core.UplinkCore.run_slot>`) takes a synthetic 160×120 camera
frame and the odometry pose (a slow circle in ``map``) and decides the slot: an image slot every
``--image-every``-th slot (the schedule entry it is given), a pose key every slot, its energy-ledger row.
The uploads go through the uplink fault injector of :mod:`gsrmr_sim.fault_relay` (default rates: 10 % drops,
3 % each other fault) into an :class:`~gsrmr_server.uplink.UplinkAssembler`; the ledger row reaches the
server untouched (as on ``gsrmr/ledger``). Then, by default (pure path, no rclpy context, node or DDS;
wiring in :mod:`gsrmr_sim.core_path`): :meth:`ServerCore.process <gsrmr_server.slot_core.ServerCore.process>`
composes the slot, its JPEG is encoded, :func:`gsrmr_server.scoring.score_slot` measures it against the true
frame (the simulation scorer's work; off with ``--no-score``) and a :class:`~gsrmr_server.recording.RunRecorder`
writes CSV + MCAP to a temp dir. With ``--node``: the same uploads go into a whole rclpy
:class:`~gsrmr_server.server_node.ServerNode` in this process (ledger row through its callback) and
:meth:`ServerNode.process_slot` composes, publishes and records — to soak the ROS layer; unless ``--no-score``
a :class:`~gsrmr_sim.world.scorer_node.ScorerNode` in this process gets what it publishes (``mr/image``,
``mr/slot_info``), the ledger row and the true frame through its callbacks and scores each slot.

Resident set size (psutil, MiB) is sampled every ``--sample-every`` slots; growth is measured from the
sample after ``--warmup`` slots to the end (the acceptance bound is 5 %; exit status 1 above it).

    .venv/bin/python bench/perf/soak.py                  # 10,000 slots, slot cores (no ROS)
    .venv/bin/python bench/perf/soak.py --slots 2000
    .venv/bin/python bench/perf/soak.py --node           # 10,000 slots through one ServerNode
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

import psutil
import rclpy
from rclpy.parameter import Parameter

from gsrmr_common.link_model import SLOT_S
from gsrmr_common.ros_wire import camera_info_from_intrinsics, image_to_msg, ledger_to_msg
from gsrmr_common.slot_clock import SlotClock
from gsrmr_server.server_node import ServerNode
from gsrmr_sim.core_path import CAMERA_FRAME, RobotSide, ServerSide, deliver, intrinsics, point_model, synthetic_frames
from gsrmr_sim.fault_relay import FaultInjector, FaultRates
from gsrmr_sim.world.scorer_node import ScorerNode


def tee(publisher, callback) -> None:
    """Hand every message ``publisher`` publishes to ``callback`` too (the subscriber in this process)."""
    publish = publisher.publish

    def both(msg) -> None:
        publish(msg)
        callback(msg)

    publisher.publish = both


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--node", action="store_true", help="drive a whole rclpy ServerNode instead of the slot cores")
    p.add_argument("--slots", type=int, default=10_000)
    p.add_argument("--warmup", type=int, default=1000, help="slots before the baseline RSS sample")
    p.add_argument("--sample-every", type=int, default=1000)
    p.add_argument("--image-every", type=int, default=2, help="schedule an image every n-th slot")
    p.add_argument("--no-score", action="store_true", help="do not measure m̂ against the true frame")
    p.add_argument("--width", type=int, default=160)
    p.add_argument("--height", type=int, default=120)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--gaussians", type=int, default=300, help="size of the (untrained) GS model; the soak "
                   "measures memory, so a small model keeps 10,000 slots short")
    args = p.parse_args()
    if args.node:
        os.environ.setdefault("ROS_DOMAIN_ID", str(random.Random(os.getpid()).randrange(1, 101)))
        os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

    tmp = Path(tempfile.mkdtemp(prefix="gsrmr-soak-"))
    model = point_model(tmp, n=args.gaussians)
    camera = intrinsics(args.width, args.height)
    score = not args.no_score
    clock = SlotClock(SLOT_S)
    k0 = clock.slot_at(time.time_ns())
    if args.node:
        rclpy.init()
        node = ServerNode(parameter_overrides=[Parameter("model_path", value=str(model)),
                                               Parameter("record_dir", value=str(tmp / "rec"))])
        info = camera_info_from_intrinsics(camera, 0, CAMERA_FRAME)  # what the robot relays
        node.use_camera_info(info)
        assert node.clock == clock, "the node's slot_s differs from SLOT_S"
        node.cursor.first = k0  # round time 0 of the MR content
        uplink = node.uplink
        scorer = None
        if score:
            scorer = ScorerNode(worker=False, parameter_overrides=[Parameter("model_path", value=str(model)),
                                                                   Parameter("record_dir", value=str(tmp / "rec"))])
            scorer.use_camera_info(info)
            tee(node._pub_mr, scorer.on_mr_image)
            tee(node._pub_info, scorer.on_slot_info)

        def server_slot(k: int, ledger, frame) -> None:
            if ledger is not None:
                node._on_ledger(ledger_to_msg(ledger))  # what gsrmr/ledger delivers
            if scorer is not None:
                if ledger is not None:
                    scorer.on_ledger(ledger_to_msg(ledger))
                scorer.on_camera(image_to_msg(frame, clock.start_ns(k), CAMERA_FRAME))  # camera/image_raw
            node.process_slot(k)
            if scorer is not None:
                scorer.score_ready(flush=True)
    else:
        server = ServerSide(model, camera, slot_s=SLOT_S, record_dir=str(tmp / "rec"))
        uplink = server.uplink

        def server_slot(k: int, ledger, frame) -> None:
            server.process(k, ledger, t0_slot=k0, truth=frame if score else None)

    robot = RobotSide(SLOT_S)
    frames = synthetic_frames(args.width, args.height, 8, args.seed)
    injector = FaultInjector(FaultRates(), seed=args.seed, slot_s=SLOT_S)
    proc = psutil.Process()
    samples: list[tuple[int, float, float]] = []  # (slots done, rss MiB, seconds)

    load = ", ".join(f"{v:.2f}" for v in os.getloadavg())
    path = "one rclpy ServerNode (--node)" if args.node else "slot cores, no ROS (UplinkCore → ServerCore)"
    print(f"# soak: {args.slots} slots through {path}, image every {args.image_every}, {args.width}×{args.height}, "
          f"{args.gaussians} Gaussians, score {'on' if score else 'off'}, recording to {tmp / 'rec'}, "
          f"fault rates {FaultRates()}")
    print(f"# machine: {os.cpu_count()} CPUs, load average {load} (1/5/15 min) at start")
    t0 = time.perf_counter()
    for i in range(args.slots):
        k = k0 + i
        t = 0.1 * i
        pose = (2.0 * math.cos(0.05 * t), 2.0 * math.sin(0.05 * t), 0.05 * t + math.pi / 2)
        frame = frames[i % len(frames)]
        start = clock.start_ns(k)
        decision = robot.run_slot(k, frame, start, pose, (int(i % args.image_every == 0), float("nan")))
        t_send = start + 1_000_000
        deliver(uplink, injector.due(t_send), t_send, clock)
        for up in robot.uploads(decision):
            deliver(uplink, injector.push(up, t_send), t_send, clock)
        t_compose = start + 30_000_000
        deliver(uplink, injector.due(t_compose), t_compose, clock)
        server_slot(k, decision.row if decision.publish_row else None, frame)
        done = i + 1
        if done == args.warmup or done % args.sample_every == 0 or done == args.slots:
            gc.collect()
            samples.append((done, proc.memory_info().rss / 2**20, time.perf_counter() - t0))
            print(f"#   {done:6d} slots  rss {samples[-1][1]:7.1f} MiB  {samples[-1][2]:6.1f} s", flush=True)
    if args.node:
        node.on_shutdown()
        composed = node.stats.slots
        scored = 0
        if scorer is not None:
            scorer.on_shutdown()
            scored = scorer.scored
    else:
        server.close()
        composed, scored = server.slots_done, server.scored
    base = next(s for s in samples if s[0] >= args.warmup)
    final = samples[-1]
    growth = (final[1] - base[1]) / base[1]
    faults = {str(f): n for f, n in uplink.faults.items()}
    print("| slots | composed | scored | rss after warm-up MiB | rss end MiB | growth % | slots/s | faults counted |")
    print("|---|---|---|---|---|---|---|---|")
    print(f"| {args.slots} | {composed} | {scored} | {base[1]:.1f} | {final[1]:.1f} | {100 * growth:+.2f} | "
          f"{args.slots / final[2]:.0f} | {sum(faults.values())} |")
    print(f"# faults: {faults}")
    print(f"# injected: {dict(sorted(injector.injected.items()))}")
    print(f"# acceptance (growth <= 5 %): {'PASS' if growth <= 0.05 else 'FAIL'}")
    if args.node:
        if scorer is not None:
            scorer.destroy_node()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0 if growth <= 0.05 else 1


if __name__ == "__main__":
    sys.exit(main())
