"""The hostile graph over full demo rounds: a rogue process lies during round 2, each case over ``--runs`` rounds.

Usage: ``.venv/bin/python bench/acceptance/hostile_graph.py [--runs 3] [--cases NAME ...] [--quick] [-- DEMO_ARGS...]``.
Each run is one ``gsrmr-demo --channel-seed 3`` (288 slots, ~45 s with the model cached). Once the round is under
way (the demo's second progress line, ~5 s in) the rogue — ``test/support/hostile.py CASE``, a process of its own in the
demo's ROS domain, at nice 19 (on a real network it is another machine: its own CPU is not the system's) — lies
until the round ends. Cases: ``none`` (no rogue: the clean reference) and every case of ``test/support/hostile.py``.

Per run it prints: images sent, mean MR loss (the scorer's, against the simulator's truth), regret and the energy
ratio against upload-all **on the simulator's true channel** — each slot's energies (the run's, upload-all's and the
hindsight optimum's) rescaled from the gain the robot's ledger booked to the gain the simulated radio published
(power ∝ 1/g for fixed bits; the bench records the radio's samples by writer name, so a lie the robot took cannot
lower them) —, slots on time, the messages each deployment node refused (by writer) and found implausible, the
nodes that named the rogue on ``/diagnostics``, and how loaded the machine was (the load average at the round's end;
the server's render wall time over its CPU time, about 2 when it has a core). Then, per case, the median and the
worst run.

``--quick``: one short case (``schedule``, one run of 100 slots) to check the bench itself. ``--reader-shm``: the
``reader`` case's stopped child on the default transport (shared memory too) instead of UDP.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import json
import math
import os
from pathlib import Path
import re
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from types import ModuleType
from typing import Any

from gsrmr_sim.machine_probe import machine_line

REPO = Path(__file__).resolve().parents[2]
ROGUE_SCRIPT = REPO / "test" / "support" / "hostile.py"  # the hostile-graph suite's rogue: run, and read here


def _rogue_module() -> ModuleType:
    """``test/support/hostile.py`` as a module (its cases, targets, /diagnostics watch and marker), loaded from its
    file: the rogue is the test suite's, not the package's, and nothing else of ``test/`` is made importable."""
    spec = importlib.util.spec_from_file_location("hostile", ROGUE_SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules["hostile"] = module
    spec.loader.exec_module(module)
    return module


_rogue = _rogue_module()
CASES, DEPLOYMENT_NODES, ROGUE_NAME, TARGETS = _rogue.CASES, _rogue.DEPLOYMENT_NODES, _rogue.ROGUE_NAME, _rogue.TARGETS
DiagnosticsWatch, named_marker = _rogue.DiagnosticsWatch, _rogue.named_marker

ALL_CASES = ("none", *CASES)
ROGUE_NICE = 19
ROUND_SLOTS, SLOT_S = 288, 0.1  # the sandbox scene's round 2
SHORT = {"gsrmr_robot": "robot", "gsrmr_server": "server", "gsrmr_scheduler": "sched", "gsrmr_limo_base": "base"}


class Monitor:
    """The bench's own participant in the demo's domain: the simulated radio's gains (by writer name) and every
    node's latest ``/diagnostics``; spun in a thread."""

    def __init__(self, domain_id: int, marker: str) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from std_msgs.msg import Float64MultiArray

        from gsrmr_common.ros_wire import channel_sample_from_msg
        from gsrmr_common.wire import CHANNEL_TOPIC

        self._rclpy, self._sample = rclpy, channel_sample_from_msg
        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=domain_id)
        self.node = rclpy.create_node("gsrmr_bench_monitor", context=self.ctx)
        self.watch = DiagnosticsWatch(self.node)
        self.watch.look_for(marker)
        self.true_gain: dict[int, float] = {}
        self._radio: set[bytes] = set()
        self.node.create_subscription(Float64MultiArray, CHANNEL_TOPIC, self._on_gain, 50)
        self.node.create_timer(0.5, self._radio_endpoints)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self._stop = False
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _radio_endpoints(self) -> None:
        from gsrmr_common.wire import CHANNEL_TOPIC

        self._radio = {bytes(i.endpoint_gid) for i in self.node.get_publishers_info_by_topic("/" + CHANNEL_TOPIC)
                       if i.node_name == "gsrmr_sim_channel"}

    def _on_gain(self, msg: Any, info: dict) -> None:
        gid = bytes((info.get("publisher_gid") or {}).get("data", b""))
        if gid in self._radio:
            sample = self._sample(msg)
            self.true_gain[sample.slot] = sample.gain

    def graph_lookup_us(self, topic: str = "/uplink/pose_key", calls: int = 200) -> float:
        """Median µs of one ``get_publishers_info_by_topic`` on the demo's graph (what a gated node pays per topic
        and refresh)."""
        times = []
        for _ in range(calls):
            t0 = time.perf_counter()
            self.node.get_publishers_info_by_topic(topic)
            times.append(time.perf_counter() - t0)
        return 1e6 * statistics.median(times)

    def _spin(self) -> None:
        while not self._stop and self.ctx.ok():
            self.ex.spin_once(timeout_sec=0.1)

    def close(self) -> None:
        self._stop = True
        self.thread.join(timeout=5)
        self.node.destroy_node()
        self._rclpy.try_shutdown(context=self.ctx)


