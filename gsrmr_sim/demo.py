"""``gsrmr-demo`` (``make demo``): the paper's system end to end on the embedded sandbox scene.

1. Build the scene's GS model from round 1 (the robot's mapping lap, recorded by the world simulator,
   trained with the CPU engine) — cached under ``--cache`` keyed by the scene file and settings.
2. Seed the scheduler's loss map with L_t of the model along the route's slot poses, against the
   *mapping round's* world (what exists before round 2; no change events) — the running system keeps
   correcting the map online from the losses it measures in image slots (cached). ``--oracle`` seeds it
   from a headless rehearsal of round 2 itself instead and lets the scheduler plan with the simulator's
   future channel: the paper's assumptions, reported as the upper bound they are.
3. Run round 2 in real time over DDS, every node a separate process (the list of
   :func:`gsrmr_sim.sim_stack.sim_stack`, the same as ``sim.launch.py``): mock LIMO on a pty, LIMO
   driver, mock camera, simulated radio (the true channel, seeded by ``--channel-seed`` and the slot's
   index in the round), route follower, robot, server, scheduler.
4. Summarise from the server's per-slot log (loss/PSNR/SSIM of the MR images actually produced against
   the simulator's ground truth, energy from the robot's ledger) and, after the run, the hindsight
   optimum over what either choice would have cost and given in each slot (``regret`` = energy /
   hindsight energy); write the report folder: MR image strip, x/p profile plot, ``slots.csv`` (with
   ``scored``), ``run.mcap``, ``summary.json``. The last stdout line is the summary as one JSON object.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
import contextlib
from dataclasses import dataclass
import json
import math
import os
from pathlib import Path
import random
import shutil
import signal
import sys
import time
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from gsrmr_sim.models import BuiltModel

REPO = Path(__file__).resolve().parents[1]


def _log(msg: str) -> None:
    print(f"[demo {time.strftime('%H:%M:%S')}] {msg}", flush=True)


def ensure_survey(scene_name: str, model_path: Path, slots: int, round_index: int = 1) -> Path:
    """Seed loss map JSON (cached beside the model): L_t of the model along the route's slot poses against
    the world of round ``round_index`` — 1, the mapping round (what exists before round 2: its frames and
    the model; the default), or 2, a rehearsal of the very round being scored (the ``--oracle`` mode)."""
    from gsrmr_server.splatting.model import GaussianModel
    from gsrmr_sim.sim_stack import config_dir, robot_jpeg_quality
    from gsrmr_sim.survey import SURVEY_VERSION, gs_losses, loss_map_from
    from gsrmr_sim.world.recorder import Round2Record, record_round2
    from gsrmr_sim.world.scene import load_scene

    quality = robot_jpeg_quality(str(config_dir() / "robot.yaml"))  # what an image slot leaves (JPEG)
    # L_t depends on the model; the image-slot loss on the robot's JPEG quality
    out = model_path.parent / f"loss_map_{model_path.stem}_{slots}_round{round_index}_q{quality}_v{SURVEY_VERSION}.json"
    if out.exists():
        _log(f"loss-map seed cached: {out}")
        return out
    scene = load_scene(scene_name)
    t0 = time.perf_counter()
    rec_dir = record_round2(scene, model_path.parent / f"survey_round{round_index}_{slots}", slots=slots,
                            round_index=round_index)
    losses = gs_losses(Round2Record(rec_dir), GaussianModel.load_ply(model_path), scene.background,
                       mr_content=scene.mr_content, jpeg_quality=quality)
    seed = loss_map_from(losses)
    seed.save(out)
    values = np.array([s.loss for s in losses])
    _log(f"round-{round_index} survey: {slots} slots, GS loss mean {values.mean():.4f}, max {values.max():.4f}; "
         f"image slot (JPEG q{quality}) {seed.image_loss:.4f} ({time.perf_counter() - t0:.1f} s)")
    return out


def run_stack(*, scene: str, model_path: Path, loss_map: Path, run_dir: Path, loss_threshold: float,
              slots: int, method: str, timeout_s: float, channel_seed: int | None = None,
              oracle_channel: bool = False, hosts: int = 1, uplink_mbit: float = 5.0,
              link_events: Sequence[LinkEvent] = (), link_log: dict | None = None,
              overrides: dict[str, dict] | None = None) -> tuple[list[dict], int]:
    """Start every node as a process over DDS; stop after ``slots`` composed slots; return the rows.
    ``overrides``: parameters per node name on top of the stack's (``gsrmr-demo --param``).

    ``hosts`` = 2 runs the robot's processes and the server's in two network namespaces joined by a veth
    pair limited to ``uplink_mbit`` (:class:`gsrmr_sim.netns.TwoHosts`), DDS over UDPv4 across it, the
    ground-truth frames over the simulation backplane (:mod:`gsrmr_common.truth_frames`); ``link_events``
    then change the link during the round, and ``link_log`` (a dict) receives the link's byte counters.
    """
    from gsrmr_server.recording import read_slots_csv
    from gsrmr_sim.sim_stack import environment, sim_stack
    from gsrmr_sim.supervisor import ProcessStack

    domain = random.Random(os.getpid() ^ time.time_ns()).randrange(1, 101)
    link = f"/tmp/gsrmr_limo_{os.getpid()}"
    truth_dir = str(run_dir / "truth_frames") if hosts == 2 else ""
    specs = sim_stack(scene=scene, model_path=str(model_path), record_dir=str(run_dir / "recording"),
                      loss_threshold=loss_threshold, link_path=link, laps=1, method=method,
                      loss_map_file=str(loss_map), state_dir=str(run_dir / "scheduler_state"),
                      channel_seed=channel_seed, oracle_channel=oracle_channel, truth_dir=truth_dir,
                      overrides=overrides)
    stack = ProcessStack(environment(domain), run_dir / "logs", params_dir=run_dir / "params")
    net = None
    placement: dict[str, dict] = {}
    if hosts == 2:
        from gsrmr_sim.netns import TwoHosts

        net = TwoHosts(uplink_mbit=uplink_mbit, domain_id=domain).open()
        for spec in specs:
            ns = net.robot_ns if spec.host == "robot" else net.server_ns
            placement[spec.name] = {"prefix": ["ip", "netns", "exec", ns], "env": net.environment(stack.env)}
        _log(f"two hosts: robot {net.robot_ns} ({net.robot_ip}), server {net.server_ns} ({net.server_ip}), "
             f"uplink limited to {uplink_mbit:g} Mbit/s, DDS over UDPv4")
    _log(f"starting {len(specs)} processes in ROS domain {domain}")
    csv_path = run_dir / "recording" / "slots.csv"
    events = sorted(link_events, key=lambda e: e.at_slot)
    try:
        # The route follower (which sets the robot in motion) starts last, once the server composes:
        # round 2 then begins with every node up and warm, as a run on the real system would; the mock
        # camera starts its round clock (change events, virtual agents) when the robot moves, in step
        # with the survey's round 2.
        last = ("gsrmr-route-follower",)
        for spec in specs:
            if spec.executable not in last:
                # the pty must exist before the driver opens it
                stack.start(spec.name, spec, wait_for_path=link if spec.executable == "gsrmr-mock-limo" else None,
                            **placement.get(spec.name, {}))
        warm = time.monotonic() + 60
        while time.monotonic() < warm and len(read_slots_csv(csv_path) if csv_path.exists() else []) < 10:
            time.sleep(0.2)
        for spec in specs:
            if spec.executable in last:
                stack.start(spec.name, spec, **placement.get(spec.name, {}))
        if net is not None and link_log is not None:
            link_log["start"] = net.link_bytes()
        deadline = time.monotonic() + timeout_s
        first_moving: int | None = None
        rows: list[dict] = []
        last_report = 0.0
        while time.monotonic() < deadline:
            time.sleep(0.5)
            stack.check()
            if not csv_path.exists():
                continue
            rows = read_slots_csv(csv_path)
            if first_moving is None:
                first_moving = first_round_row(rows)
            while net is not None and events and first_moving is not None \
                    and len(rows) - first_moving >= events[0].at_slot:
                event = events.pop(0)
                event.apply(net)
                if link_log is not None:
                    link_log.setdefault("events", []).append(
                        {**event.as_dict(), "applied_after_slot": len(rows) - first_moving,
                         "wall_s": time.time()})
                _log(f"link: {event.describe()} (round slot ~{len(rows) - first_moving})")
            if first_moving is not None and len(rows) - first_moving >= slots:
                break
            if time.monotonic() - last_report > 5:
                done = 0 if first_moving is None else len(rows) - first_moving
                _log(f"round 2: {done}/{slots} slots")
                last_report = time.monotonic()
        else:
            raise TimeoutError(f"round 2 did not produce {slots} slots in {timeout_s:.0f} s")
    finally:
        if net is not None and link_log is not None and "start" in link_log:
            with contextlib.suppress(Exception):
                link_log["end"] = net.link_bytes()
        for name, took in stack.stop().items():
            if took >= stack.stop_timeout_s:
                _log(f"{name} ignored SIGINT for {stack.stop_timeout_s:.0f} s; killed")
        if net is not None:
            net.close()
        if truth_dir:
            shutil.rmtree(truth_dir, ignore_errors=True)
        if os.path.islink(link):
            os.unlink(link)
    rows = read_slots_csv(csv_path)
    return rows[first_moving:first_moving + slots], first_moving


@dataclass(frozen=True)
class LinkEvent:
    """A change of the two-host link once the round has composed ``at_slot`` slots: ``down`` (link down),
    ``up`` (link back up) or ``rate`` (``mbit`` Mbit/s on the uplink)."""

    at_slot: int
    action: str
    mbit: float = 0.0

    def apply(self, net: object) -> None:
        """Apply to a :class:`gsrmr_sim.netns.TwoHosts`."""
        if self.action in ("down", "up"):
            net.set_link(self.action == "up")  # type: ignore[attr-defined]
        elif self.action == "rate":
            net.set_rate(self.mbit)  # type: ignore[attr-defined]
        else:
            raise ValueError(f"unknown link action {self.action!r}")

    def describe(self) -> str:
        return f"rate {self.mbit:g} Mbit/s" if self.action == "rate" else f"link {self.action}"

    def as_dict(self) -> dict:
        rate = {"mbit": self.mbit} if self.action == "rate" else {}
        return {"at_slot": self.at_slot, "action": self.action, **rate}


def parse_params(items: Sequence[str]) -> dict[str, dict]:
    """``["gsrmr_robot:jpeg_quality=70", …]`` → ``{"gsrmr_robot": {"jpeg_quality": 70}}`` (values parsed as YAML)."""
    import yaml

    out: dict[str, dict] = {}
    for item in items:
        node, sep, rest = item.partition(":")
        name, eq, value = rest.partition("=")
        if not (sep and eq and node and name):
            raise ValueError(f"--param {item!r}: expected NODE:NAME=VALUE")
        out.setdefault(node, {})[name] = yaml.safe_load(value)
    return out


def parse_link_events(text: str) -> list[LinkEvent]:
    """``"down@100,up@120,rate=1.5@150"`` → link events at round slots 100, 120 and 150."""
    events = []
    for item in filter(None, (t.strip() for t in text.split(","))):
        what, _, at = item.partition("@")
        if not at.isdigit():
            raise ValueError(f"link event {item!r}: expected ACTION@SLOT")
        action, _, mbit = what.partition("=")
        if action not in ("down", "up", "rate") or (action == "rate") != bool(mbit):
            raise ValueError(f"link event {item!r}: ACTION is down, up or rate=MBIT")
        events.append(LinkEvent(int(at), action, float(mbit) if mbit else 0.0))
    return events


def first_round_row(rows: list[dict]) -> int | None:
    """Index of the row of the round's first slot: where the radio's ``round_slot`` (through the robot's
    ledger) is 0 — the slot the channel's fading index starts from, so runs with one channel seed score
    the same fading; without round slots (no radio), the first slot whose pose key moved."""
    for i, r in enumerate(rows):
        k = r.get("round_slot")
        if k is not None and k >= 0:
            return max(0, i - int(k))
    return first_moving_slot(rows)


def first_moving_slot(rows: list[dict]) -> int | None:
    """Index of the first row whose pose key has moved from the first keyed pose: round 2 starts when
    the robot sets off (the mock camera starts its round clock then too). None before that."""
    from gsrmr_sim.world.kinematics import has_moved

    rest = None
    for i, r in enumerate(rows):
        if r["pose_a_m"] is None or r["source"] not in ("image", "render"):
            continue
        pose = (r["pose_a_m"], r["pose_b_m"], r["pose_theta_rad"])
        rest = rest or pose
        if has_moved(pose, rest):
            return i
    return None


def summarise(rows: list[dict], slot_s: float) -> dict:
    """Headline figures of a run from its per-slot rows."""
    from gsrmr_common.metrics import pooled_psnr_db

    def col(name: str) -> np.ndarray:
        return np.array([r[name] for r in rows if r[name] is not None], dtype=np.float64)

    energy, upload_all = col("energy_j").sum(), col("energy_upload_all_j").sum()
    return {"slots": len(rows), "slots_on_time": int((col("latency_ms") <= 1e3 * slot_s).sum()),
            "images_sent": int(sum(1 for r in rows if r["source"] == "image")),
            "energy_j": float(energy), "energy_upload_all_j": float(upload_all),
            "energy_ratio_vs_upload_all": float(upload_all / energy) if energy > 0 else math.nan,
            "mean_loss": float(col("loss").mean()) if col("loss").size else math.nan,
            # the two PSNRs of every report (docs/experiments.md, "Metrics"): pooled, and the per-slot mean
            "psnr_db": pooled_psnr_db(col("psnr_db")),
            "psnr_slot_mean_db": float(col("psnr_db").mean()) if col("psnr_db").size else math.nan,
            "ssim": float(col("ssim").mean()) if col("ssim").size else math.nan,
            "faults": sum(1 for r in rows if r["faults"])}


def link_summary(link_log: dict, rows: list[dict], uplink_mbit: float) -> dict:
    """What crossed the two-host link (veth byte counters from the round's start to the stack's stop) beside
    what the robot's ledger says it sent in the scored slots (images and keys, payload only)."""
    start, end = link_log.get("start"), link_log.get("end")
    if not (start and end):
        return {"uplink_mbit": uplink_mbit}
    up, down = end["uplink"] - start["uplink"], end["downlink"] - start["downlink"]
    duration_s = max(1e-9, end.get("wall_s", 0.0) - start.get("wall_s", 0.0))
    return {"uplink_mbit": uplink_mbit, "link_uplink_bytes": int(up), "link_downlink_bytes": int(down),
            "link_seconds": round(duration_s, 2), "link_uplink_mbit_mean": 8e-6 * up / duration_s,
            "ledger_bytes_sent": int(sum(r["bytes_sent"] or 0 for r in rows)),
            "link_uplink_dropped_packets": int(end.get("uplink_dropped", 0) - start.get("uplink_dropped", 0)),
            "link_events": link_log.get("events", [])}


