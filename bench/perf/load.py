"""Load benchmark: N robots uploading at 1/τ to ONE server process for D seconds.

Two modes (``--core``, the default, and ``--dds``):

* **core** (default): this process holds N :class:`~gsrmr_robot.uplink_core.UplinkCore` instances (a synthetic
  W×H camera frame and a slow odometry circle each; no schedule, so every robot uploads its JPEG and pose
  key every slot, the heaviest uplink) and N :class:`~gsrmr_server.slot_core.ServerCore` instances (each with its
  own :class:`~gsrmr_server.uplink.UplinkAssembler` and model copy, built as the server node builds them:
  ``gsrmr_sim/core_path.py``). Every slot start (+1 ms, the robot's phase) the robots decide; a pool of
  ``--threads`` workers composes each robot's slot (one robot's slots in order, never two at once — like a
  node's single callback group). Per slot: compose time (take → m̂ → its JPEG, ms) and latency (m̂ and its
  JPEG ready − slot start, ms); ``missed`` = slots not ready within τ (composed late, or still queued at the
  end). This is the workstation's composition capacity without DDS, transport, or a second process: the
  default because it is what the issue asks the cores for, it is repeatable on a shared machine and it needs
  no ROS. Nothing is recorded, as in ``--dds`` (the nodes have no ``record_dir`` there).
* **dds** (``--dds``): the deployed layout, two processes in one isolated ROS domain (localhost discovery).
  The server process (this one) spins N :class:`~gsrmr_server.server_node.ServerNode` instances, one per
  namespace ``/r0 … /r{N-1}``, with one ``MultiThreadedExecutor`` (``--threads``); the robot process
  (``--role robots``, started by this script) runs N :class:`~gsrmr_robot.robot_node.RobotNode` instances
  in the same namespaces plus, per robot, a feeder publishing a synthetic camera frame
  (``camera/image_raw``, rgb8 W×H) and odometry (``odom``, a slow circle) at 1/τ. No schedule is
  published, so every robot uploads its JPEG and pose key every slot. Per slot and robot the server's own
  latency (MR image published − slot start, ms) is collected; drops are the slots whose key did not
  arrive in time (``missing_key``), slots composed without the uploaded image (``no_image``: every robot
  uploads one per slot), uploads that arrived after their slot (``late``) and slots the server skipped.

Prints one table row per run, then the median and the worst (per column) over ``--repeats`` runs; the
header gives the configuration and the machine's load average when the benchmark started.

    .venv/bin/python bench/perf/load.py                            # core: 10 robots, 10 Hz, 60 s, 160×120
    .venv/bin/python bench/perf/load.py --robots 4 --duration-s 20
    .venv/bin/python bench/perf/load.py --dds                      # DDS: 10 RobotNodes → 10 ServerNodes
    .venv/bin/python bench/perf/load.py --dds --robots 4 --duration-s 20
"""

from __future__ import annotations

import argparse
from collections import deque
import json
import math
import os
from pathlib import Path
import random
import sys
import tempfile
import threading
import time

import numpy as np

from gsrmr_common.tf_tree import CAMERA_OPTICAL_FRAME