def true_channel_figures(rows: list[dict], true_gain: dict[int, float], loss_threshold: float) -> dict:
    """Energies rescaled from the ledger's booked gain to the radio's true one (p ∝ 1/g), then the run's energy,
    the energy ratio against upload-all and the regret against the hindsight optimum over those slots."""
    from gsrmr_sim.hindsight import hindsight_summary

    fixed, missing = [], 0
    for r in rows:
        booked, true = r.get("channel_gain"), true_gain.get(int(r["slot"]))
        if booked is None or true is None or not booked > 0 or not true > 0:
            missing += 1
            continue
        scale = booked / true
        fixed.append({**r, **{c: (r[c] * scale if r.get(c) is not None else None)
                              for c in ("energy_j", "energy_upload_all_j", "energy_image_j", "energy_key_j")}})
    energy = math.fsum(r["energy_j"] for r in fixed if r["energy_j"] is not None)
    upload_all = math.fsum(r["energy_upload_all_j"] for r in fixed if r["energy_upload_all_j"] is not None)
    return {"true_energy_j": energy, "true_ratio": upload_all / energy if energy > 0 else math.nan,
            "true_regret": hindsight_summary(fixed, loss_threshold)["regret"], "slots_without_true_gain": missing}


def run_case(case: str, demo_args: list[str], out_root: Path, rogue_args: tuple[str, ...] = ()) -> dict:
    """One demo round with the rogue of ``case`` (none: no rogue): the demo's summary, the true-channel figures,
    what the nodes counted and who named the rogue."""
    from gsrmr_server.recording import read_slots_csv

    out = out_root / f"{case}-{time.strftime('%H%M%S')}"
    exe = Path(sys.executable).parent / "gsrmr-demo"
    demo = subprocess.Popen([str(exe), "--channel-seed", "3", "--out", str(out), *demo_args], stdout=subprocess.PIPE,
                            text=True, bufsize=1)
    monitor: Monitor | None = None
    rogue: subprocess.Popen | None = None
    rogue_out = out_root / f"{out.name}-rogue.json"
    rogue_name = "gsrmr_server" if case == "impostor_loss" else ROGUE_NAME
    lines: list[str] = []
    extra: dict[str, float] = {}
    progress = 0
    # the rogue lies from ~5 s into the round to its end (a timed case — the flood — lies in its middle)
    slots = int(demo_args[demo_args.index("--slots") + 1]) if "--slots" in demo_args else ROUND_SLOTS
    lie_s = max(3.0, slots * SLOT_S - 6.0)
    try:
        assert demo.stdout is not None
        for line in demo.stdout:
            lines.append(line)
            domain = re.search(r"in ROS domain (\d+)", line)
            if domain and monitor is None:
                monitor = Monitor(int(domain.group(1)), named_marker(rogue_name, case))
            if "round 2: " in line and "/" in line and " slots" in line:
                progress += 1
                if progress == 2 and case != "none" and monitor is not None:
                    env = {**os.environ, "ROS_DOMAIN_ID": domain_id(lines),
                           "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
                    with open(out_root / f"{out.name}-rogue.log", "w") as rogue_log:
                        rogue = subprocess.Popen(["nice", "-n", str(ROGUE_NICE), sys.executable,
                                                  str(ROGUE_SCRIPT), case, "--duration-s",
                                                  f"{lie_s:.1f}", "--out", str(rogue_out), *rogue_args], env=env,
                                                 stdout=rogue_log, stderr=subprocess.STDOUT)
            if "round 2: " in line and progress == 2 and monitor is not None and "graph_lookup_us" not in extra:
                extra["graph_lookup_us"] = round(monitor.graph_lookup_us(), 1)
            if "gsrmr demo — " in line and rogue is not None:  # the round is over: the rogue stops lying
                rogue.send_signal(2)
        demo.wait()
    finally:
        if rogue is not None:
            with contextlib.suppress(ProcessLookupError):
                rogue.send_signal(2)
            try:
                rogue.wait(timeout=30)
            except subprocess.TimeoutExpired:
                rogue.kill()
                rogue.wait()
        if demo.poll() is None:
            demo.terminate()
            demo.wait(timeout=60)
    if demo.returncode:
        raise SystemExit(f"{case}: gsrmr-demo exited {demo.returncode}:\n{''.join(lines[-20:])}")
    summary = json.loads(lines[-1])
    rows = [r for r in read_slots_csv(out / "slots.csv") if r.get("scored")]
    fig = {"case": case, "report_dir": str(out), **{k: summary.get(k) for k in
                                                   ("slots", "slots_on_time", "images_sent", "mean_loss", "regret",
                                                    "loss_threshold")}}
    if monitor is not None:
        time.sleep(0.5)
        fig.update(true_channel_figures(rows, monitor.true_gain, summary["loss_threshold"]))
        fig["counted"] = {n: monitor.watch.counters(n) for n in DEPLOYMENT_NODES}
        fig["named_by"] = monitor.watch.named_by(named_marker(rogue_name, case))
        monitor.close()
    fig["rogue"] = json.loads(rogue_out.read_text()) if rogue_out.exists() else {}
    fig.update(extra)
    # how loaded the machine was: the load average at the round's end, and how starved the server's render was
    # (its wall time over its CPU time, medians per slot: about 2 when it has a core, 4-5 when others take them)
    fig["load_1min"] = round(os.getloadavg()[0], 1)
    server = out / "recording" / "server_summary.json"
    stages = json.loads(server.read_text()).get("compose_ms_p50", {}) if server.exists() else {}
    if stages.get("render") and stages.get("render_cpu"):
        fig["render_wall_per_cpu"] = round(stages["render"] / stages["render_cpu"], 1)
    return fig


def domain_id(lines: list[str]) -> str:
    """The ROS domain the demo said it runs in."""
    for line in lines:
        m = re.search(r"in ROS domain (\d+)", line)
        if m:
            return m.group(1)
    raise ValueError("the demo named no ROS domain")


def counted_cells(fig: dict) -> tuple[str, str]:
    """(messages refused per node, implausible per node) as short cells."""
    refused, implausible = [], []
    for node, counted in fig.get("counted", {}).items():
        r = sum(sum(v.values()) for v in counted.get("writers_refused", {}).values()) \
            if isinstance(counted.get("writers_refused"), dict) else 0
        i = sum(counted.get("implausible", {}).values()) if isinstance(counted.get("implausible"), dict) else 0
        extra = counted.get("replans_refused")
        refused.append(f"{SHORT[node]} {r}" + (f"+{extra} replans" if extra else ""))
        implausible.append(f"{SHORT[node]} {i}")
    return ", ".join(refused), ", ".join(implausible)


COLUMNS = ("images_sent", "mean_loss", "true_regret", "true_ratio", "slots_on_time")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--cases", nargs="*", default=list(ALL_CASES), choices=list(ALL_CASES))
    ap.add_argument("--quick", action="store_true", help="one short case (schedule, 1 run of 100 slots)")
    ap.add_argument("--reader-shm", action="store_true",
                    help="the reader case's child on the default transport (shared memory included), not UDP")
    ap.add_argument("demo_args", nargs="*", help="passed to gsrmr-demo (after --)")
    args = ap.parse_args()
    if args.quick:
        args.runs, args.cases, args.demo_args = 1, ["schedule"], ["--slots", "100", *args.demo_args]
    out_root = Path(tempfile.mkdtemp(prefix="gsrmr-hostile-"))
    print(f"# bench/acceptance/hostile_graph.py: {args.runs} run(s) per case of gsrmr-demo --channel-seed 3 "
          f"{' '.join(args.demo_args)} (before the runs: {machine_line()} (gsrmr_sim.machine_probe); rogue at nice "
          f"{ROGUE_NICE}; reports in {out_root}; {time.strftime('%Y-%m-%d %H:%M')})", flush=True)
    print("| case | run | images | mean loss | regret (true channel) | energy ratio (true) | on time | refused "
          "(by writer) | implausible | named by | rogue sent |")
    print("|" + "---|" * 11)
    for case in args.cases:
        runs = []
        for k in range(args.runs):
            fig = run_case(case, args.demo_args, out_root, ("--reader-shm",) if args.reader_shm else ())
            runs.append(fig)
            refused, implausible = counted_cells(fig)
            named = ", ".join(SHORT.get(n, n) for n in fig.get("named_by", [])) or "—"
            print(f"| {case} | {k + 1} | {fig['images_sent']} | {fig['mean_loss']:.4f} | {fig['true_regret']:.2f} | "
                  f"{fig['true_ratio']:.1f} | {fig['slots_on_time']}/{fig['slots']} | {refused} | {implausible} | "
                  f"{named} | {fig['rogue'].get('sent', 0)} |", flush=True)
            notes = {k: v for k, v in fig["rogue"].items() if k in ("set_parameters", "replan_answers", "flood_hz",
                                                                   "flood_topic", "reader_ready", "recorded_image")}
            notes.update({k: fig[k] for k in ("graph_lookup_us", "slots_without_true_gain", "load_1min",
                                              "render_wall_per_cpu") if k in fig})
            if notes:
                print(f"|   | rogue: {json.dumps(notes)} |", flush=True)
        if len(runs) > 1:
            worse = {"mean_loss": max, "true_regret": max, "slots_on_time": min, "images_sent": max,
                     "true_ratio": min}
            med = " | ".join(f"{statistics.median(r[c] for r in runs):.4g}" for c in COLUMNS)
            worst = " | ".join(f"{worse[c](r[c] for r in runs):.4g}" for c in COLUMNS)
            named_all = all(not TARGETS.get(case) or set(TARGETS[case]) & set(r.get("named_by", [])) for r in runs)
            print(f"| {case} | **median** | {med} | | | {'named in every run' if named_all else 'NOT named'} | |")
            print(f"| {case} | **worst** | {worst} | | | | |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