def copy_recording(out: Path, recording: Path, first_moving: int, scored: int) -> None:
    """The report's copies of the server's recording: ``run.mcap``, and ``slots.csv`` with ``scored`` marking
    the ``scored`` rows of the round from row ``first_moving`` on."""
    if (recording / "run.mcap").exists():
        (out / "run.mcap").write_bytes((recording / "run.mcap").read_bytes())
    if (recording / "slots.csv").exists():  # the report's copy marks the scored round
        from gsrmr_server.recording import read_slots_csv, write_slots_csv

        every = read_slots_csv(recording / "slots.csv")
        for i, row in enumerate(every):
            row["scored"] = int(first_moving <= i < first_moving + scored)
        write_slots_csv(out / "slots.csv", every)


def run_summary(args: argparse.Namespace, rows: list[dict], slot_s: float, built: BuiltModel,
                channel_seed: int | None) -> dict:
    """The summary of one robot's round (the demo's JSON without hosts, link and report folder): headline
    figures, the model, the settings and the hindsight optimum."""
    from gsrmr_sim.hindsight import hindsight_summary

    return {"scene": args.scene, "loss_threshold": args.loss_threshold, **summarise(rows, slot_s),
            "model_gaussians": built.model.num_gaussians, "model_heldout_psnr_db": built.heldout_psnr_db,
            "model_compacted": not args.no_compact, "channel_seed": channel_seed, "oracle": args.oracle,
            "method": args.method, "loss_map_seed": "round-2 survey (oracle)" if args.oracle else "mapping round",
            **hindsight_summary(rows, args.loss_threshold)}


