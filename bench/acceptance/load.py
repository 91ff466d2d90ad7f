"""The load bench (issue 45): ``gsrmr-demo`` rounds beside the loads another session of a busy workstation makes.

Usage: ``.venv/bin/python bench/acceptance/load.py [--loads idle,busy1,busy2,build,update] [--runs 3] [--seed 3]
[--lead 3] [--update-model PLY] [--update-dataset DIR] [-- DEMO_ARGS...]``.
Each load starts in a session of its own (``start_new_session``: a program started in another terminal), ``--lead``
seconds before each run, and its whole session is killed after the run (also on Ctrl-C, SIGTERM or an error). With
``kernel.sched_autogroup_enabled`` = 1 the kernel shares the CPU between sessions first, so a load takes its share
whatever its niceness. Loads: ``idle`` nothing; ``busy1`` one ``python -c "while True: pass"``; ``busy2`` two, each
in its own session; ``build`` one session of two CPU-bound threads (``python -c``: two threads each multiplying
512×512 numpy matrices with one BLAS thread, as ``make -j2`` keeps two compilers busy); ``update`` a
``gsrmr-update`` of ``--update-model`` (default: the newest ``.cache/gsrmr/sandbox-*/model-compact-*.ply`` of the
repo) on ``--update-dataset`` (default: its sibling ``round1``), restarted whenever it ends before the run does.
Every run is ``gsrmr-demo DEMO_ARGS --channel-seed SEED`` (``--seed``, default 3: the same channel every run).

Prints a Markdown table: a row per run and per load "median (worst)" (worst: the lowest for slots on time, slots
scored and the energy ratio, the highest otherwise). Columns: slots on time / slots; the JSON's ``slots_missed``,
``slots_degraded`` (by level) and ``slots_scored`` where it has them; mean MR loss, whether it is within L_th,
regret, energy ratio vs upload-all, images sent; then how late the simulated world (niced processes, not deployment
nodes) ran, over the scored slots (:mod:`gsrmr_sim.world_lateness`): ``camera age p95`` slot start − capture stamp
of the frame the robot used, plus the JSON's ``cpu`` world cores where present; ``base late p95`` the mock base's
50 Hz ticks behind their schedule; ``channel gain p95`` the radio's publish time of the slot's gain − slot start
(negative: ahead; the radio aims at −39) and how many slots the robot booked with no measured gain. ``load
cores``: CPU the load's sessions took over the demo's wall time. A demo that exits non-zero (3: its scorer scored too
few slots) or has no mean loss is a row with its exit code and last stderr line: it keeps the timing columns (on
time … scored, camera … channel) and blanks loss … images, which its median row takes from the other runs.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import json
import math
import os
from pathlib import Path
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time

from gsrmr_sim.cpu_usage import cpu_seconds_by_group
from gsrmr_sim.machine_probe import machine_line
from gsrmr_sim.world_lateness import world_lateness

REPO = Path(__file__).resolve().parents[2]
LOADS = ("idle", "busy1", "busy2", "build", "update")
BUSY = "while True: pass"
BUILD = ("import threading, numpy as np\n"
         "def work():\n"
         "    a = np.random.default_rng().random((512, 512))\n"
         "    while True:\n"
         "        a @ a\n"
         "for t in [threading.Thread(target=work) for _ in range(2)]:\n"
         "    t.start()\n")
ONE_BLAS_THREAD = {k: "1" for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
HEADER = ("load", "run", "slots on time", "missed", "degraded", "scored", "mean loss", "≤ L_th", "regret",
          "energy ratio", "images", "camera age p95 ms", "base late p95 ms", "channel gain p95 ms vs slot start",
          "load cores", "wall s", "note")


def _exit_on_sigterm(signum: int, _frame: object) -> None:
    raise SystemExit(128 + signum)


def _die_with_parent() -> None:  # in the child before exec: SIGKILL when the bench dies (even by SIGKILL)
    with contextlib.suppress(Exception):
        ctypes.CDLL(None).prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG


def _cli(name: str) -> str:
    return str(Path(sys.executable).parent / name)


class Load:
    """A named load: its processes, each the leader of a session of its own; ``restart`` starts one again when it
    ends while the load runs (``gsrmr-update``)."""

    def __init__(self, name: str, argvs: list[list[str]], env: dict[str, str] | None = None,
                 restart: bool = False, workdir: Path | None = None) -> None:
        self.name, self.argvs, self.env, self.restart, self.workdir = name, argvs, env, restart, workdir
        self.procs: list[subprocess.Popen | None] = []
        self.starts, self.exits, self.last_line = 0, [], ""
        self.cpu_first: dict[int, float] = {}
        self.cpu_last: dict[int, float] = {}

    def _popen(self, i: int) -> subprocess.Popen:
        argv = [a.replace("{n}", str(self.starts)) for a in self.argvs[i]]
        self.starts += 1
        log = open(self.workdir / "load.log", "a") if self.workdir else subprocess.DEVNULL  # noqa: SIM115
        try:
            return subprocess.Popen(argv, env={**os.environ, **(self.env or {})}, stdin=subprocess.DEVNULL,
                                    stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
                                    preexec_fn=_die_with_parent)
        finally:
            if self.workdir:
                log.close()

    def start(self) -> None:
        for i in range(len(self.argvs)):  # one by one: stop() reaches those started before an interruption
            self.procs.append(self._popen(i))

    def tick(self, now_cpu: dict[int, float]) -> None:
        """Note the CPU of every live session of the load; restart one that ended (``restart``)."""
        for i, proc in enumerate(self.procs):
            if proc is None:
                continue
            if proc.pid in now_cpu:
                self.cpu_first.setdefault(proc.pid, now_cpu[proc.pid])
                self.cpu_last[proc.pid] = now_cpu[proc.pid]
            rc = proc.poll()
            if rc is not None and self.restart:
                self.exits.append(rc)
                self._note_last_line()
                self.procs[i] = self._popen(i)
                self.cpu_first[self.procs[i].pid] = 0.0  # born inside the window

    def cpu_s(self) -> float:
        return sum(self.cpu_last[p] - self.cpu_first[p] for p in self.cpu_last)

    def stop(self) -> None:
        """Kill every session of the load (``killpg``: the leader's group) and reap the leaders."""
        for proc in self.procs:
            if proc is not None:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(proc.pid, signal.SIGKILL)
        for proc in self.procs:
            if proc is not None:
                proc.wait()
        self.procs = []

    def _note_last_line(self) -> None:
        if self.workdir and (self.workdir / "load.log").exists():
            lines = [ln for ln in (self.workdir / "load.log").read_text(errors="replace").splitlines() if ln.strip()]
            self.last_line = lines[-1][:160] if lines else ""

    def note(self) -> str:
        if not self.restart:
            return ""
        ends = f", ended {len(self.exits)}× (exit {','.join(map(str, self.exits))})" if self.exits else ""
        failed = f"; its last line: {self.last_line}".replace("|", "\\|") if any(self.exits) else ""
        return f"{self.starts} start(s){ends}{failed}"


def make_load(name: str, model: Path | None, dataset: Path | None, workdir: Path) -> Load | None:
    if name == "idle":
        return Load(name, [])
    if name in ("busy1", "busy2"):
        return Load(name, [[sys.executable, "-c", BUSY]] * int(name[-1]))
    if name == "build":
        return Load(name, [[sys.executable, "-c", BUILD]], env=ONE_BLAS_THREAD)
    if model is None or dataset is None:
        return None
    return Load(name, [[_cli("gsrmr-update"), str(workdir / "models{n}"), "--init", str(model),
                        "--received", str(dataset), "--mapping", str(dataset)]], restart=True, workdir=workdir)


def default_update_inputs() -> tuple[Path | None, Path | None]:
    models = sorted(REPO.glob(".cache/gsrmr/sandbox-*/model-compact-*.ply"), key=lambda p: p.stat().st_mtime)
    if not models:
        return None, None
    return models[-1], models[-1].parent / "round1"


def run_demo(demo_args: list[str], loads: list[Load], workdir: Path) -> dict:
    """One ``gsrmr-demo`` run while ``loads`` run (ticked every 0.5 s); its summary or ``error``."""
    out_path, err_path = workdir / "demo.out", workdir / "demo.err"
    t0 = time.perf_counter()
    with open(out_path, "w") as out, open(err_path, "w") as err:
        proc = subprocess.Popen([_cli("gsrmr-demo"), *demo_args], stdin=subprocess.DEVNULL, stdout=out, stderr=err)
    try:
        while True:
            now = cpu_seconds_by_group()
            for load in loads:
                load.tick(now)
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(timeout=0.5)
                break
    except BaseException:  # Ctrl-C / SIGTERM: let the demo stop its nodes (it handles SIGTERM)
        proc.terminate()
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        raise
    wall_s = time.perf_counter() - t0
    lines = [ln for ln in out_path.read_text(errors="replace").splitlines() if ln.strip()]
    errs = [ln for ln in err_path.read_text(errors="replace").splitlines() if ln.strip()]
    summary: dict = {}
    with contextlib.suppress(IndexError, json.JSONDecodeError):
        summary = json.loads(lines[-1])
        summary = summary if isinstance(summary, dict) else {}
    summary["wall_s"] = wall_s
    if "report_dir" in summary:
        lateness, problems = world_lateness(Path(summary["report_dir"]))
        summary.update(lateness)
        if problems:
            summary["note"] = "; ".join(problems)[:160]
    loss = summary.get("mean_loss")
    if proc.returncode or not isinstance(loss, (int, float)) or math.isnan(loss):
        last = errs[-1] if errs else (lines[-1] if lines else "")
        summary["error"] = f"exit {proc.returncode}: {last[:200]}"
    return summary


def _num(v: object, fmt: str) -> str:
    return "" if not isinstance(v, (int, float)) or math.isnan(v) else format(v, fmt)


def _within(s: dict) -> str:
    if not isinstance(s.get("loss_threshold"), (int, float)):
        return ""
    return "yes" if s["mean_loss"] <= s["loss_threshold"] else "no"


def _world(s: dict) -> list[str]:
    """The simulated world's cells: camera age (and world cores), base lateness, channel gain (and no-gain slots)."""
    cpu = s.get("cpu") if isinstance(s.get("cpu"), dict) else {}
    extra = f"; world {cpu['world_cores']:.2f} cores" if isinstance(cpu.get("world_cores"), (int, float)) else ""
    no_gain = s.get("channel_no_gain_slots")
    no_gain = f"; {no_gain} no gain" if isinstance(no_gain, int) else ""
    return [_num(s.get("world_age_p95_ms"), ".0f") + extra, _num(s.get("base_late_p95_ms"), ".1f"),
            _num(s.get("channel_gain_p95_ms"), ".0f") + no_gain]


def _cells(s: dict, note: str) -> list[str]:
    """The figure cells of one run (after load and run). A run that failed (``error``) keeps the figures of its
    loop's timing and blanks those its demo says do not stand (loss, L_th, regret, energy, images)."""
    degraded = s.get("slots_degraded")
    timing = [f"{s['slots_on_time']}/{s['slots']}" if "slots_on_time" in s and "slots" in s else "",
              _num(s.get("slots_missed"), ".0f"),
              json.dumps(degraded, separators=(",", ":")) if isinstance(degraded, dict) else "",
              _num(s.get("slots_scored"), ".0f")]
    if "error" in s:
        measured = [""] * 5
        note = "; ".join(filter(None, [s["error"].replace("|", "\\|"), note]))
    else:
        measured = [_num(s["mean_loss"], ".4f"), _within(s), _num(s.get("regret"), ".3g"),
                    _num(s.get("energy_ratio_vs_upload_all"), ".3g"), _num(s.get("images_sent"), ".0f")]
    return [*timing, *measured, *_world(s), _num(s.get("load_cores"), ".2f"), _num(s["wall_s"], ".0f"),
            "; ".join(filter(None, [note, s.get("note", "")]))]


def _median_worst(values: list, worst, fmt: str) -> str:
    values = [v for v in values if isinstance(v, (int, float)) and not math.isnan(v)]
    if not values:
        return ""
    return f"{format(statistics.median(values), fmt)} ({format(worst(values), fmt)})"


def summary_row(name: str, runs: list[dict]) -> str:
    """Median (worst) per column: the timing columns over every run with a summary, the rest over those that
    stand (no ``error``)."""
    ok = [s for s in runs if "error" not in s]
    timed = [s for s in runs if "slots_on_time" in s]
    slots = {s.get("slots") for s in timed}
    on_time = _median_worst([s["slots_on_time"] for s in timed], min, ".0f")
    on_time += f" of {slots.pop()}" if on_time and len(slots) == 1 else ""
    by_level = [s["slots_degraded"] for s in timed if isinstance(s.get("slots_degraded"), dict)]
    degraded = "; ".join(f"{k}: {_median_worst([d.get(k, 0) for d in by_level], max, '.0f')}"
                         for k in sorted({k for d in by_level for k in d}))
    no_gain = _median_worst([s.get("channel_no_gain_slots") for s in timed], max, ".0f")
    cells = [on_time, _median_worst([s.get("slots_missed") for s in timed], max, ".0f"), degraded,
             _median_worst([s.get("slots_scored") for s in timed], min, ".0f"),
             _median_worst([s["mean_loss"] for s in ok], max, ".4f"),
             f"{sum(_within(s) == 'yes' for s in ok)}/{len(ok)}" if ok else "",
             _median_worst([s.get("regret") for s in ok], max, ".3g"),
             _median_worst([s.get("energy_ratio_vs_upload_all") for s in ok], min, ".3g"),
             _median_worst([s.get("images_sent") for s in ok], max, ".0f"),
             _median_worst([s.get("world_age_p95_ms") for s in timed], max, ".0f"),
             _median_worst([s.get("base_late_p95_ms") for s in timed], max, ".1f"),
             "; ".join(filter(None, [_median_worst([s.get("channel_gain_p95_ms") for s in timed], max, ".0f"),
                                     no_gain and f"{no_gain} no gain"])),
             _median_worst([s.get("load_cores") for s in runs], max, ".2f"),
             _median_worst([s["wall_s"] for s in runs], max, ".0f"),
             f"{len(runs) - len(ok)} of {len(runs)} failed: loss … images of {len(ok)}" if len(ok) < len(runs) else ""]
    return f"| **{name}** | median (worst) | " + " | ".join(cells) + " |"


def main() -> int:
    signal.signal(signal.SIGTERM, _exit_on_sigterm)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 epilog="See the module docstring (bench/acceptance/load.py) for the columns.")
    ap.add_argument("--loads", default=",".join(LOADS), help=f"comma-separated, of {', '.join(LOADS)} (default: all)")
    ap.add_argument("--runs", type=int, default=3, help="demo runs per load (default 3)")
    ap.add_argument("--seed", type=int, default=3, help="gsrmr-demo --channel-seed of every run (default 3)")
    ap.add_argument("--lead", type=float, default=3.0, help="seconds the load runs before each demo (default 3)")
    ap.add_argument("--update-model", type=Path, default=None,
                    help="the update load's --init model (default: newest .cache/gsrmr/sandbox-*/model-compact-*.ply)")
    ap.add_argument("--update-dataset", type=Path, default=None,
                    help="the update load's --received/--mapping dataset (default: the model's sibling round1)")
    ap.add_argument("demo_args", nargs="*", help="passed to gsrmr-demo (after --)")
    args = ap.parse_args()
    names = [n.strip() for n in args.loads.split(",") if n.strip()]
    if unknown := [n for n in names if n not in LOADS]:
        ap.error(f"unknown load(s) {unknown}; choose from {', '.join(LOADS)}")
    model, dataset = default_update_inputs()
    model = args.update_model or model
    dataset = args.update_dataset or (model.parent / "round1" if args.update_model and model else dataset)
    demo_args = [*args.demo_args, "--channel-seed", str(args.seed)]
    autogroup = Path("/proc/sys/kernel/sched_autogroup_enabled")
    autogroup = autogroup.read_text().strip() if autogroup.exists() else "n/a"
    print(f"# bench/acceptance/load.py: loads {', '.join(names)}; {args.runs} run(s) each of gsrmr-demo "
          f"{' '.join(demo_args)}; each load in its own session(s) from {args.lead:g} s before a run "
          f"(kernel.sched_autogroup_enabled = {autogroup}; before the runs: {machine_line()} "
          f"(gsrmr_sim.machine_probe))", flush=True)
    missing = [str(p) for p in (model, dataset) if p is not None and not p.exists()]
    if "update" in names and (model is None or dataset is None or missing):
        why = f"missing {', '.join(missing)}" if missing else \
            "no .cache/gsrmr/sandbox-*/model-compact-*.ply in the repo (give --update-model, --update-dataset)"
        print(f"# update load skipped: {why}", flush=True)
        names.remove("update")
    elif "update" in names:
        print(f"# update load: gsrmr-update --init {model} --received {dataset} --mapping {dataset}", flush=True)
    print("| " + " | ".join(HEADER) + " |")
    print("|" + "---|" * len(HEADER), flush=True)
    with tempfile.TemporaryDirectory(prefix="gsrmr-load-bench-") as tmp:
        for name in names:
            runs = []
            for k in range(args.runs):
                workdir = Path(tmp) / f"{name}-{k + 1}"
                workdir.mkdir()
                load = make_load(name, model, dataset, workdir)
                assert load is not None
                print(f"[load bench] {name} run {k + 1}/{args.runs}", file=sys.stderr, flush=True)
                try:
                    load.start()
                    time.sleep(args.lead)
                    s = run_demo(demo_args, [load], workdir)
                finally:
                    load.stop()
                s["load_cores"] = load.cpu_s() / s["wall_s"]
                runs.append(s)
                print(f"| {name} | {k + 1} | " + " | ".join(_cells(s, load.note())) + " |", flush=True)
                shutil.rmtree(workdir, ignore_errors=True)
            print(summary_row(name, runs), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