def _feeder_class():
    from nav_msgs.msg import Odometry
    from rclpy.node import Node
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import CameraInfo, Image

    from gsrmr_common.camera import Intrinsics
    from gsrmr_common.ros_wire import camera_info_from_intrinsics, image_to_msg

    class Feeder(Node):
        """Synthetic camera frames and odometry (odom frame: circle of 1 m radius at 0.2 rad/s)."""

        def __init__(self, width: int, height: int, slot_s: float, seed: int, **kw) -> None:
            super().__init__("load_feeder", **kw)
            rng = np.random.default_rng(seed)
            yy, xx = np.mgrid[0:height, 0:width]
            base = np.stack([xx * 255 // width, yy * 255 // height, (xx + yy) % 256], axis=2)
            self.frame = np.clip(base + rng.integers(0, 40, (height, width, 3)), 0, 255).astype(np.uint8)
            self.t0 = time.monotonic()
            self.img_pub = self.create_publisher(Image, "camera/image_raw", qos_profile_sensor_data)
            # the robot uploads images only once it knows the camera (a pinhole at the frame's size: passed through)
            self.info_pub = self.create_publisher(CameraInfo, "camera/camera_info", qos_profile_sensor_data)
            self.intrinsics = Intrinsics.from_fov(width, height, math.radians(70.0))
            self.odom_pub = self.create_publisher(Odometry, "odom", 20)
            self.create_timer(slot_s, self._tick)

        def _tick(self) -> None:
            now = self.get_clock().now()
            self.img_pub.publish(image_to_msg(self.frame, now.nanoseconds, CAMERA_OPTICAL_FRAME))
            self.info_pub.publish(camera_info_from_intrinsics(self.intrinsics, now.nanoseconds, CAMERA_OPTICAL_FRAME))
            t = time.monotonic() - self.t0
            msg = Odometry()
            msg.header.stamp = now.to_msg()
            msg.header.frame_id, msg.child_frame_id = "odom", "base_link"
            msg.pose.pose.position.x, msg.pose.pose.position.y = math.cos(0.2 * t), math.sin(0.2 * t)
            yaw = 0.2 * t + math.pi / 2
            msg.pose.pose.orientation.z, msg.pose.pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
            self.odom_pub.publish(msg)

    return Feeder


def run_robots(n: int, width: int, height: int, slot_s: float) -> int:
    """Role ``robots``: N RobotNodes + feeders until SIGINT/SIGTERM."""
    import rclpy
    from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor

    from gsrmr_robot.robot_node import RobotNode

    rclpy.init()
    feeder = _feeder_class()
    ex = MultiThreadedExecutor(num_threads=2)
    nodes = []
    for i in range(n):
        nodes.append(RobotNode(namespace=f"/r{i}"))
        nodes.append(feeder(width, height, slot_s, i, namespace=f"/r{i}"))
    for node in nodes:
        ex.add_node(node)
    try:
        ex.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


def run_servers(args: argparse.Namespace, model_path: Path) -> dict:
    """One load run: start the robot process, spin N ServerNodes for ``duration_s``, collect stats."""
    import rclpy
    from rclpy.executors import MultiThreadedExecutor
    from rclpy.parameter import Parameter

    from gsrmr_server.server_node import ServerNode
    from gsrmr_sim.supervisor import ProcessStack

    robots = ProcessStack(os.environ.copy(), Path(tempfile.mkdtemp(prefix="gsrmr-load-logs-")))
    robots.start("robots", [sys.executable, __file__, "--role", "robots", "--robots", str(args.robots),
                            "--width", str(args.width), "--height", str(args.height)])
    rclpy.init()
    from gsrmr_common.camera import Intrinsics
    from gsrmr_common.ros_wire import camera_info_from_intrinsics

    params = [Parameter("model_path", value=str(model_path)), Parameter("measure_loss", value=True)]
    servers = [ServerNode(namespace=f"/r{i}", parameter_overrides=params) for i in range(args.robots)]
    info = camera_info_from_intrinsics(Intrinsics.from_fov(args.width, args.height, math.radians(70)), 0,
                                       CAMERA_OPTICAL_FRAME)
    for s in servers:  # the robots' calibration (what each robot relays on uplink/camera_info)
        s.use_camera_info(info)
    ex = MultiThreadedExecutor(num_threads=args.threads)
    for s in servers:
        ex.add_node(s)
    import psutil

    proc = psutil.Process()
    spinner = threading.Thread(target=ex.spin, daemon=True)
    spinner.start()
    try:
        time.sleep(args.warmup_s)
        for s in servers:  # measure from here on (the counters are only read and reset here)
            s.stats = type(s.stats)(s.params.slot_s, history=100_000)
            s.uplink.faults.clear()
        cpu0 = proc.cpu_times()
        t0 = time.monotonic()
        time.sleep(args.duration_s)
        wall = time.monotonic() - t0
        cpu1 = proc.cpu_times()
        snapshot = [(list(s.stats.latencies_ms), dict(s.uplink.faults), s.stats.slots, s.stats.slots_on_time,
                     dict(s.stats.sources)) for s in servers]
    finally:
        ex.shutdown(timeout_sec=5)
        robots.stop()
    lat = np.concatenate([np.asarray(snap[0]) for snap in snapshot])
    faults: dict[str, int] = {}
    for snap in snapshot:
        for k, v in snap[1].items():
            faults[k] = faults.get(k, 0) + v
    slots = sum(snap[2] for snap in snapshot)
    sources = {k: sum(snap[4].get(k, 0) for snap in snapshot) for k in ("image", "render", "fallback", "none")}
    expected = int(args.robots * wall / args.slot_s)
    dropped_keys = faults.get("missing_key", 0)
    result = {"robots": args.robots, "wall_s": round(wall, 1), "slots": slots, "slots_expected": expected,
              "on_time": sum(snap[3] for snap in snapshot),
              "p50_ms": float(np.percentile(lat, 50)), "p95_ms": float(np.percentile(lat, 95)),
              "p99_ms": float(np.percentile(lat, 99)), "max_ms": float(lat.max()),
              "missing_key": dropped_keys, "no_image": slots - sources["image"],
              "late": faults.get("late", 0),
              "skipped": faults.get("skipped_slots", 0),
              "sources": sources,
              "server_cpu_s_per_s": round((cpu1.user + cpu1.system - cpu0.user - cpu0.system) / wall, 2)}
    for s in servers:
        s.destroy_node()
    rclpy.try_shutdown()
    return result


def run_cores(args: argparse.Namespace, model_path: Path) -> dict:
    """One core-mode run: N robot cores and N server cores in this process, paced at 1/τ, no ROS."""
    from concurrent.futures import ThreadPoolExecutor

    import psutil

    from gsrmr_common.slot_clock import SlotClock
    from gsrmr_sim.core_path import RobotSide, ServerSide, deliver, intrinsics, synthetic_frames

    camera = intrinsics(args.width, args.height)
    clock = SlotClock(args.slot_s)
    servers = [ServerSide(model_path, camera, slot_s=args.slot_s, measure_loss=True) for _ in range(args.robots)]
    robots = [RobotSide(args.slot_s) for _ in range(args.robots)]
    frames = [synthetic_frames(args.width, args.height, 1, seed=i, noise=40)[0] for i in range(args.robots)]
    lock, stop = threading.Lock(), threading.Event()
    pending: list[deque] = [deque() for _ in range(args.robots)]  # (slot, uploads, ledger row, arrival ns)
    busy = [False] * args.robots
    done: list[tuple[int, float, float, str]] = []  # (slot, compose ms, latency ms, source)

    def drain(r: int) -> None:
        """Robot r's queued slots in order (uploads go into its assembler here: one thread per robot at a time)."""
        server = servers[r]
        while not stop.is_set():
            with lock:
                if not pending[r]:
                    busy[r] = False
                    return
                k, uploads, ledger, arrival_ns = pending[r].popleft()
            deliver(server.uplink, uploads, arrival_ns, clock)
            out, ms = server.process(k, ledger, t0_slot=k_first)
            source = str(out.composed.source)
            done.append((k, ms, (time.time_ns() - clock.start_ns(k)) / 1e6, source))
        with lock:
            busy[r] = False

    n_warm, n_run = round(args.warmup_s / args.slot_s), round(args.duration_s / args.slot_s)
    k_first = clock.slot_at(time.time_ns()) + 2
    k_meas, k_end = k_first + n_warm, k_first + n_warm + n_run
    proc = psutil.Process()
    pool = ThreadPoolExecutor(max_workers=args.threads, thread_name_prefix="compose")
    try:
        for k in range(k_first, k_end + 1):
            wait_ns = clock.start_ns(k) + 1_000_000 - time.time_ns()  # the robots run 1 ms into the slot
            if wait_ns > 0:
                time.sleep(wait_ns / 1e9)
            if k == k_meas:
                cpu0, t0 = proc.cpu_times(), time.monotonic()
            if k == k_end:  # the last measured slot's deadline
                break
            t = (k - k_first) * args.slot_s
            pose = (math.cos(0.2 * t), math.sin(0.2 * t), 0.2 * t + math.pi / 2)
            for r, robot in enumerate(robots):
                decision = robot.run_slot(k, frames[r], clock.start_ns(k), pose)
                item = (k, robot.uploads(decision), decision.row if decision.publish_row else None, time.time_ns())
                with lock:
                    pending[r].append(item)
                    start, busy[r] = not busy[r], True
                if start:
                    pool.submit(drain, r)
        wall = time.monotonic() - t0
        cpu1 = proc.cpu_times()
    finally:
        stop.set()
        pool.shutdown(wait=True, cancel_futures=True)
    measured = [d for d in done if k_meas <= d[0] < k_end]
    expected = args.robots * n_run
    compose = np.asarray([d[1] for d in measured]) if measured else np.full(1, np.nan)
    lat = np.asarray([d[2] for d in measured]) if measured else np.full(1, np.nan)
    on_time = int(np.sum(lat <= 1e3 * args.slot_s))
    sources = {k: sum(1 for d in measured if d[3] == k) for k in ("image", "render", "fallback", "none")}
    return {"robots": args.robots, "wall_s": round(wall, 1), "slots": len(measured), "slots_expected": expected,
            "on_time": on_time, "missed": expected - on_time,
            "compose_p50_ms": float(np.percentile(compose, 50)), "compose_p95_ms": float(np.percentile(compose, 95)),
            "compose_p99_ms": float(np.percentile(compose, 99)),
            "p50_ms": float(np.percentile(lat, 50)), "p95_ms": float(np.percentile(lat, 95)),
            "p99_ms": float(np.percentile(lat, 99)), "max_ms": float(lat.max()), "sources": sources,
            "server_cpu_s_per_s": round((cpu1.user + cpu1.system - cpu0.user - cpu0.system) / wall, 2)}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--role", choices=("bench", "robots"), default="bench")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--core", dest="dds", action="store_false", help="slot cores in this process (default)")
    mode.add_argument("--dds", action="store_true", help="RobotNodes in another process → ServerNodes over DDS")
    p.set_defaults(dds=False)
    p.add_argument("--robots", type=int, default=10)
    p.add_argument("--duration-s", type=float, default=60.0)
    p.add_argument("--warmup-s", type=float, default=None, help="before measuring (default 8 s --dds, 2 s core)")
    p.add_argument("--repeats", type=int, default=3, help="runs; the table ends with their median and worst")
    p.add_argument("--threads", type=int, default=4, help="server threads (MultiThreadedExecutor with --dds, "
                   "compose workers in core mode)")
    p.add_argument("--width", type=int, default=160)
    p.add_argument("--height", type=int, default=120)
    p.add_argument("--slot-s", type=float, default=0.1, help="τ (must match the nodes' slot_s default)")
    p.add_argument("--gaussians", type=int, default=2000, help="size of the (untrained) GS model")
    args = p.parse_args()
    if args.role == "robots":
        return run_robots(args.robots, args.width, args.height, args.slot_s)
    if args.warmup_s is None:
        args.warmup_s = 8.0 if args.dds else 2.0
    load = ", ".join(f"{v:.2f}" for v in os.getloadavg())
    from gsrmr_sim.core_path import point_model

    model = point_model(Path(tempfile.mkdtemp(prefix="gsrmr-load-")), n=args.gaussians)
    if args.dds:
        os.environ.setdefault("ROS_DOMAIN_ID", str(random.Random(os.getpid()).randrange(1, 101)))
        os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        print(f"# load (--dds): {args.robots} robots × {1 / args.slot_s:g} Hz (image + key every slot) → 1 server "
              f"process ({args.robots} ServerNodes, {args.threads} threads), {args.width}×{args.height}, "
              f"{args.gaussians} Gaussians, {args.duration_s:g} s after {args.warmup_s:g} s warm-up, "
              f"ROS_DOMAIN_ID={os.environ['ROS_DOMAIN_ID']}, {os.cpu_count()} CPUs, load average {load} "
              f"(1/5/15 min) at start")
        run = run_servers
        cols = ("robots", "slots", "slots_expected", "on_time", "p50_ms", "p95_ms", "p99_ms", "max_ms",
                "missing_key", "no_image", "late", "skipped", "server_cpu_s_per_s")
    else:
        print(f"# load (core): {args.robots} robots × {1 / args.slot_s:g} Hz (image + key every slot; UplinkCore → "
              f"UplinkAssembler → ServerCore in 1 process, no ROS), {args.threads} compose threads, "
              f"{args.width}×{args.height}, {args.gaussians} Gaussians, {args.duration_s:g} s after "
              f"{args.warmup_s:g} s warm-up, {os.cpu_count()} CPUs, load average {load} (1/5/15 min) at start")
        run = run_cores
        cols = ("robots", "slots", "slots_expected", "on_time", "missed", "compose_p50_ms", "compose_p95_ms",
                "compose_p99_ms", "p50_ms", "p95_ms", "p99_ms", "max_ms", "server_cpu_s_per_s")
    print("| run | " + " | ".join(cols) + " |")
    print("|" + "---|" * (len(cols) + 1))
    results = []
    for r in range(args.repeats):
        res = run(args, model)
        results.append(res)
        print(f"| {r + 1} | " + " | ".join(f"{res[c]:.1f}" if isinstance(res[c], float) else str(res[c])
                                          for c in cols) + " |", flush=True)
        print("#   sources: " + json.dumps(res["sources"]), flush=True)
    if args.repeats > 1:
        higher_is_better = ("slots", "on_time")
        med = {c: float(np.median([r[c] for r in results])) for c in cols}
        worst = {c: (min if c in higher_is_better else max)(r[c] for r in results) for c in cols}
        ints = {c for c in cols if all(isinstance(r[c], int) for r in results)}
        print("| median | " + " | ".join(f"{med[c]:.0f}" if c in ints else f"{med[c]:.1f}" for c in cols) + " |")
        print("| worst | " + " | ".join(f"{worst[c]:.1f}" if isinstance(worst[c], float) else str(worst[c])
                                        for c in cols) + " |")
    return 0

if __name__ == "__main__":
    sys.exit(main())