def write_report(report_dir: Path, rows: list[dict], summary: dict) -> None:
    """x/p profile plot, MR image strip, CSV copy, summary.json."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from gsrmr_server.recording import TOPIC_MR_IMAGE, read_mcap

    report_dir.mkdir(parents=True, exist_ok=True)
    slots = np.arange(len(rows))
    x = np.array([r["x"] if r["x"] is not None else np.nan for r in rows], float)
    p = np.array([r["power_w"] if r["power_w"] is not None else np.nan for r in rows], float)
    fig, ax = plt.subplots(2, 1, figsize=(9, 4.5), sharex=True)
    ax[0].step(slots, x, where="post")
    ax[0].set_ylabel("x_t (1 = image)")
    ax[1].semilogy(slots, np.where(p > 0, p, np.nan), ".", ms=3)
    ax[1].set_ylabel("p_t [W]")
    ax[1].set_xlabel("slot")
    fig.suptitle(f"content switching and power (energy ratio vs upload-all "
                 f"{summary['energy_ratio_vs_upload_all']:.1f}×)")
    fig.tight_layout()
    fig.savefig(report_dir / "profile_x_p.png", dpi=120)
    plt.close(fig)
    mcap = report_dir / "run.mcap"
    if mcap.exists():
        import cv2

        wanted = {r["slot"] for r in rows[:: max(1, len(rows) // 6)][:6]}
        by_stamp_ms = {round(r["stamp_s"] * 1e3): r for r in rows if r.get("stamp_s") is not None}
        tiles = []
        for topic, _, msg in read_mcap(mcap):
            if topic != TOPIC_MR_IMAGE:
                continue
            # the MR image's stamp is its slot's start (slots.csv stamp_s): match them to the millisecond
            row = by_stamp_ms.get(round(msg.header.stamp.sec * 1e3 + msg.header.stamp.nanosec / 1e6))
            k = row["slot"] if row is not None else None
            if k in wanted:
                img = cv2.imdecode(np.frombuffer(bytes(msg.data), np.uint8), cv2.IMREAD_COLOR)
                cv2.putText(img, f"slot {k - rows[0]['slot']} {row['source']}", (4, 14), cv2.FONT_HERSHEY_SIMPLEX,
                            0.45, (255, 255, 255), 1)
                tiles.append(img)
        if tiles:
            cv2.imwrite(str(report_dir / "mr_strip.png"), np.hstack(tiles))
    (report_dir / "summary.json").write_text(json.dumps(summary, indent=1))


def _exit_on_sigterm(signum: int, _frame: object) -> None:
    """SIGTERM (``kill``, a CI runner's timeout) as an exit: the stack's ``finally`` stops every node."""
    raise SystemExit(128 + signum)


def main(argv: Sequence[str] | None = None) -> int:
    """Console script ``gsrmr-demo``."""
    signal.signal(signal.SIGTERM, _exit_on_sigterm)
    ap = argparse.ArgumentParser(prog="gsrmr-demo", description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="sandbox")
    ap.add_argument("--loss-threshold", type=float, default=0.03)
    ap.add_argument("--method", default="exact")
    ap.add_argument("--slots", type=int, default=0, help="slots of round 2 (0 = the scene's T)")
    ap.add_argument("--cache", default=str(REPO / ".cache" / "gsrmr"))
    ap.add_argument("--out", default="", help="report folder (default reports/demo-<time>)")
    ap.add_argument("--frames", type=int, default=0, help="round-1 frames H (0 = the scene's)")
    ap.add_argument("--train-iterations", type=int, default=None,
                    help="GS training steps (default: the scene's model.train_iterations, else 2000; deterministic: "
                         "the same model on any machine and load)")
    ap.add_argument("--train-seconds", type=float, default=None,
                    help="train for this wall time instead of a step count (the model then depends on the machine "
                         "and its load)")
    ap.add_argument("--train-width", type=int, default=None,
                    help="GS training width in px (default: the scene's model.train_width_px, else 160)")
    ap.add_argument("--budget", type=int, default=None,
                    help="Gaussian budget of the trained model (default: the scene's model.budget, else 100k): "
                         "render time per slot grows with it (docs/splatting.md)")
    ap.add_argument("--max-psnr-drop-db", type=float, default=0.3,
                    help="compact the trained model to the smallest one within this held-out PSNR loss "
                         "(gsrmr-compact; bench/compact.py: sandbox 97k → 17k Gaussians at −0.21 dB)")
    ap.add_argument("--no-compact", action="store_true", help="run on the trained (uncompacted) model")
    ap.add_argument("--channel-seed", type=int, default=7,
                    help="seed of the simulated channel: the fading of the k-th slot of round 2 depends only "
                         "on (seed, k), so two runs with one seed see the same channel")
    ap.add_argument("--oracle", action="store_true",
                    help="the oracle-fed upper bound: the scheduler plans with the simulator's future channel "
                         "realisation and a loss map surveyed on the very round being scored (by default it "
                         "plans with the channel's statistics and a map of the mapping round)"),
    ap.add_argument("--hosts", type=int, choices=(1, 2), default=1,
                    help="2: the robot's processes and the server's in two network namespaces joined by a veth pair "
                         "(DDS over UDPv4 across it; needs root and iproute2)")
    ap.add_argument("--uplink-mbit", type=float, default=5.0,
                    help="with --hosts 2: the robot → server rate limit in Mbit/s (tbf)")
    ap.add_argument("--link-events", default="",
                    help="with --hosts 2: link changes during the round, e.g. 'down@100,up@120,rate=1.5@150' "
                         "(ACTION@SLOT, SLOT = composed round slots)")
    ap.add_argument("--robots", type=int, default=None, metavar="N",
                    help="a fleet: N robots at once (namespaces /robot1 … /robotN, each with its own server, "
                         "scheduler and simulated world; channel seed + k - 1 for robot k), one report folder per "
                         "robot and fleet totals (gsrmr_sim.fleet); without it, the single robot in the root "
                         "namespace (default)")
    ap.add_argument("--param", action="append", default=[], metavar="NODE:NAME=VALUE",
                    help="set a node's parameter on top of the stack's (YAML value), e.g. "
                         "gsrmr_robot:hold_images_while_queued=false; repeatable")
    args = ap.parse_args(argv)
    try:
        args.overrides = parse_params(args.param)
    except ValueError as e:
        ap.error(str(e))
    if args.robots is not None and args.robots < 1:
        ap.error("--robots must be >= 1")
    try:
        link_events = parse_link_events(args.link_events)
    except ValueError as e:
        ap.error(str(e))
    if args.hosts == 2:
        from gsrmr_sim.netns import unavailable_reason

        reason = unavailable_reason()
        if reason:
            print(f"gsrmr-demo --hosts 2: {reason}", file=sys.stderr)
            return 2
        if not args.uplink_mbit > 0:
            ap.error("--uplink-mbit must be > 0")
        if args.oracle:  # the oracle reads the simulator's channel on the server: simulation traffic on the uplink
            ap.error("--oracle reads the simulated radio on the server side; it is not run across two hosts")
    elif link_events:
        ap.error("--link-events needs --hosts 2")

    from gsrmr_sim.world.scene import load_scene

    scene = load_scene(args.scene)
    slots = args.slots or scene.slots
    out = Path(args.out or REPO / "reports" / f"demo-{time.strftime('%Y%m%d-%H%M%S')}")
    if (out / "recording").exists() or (out / "robot1").exists():  # the server would refuse to record into it
        ap.error(f"--out {out} already holds a run; use a fresh folder")
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    from gsrmr_sim.models import live_model, live_recipe

    recipe = live_recipe(args.scene, frames=args.frames or None, train_seconds=args.train_seconds,
                         iterations=args.train_iterations, width=args.train_width, budget=args.budget)
    built = live_model(recipe, Path(args.cache), max_psnr_drop_db=None if args.no_compact else args.max_psnr_drop_db,
                       log=_log)
    model = built.path
    seed = ensure_survey(args.scene, model, slots, round_index=2 if args.oracle else 1)
    if args.robots is not None:
        from gsrmr_sim.fleet import fleet_demo

        return fleet_demo(args, slots=slots, slot_s=scene.slot_s, out=out, built=built, loss_map=seed,
                          link_events=link_events, t_start=t_start)
    _log(f"round 2: {slots} slots in real time ({slots * scene.slot_s:.1f} s) over DDS, L_th = {args.loss_threshold}")
    link_log: dict = {}
    rows, first_moving = run_stack(scene=args.scene, model_path=model, loss_map=seed, run_dir=out,
                                   loss_threshold=args.loss_threshold, slots=slots, method=args.method,
                                   timeout_s=slots * scene.slot_s + 120.0, channel_seed=args.channel_seed,
                                   oracle_channel=args.oracle, hosts=args.hosts, uplink_mbit=args.uplink_mbit,
                                   link_events=link_events, link_log=link_log, overrides=args.overrides)
    copy_recording(out, out / "recording", first_moving, len(rows))
    summary = {**run_summary(args, rows, scene.slot_s, built, args.channel_seed),
               "hosts": args.hosts, **(link_summary(link_log, rows, args.uplink_mbit) if args.hosts == 2 else {}),
               "report_dir": str(out)}
    write_report(out, rows, summary)
    print(f"\ngsrmr demo — scene {args.scene}, L_th {args.loss_threshold}, {summary['slots']} slots "
          f"({time.perf_counter() - t_start:.0f} s in all)")
    print(f"  images sent {summary['images_sent']}/{summary['slots']}, uplink energy {summary['energy_j']:.4g} J "
          f"vs upload-all {summary['energy_upload_all_j']:.4g} J ({summary['energy_ratio_vs_upload_all']:.1f}× less)")
    print(f"  hindsight optimum (computed after the run) {summary['energy_hindsight_j']:.4g} J: regret "
          f"{summary['regret']:.2f} over {summary['hindsight_slots']} slots")
    print(f"  MR images: mean loss {summary['mean_loss']:.4f}, PSNR {summary['psnr_db']:.2f} dB pooled "
          f"({summary['psnr_slot_mean_db']:.2f} dB per-slot mean), "
          f"SSIM {summary['ssim']:.4f}; on time {summary['slots_on_time']}/{summary['slots']}")
    if args.hosts == 2:
        print(f"  two hosts: uplink limited to {args.uplink_mbit:g} Mbit/s; {summary['link_uplink_bytes']} B crossed "
              f"robot → server ({summary['link_uplink_mbit_mean']:.2f} Mbit/s mean), "
              f"{summary['link_downlink_bytes']} B server → robot; the robot's ledger sent "
              f"{summary['ledger_bytes_sent']} B in the scored slots")
    print(f"  report: {out}")
    summary.pop("faults", None)
    print(json.dumps(summary), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
