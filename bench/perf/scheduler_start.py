"""Time from ``gsrmr-scheduler`` process start to its first published schedule (warm and cold kernel cache).

Usage: ``.venv/bin/python bench/perf/scheduler_start.py [--runs 5] [--cold 2] [--method exact]``. Each run starts
the scheduler as the demo does (``config/link.yaml`` + ``config/scheduler.yaml``, the sandbox route, the
demo's seed loss map when cached) in its own ROS domain, and a subscriber in this process (started first,
transient-local QoS like the robot's) notes when the first ``gsrmr/schedule`` arrives. "Warm" uses the
project's numba cache as it is after one run; "cold" points ``NUMBA_CACHE_DIR`` at an empty folder, so the
knapsack kernel is compiled in the process. Prints every run and the median and worst per kind.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
import random
import statistics
import sys
import tempfile
import threading
import time

REPO = Path(__file__).resolve().parents[2]


def first_schedule_s(method: str, env_extra: dict[str, str], timeout_s: float = 60.0) -> float:
    """Seconds from Popen of the scheduler to the first schedule received (NaN on timeout)."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from std_msgs.msg import Float64MultiArray

    from gsrmr_common.ros_wire import SCHEDULE_QOS
    from gsrmr_sim.sim_stack import environment, sim_stack
    from gsrmr_sim.supervisor import ProcessStack

    domain = random.randrange(120, 200)
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    seeds = sorted((REPO / ".cache" / "gsrmr").glob("sandbox-*/loss_map_*_round1_q*.json"))
    spec = next(s for s in sim_stack(scene="sandbox", model_path="", record_dir="", method=method,
                                     loss_map_file=str(seeds[-1]) if seeds else "")
                if s.executable == "gsrmr-scheduler")
    rclpy.init()
    node = rclpy.create_node("scheduler_start_bench")
    got = threading.Event()
    node.create_subscription(Float64MultiArray, "gsrmr/schedule", lambda _m: got.set(), SCHEDULE_QOS)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spin = threading.Thread(target=lambda: [executor.spin_once(0.01) for _ in iter(lambda: got.is_set(), True)],
                            daemon=True)
    spin.start()
    with tempfile.TemporaryDirectory() as tmp:
        stack = ProcessStack(environment(domain, {**os.environ, **env_extra}), Path(tmp) / "logs")
        try:
            t0 = time.perf_counter()
            stack.start("scheduler", spec)
            ok = got.wait(timeout_s)
            elapsed = time.perf_counter() - t0 if ok else float("nan")
        finally:
            stack.stop()
            got.set()
            spin.join(2)
            executor.shutdown()
            node.destroy_node()
            rclpy.shutdown()
    return elapsed


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--cold", type=int, default=2)
    ap.add_argument("--method", default="exact")
    args = ap.parse_args()
    print(f"# bench/perf/scheduler_start.py: method {args.method} ({os.cpu_count()} CPUs, load average "
          f"{os.getloadavg()[0]:.1f})")
    print("| kind | run | first schedule after start [s] |")
    print("|---|---|---|")
    results: dict[str, list[float]] = {"warm": [], "cold": []}
    first_schedule_s(args.method, {})  # fills the numba cache: the warm runs start from it
    for kind, n in (("warm", args.runs), ("cold", args.cold)):
        for k in range(n):
            extra = {}
            if kind == "cold":
                extra["NUMBA_CACHE_DIR"] = tempfile.mkdtemp(prefix="numba-cold-")
            t = first_schedule_s(args.method, extra)
            results[kind].append(t)
            print(f"| {kind} | {k + 1} | {t:.2f} |", flush=True)
    for kind, values in results.items():
        if values:
            print(f"| **{kind}** | median (worst) | {statistics.median(values):.2f} ({max(values):.2f}) |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
