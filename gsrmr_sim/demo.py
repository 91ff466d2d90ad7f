"""``gsrmr-demo`` (``make demo``): the paper's system end to end on the embedded sandbox scene.

The steps (mapping round and model, seed loss map, the scored round over DDS, the report) and the options:
README.md, "Main job"; ``--model`` and ``--loss-map`` from elsewhere: docs/hardware.md, "A dry run with the
simulator playing the robot"; ``--robots``, ``--rounds`` and ``--hosts``: :mod:`gsrmr_sim.fleet`,
:mod:`gsrmr_sim.rounds`, docs/two_hosts.md.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
import hashlib
import math
from pathlib import Path
import signal
import sys
import time

import numpy as np
import yaml

from gsrmr_scheduler.loss_map import LossMap
from gsrmr_sim import netns
from gsrmr_sim.fleet import fleet_demo
from gsrmr_sim.limo.odometry_errors import OdometryErrors, run_settings
from gsrmr_sim.link_events import LinkEvent, parse_link_events
from gsrmr_sim.models import LIVE_MAX_PSNR_DROP_DB, BuiltModel, live_model, live_recipe
from gsrmr_sim.param_events import ParamEvent, swap_loss_map_event, swap_model_event, swap_summary
from gsrmr_sim.pose_errors import key_pose_errors, read_truth
from gsrmr_sim.report import (
    copy_recording,
    exit_status,
    link_summary,
    log,
    run_summary,
    summary_json,
    write_report,
)
from gsrmr_sim.round_start import first_moving_slot as first_moving_slot  # re-exported: test_pipeline_units
from gsrmr_sim.rounds import run_rounds, worlds_cache
from gsrmr_sim.sim_stack import TRUTH_LOG, config_dir, robot_jpeg_quality, sim_stack
from gsrmr_sim.stack_runner import RobotRun, limo_link_path, run_round
from gsrmr_sim.survey import SURVEY_VERSION, gs_losses, loss_map_from
from gsrmr_sim.world.recorder import Round2Record, record_round2
from gsrmr_sim.world.scene import Scene, load_scene
from gsrmr_splat.model import GaussianModel

REPO = Path(__file__).resolve().parents[1]
#: The options that say how the demo builds its model: ``--model`` replaces the building, so they are refused with it.
MODEL_BUILDING_OPTIONS = ("frames", "train_iterations", "train_seconds", "train_width", "budget", "max_psnr_drop_db",
                          "no_compact")


class DemoInputError(ValueError):
    """A ``--model`` or ``--loss-map`` file the demo cannot use (the message is the one line it prints)."""


def file_sha256(path: Path) -> str:
    """Hex SHA-256 of the file's bytes: which model or loss map a run used, whatever its path."""
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def load_outside_model(path: str) -> GaussianModel:
    """``--model PLY``: the 3DGS model read as the server reads it; :class:`DemoInputError` when it cannot be."""
    try:
        return GaussianModel.load_ply(path)
    except (OSError, ValueError) as err:  # FileNotFoundError, IsADirectoryError, PlyFormatError
        raise DemoInputError(f"--model {path}: {' '.join(str(err).splitlines())} — give a 3DGS .ply in map "
                             "(gsrmr-train --out, or gsrmr-align --out for a model trained elsewhere)") from err


def load_outside_loss_map(path: str) -> LossMap:
    """``--loss-map JSON``: the seed map read as the scheduler reads its ``loss_map_file``
    (:meth:`gsrmr_scheduler.loss_map.LossMap.load`); :class:`DemoInputError` when it cannot be."""
    try:
        return LossMap.load(path)
    except KeyError as err:
        raise DemoInputError(f"--loss-map {path}: not a LossMap JSON (no key {err}) — give gsrmr-survey's --out "
                             "file") from err
    except (OSError, ValueError, TypeError, AttributeError) as err:  # missing, unreadable, not JSON, bad values
        raise DemoInputError(f"--loss-map {path}: {' '.join(str(err).splitlines())} — give gsrmr-survey's --out "
                             "file (a LossMap JSON)") from err


def outside_built_model(path: Path, model: GaussianModel) -> BuiltModel:
    """A ``--model`` file as the report's :class:`~gsrmr_sim.models.BuiltModel`: no training record, so its
    held-out PSNR is unknown (NaN)."""
    return BuiltModel(model, path.parent, {}, path.name)


def input_record(model_path: Path, model_source: str, loss_map_path: Path, loss_map_source: str) -> dict:
    """The summary's record of what the run used: each file's absolute path, SHA-256 and where it came from."""
    return {"model_path": str(model_path.resolve()), "model_sha256": file_sha256(model_path),
            "model_source": model_source, "loss_map_path": str(loss_map_path.resolve()),
            "loss_map_sha256": file_sha256(loss_map_path), "loss_map_seed": loss_map_source}


def ensure_survey(scene_name: str, model_path: Path, slots: int, round_index: int = 1,
                  cache_dir: Path | None = None) -> Path:
    """Seed loss map JSON (cached in ``cache_dir``, default beside the model): L_t of the model along the route's
    slot poses against the world of round ``round_index`` — 1, the mapping round (what exists before round 2: its
    frames and the model; the default), or 2, a rehearsal of the very round being scored (the ``--oracle`` mode)."""
    quality = robot_jpeg_quality(str(config_dir() / "robot.yaml"))  # what an image slot leaves (JPEG)
    folder = model_path.parent if cache_dir is None else cache_dir
    folder.mkdir(parents=True, exist_ok=True)
    # L_t depends on the model; the image-slot loss on the robot's JPEG quality
    out = folder / f"loss_map_{model_path.stem}_{slots}_round{round_index}_q{quality}_v{SURVEY_VERSION}.json"
    if out.exists():
        log(f"loss-map seed cached: {out}")
        return out
    scene = load_scene(scene_name)
    t0 = time.perf_counter()
    rec_dir = record_round2(scene, folder / f"survey_round{round_index}_{slots}", slots=slots,
                            round_index=round_index)
    losses = gs_losses(Round2Record(rec_dir), GaussianModel.load_ply(model_path), scene.background,
                       mr_content=scene.mr_content, jpeg_quality=quality)
    seed = loss_map_from(losses)
    seed.save(out)
    values = np.array([s.loss for s in losses])
    log(f"round-{round_index} survey: {slots} slots, GS loss mean {values.mean():.4f}, max {values.max():.4f}; "
         f"image slot (JPEG q{quality}) {seed.image_loss:.4f} ({time.perf_counter() - t0:.1f} s)")
    return out


def run_stack(*, scene: str, model_path: Path, loss_map: Path, run_dir: Path, loss_threshold: float,
              slots: int, method: str, timeout_s: float, channel_seed: int | None = None,
              oracle_channel: bool = False, hosts: int = 1, uplink_mbit: float = 5.0,
              link_events: Sequence[LinkEvent] = (), link_log: dict | None = None,
              overrides: dict[str, dict] | None = None, label: str = "round 2",
              param_events: Sequence[ParamEvent] = (), param_log: list | None = None,
              odometry: OdometryErrors = OdometryErrors(), odometry_seed: int = 0,
              localization: bool = True) -> RobotRun:
    """Run the single robot's closed loop (:func:`gsrmr_sim.sim_stack.sim_stack`: recording in
    ``<run_dir>/recording``) with :func:`gsrmr_sim.stack_runner.run_round`: every node a process over DDS, stopped
    after ``slots`` composed slots of the round; return the robot's run (its scored rows).
    ``overrides``: parameters per node name on top of the stack's (``gsrmr-demo --param``); ``label``: what the
    progress lines call the round; ``param_events``/``param_log``: ``ros2 param set`` during the round
    (:mod:`gsrmr_sim.param_events`).

    ``hosts`` = 2 runs the robot's processes and the server's in two network namespaces joined by a veth pair
    limited to ``uplink_mbit`` (:class:`gsrmr_sim.netns.TwoHosts`), DDS over UDPv4 across it, the
    ground-truth frames over the simulation backplane (:mod:`gsrmr_sim.truth_frames`); ``link_events``
    then change the link during the round, and ``link_log`` (a dict) receives the link's byte counters.
    """
    specs = sim_stack(scene=scene, model_path=str(model_path), record_dir=str(run_dir / "recording"),
                      loss_threshold=loss_threshold, link_path=limo_link_path(), laps=1, method=method,
                      loss_map_file=str(loss_map), state_dir=str(run_dir / "scheduler_state"),
                      channel_seed=channel_seed, oracle_channel=oracle_channel,
                      truth_dir=str(run_dir / "truth_frames") if hosts == 2 else "", overrides=overrides,
                      odometry=odometry, odometry_seed=odometry_seed, localization=localization)
    (run,) = run_round(specs, run_dir=run_dir, slots=slots, timeout_s=timeout_s, hosts=hosts,
                       uplink_mbit=uplink_mbit, link_events=link_events, link_log=link_log, label=label,
                       param_events=param_events, param_log=param_log, log=log)
    return run


def odometry_settings(args: argparse.Namespace, scene: Scene) -> dict:
    """``run_stack``'s odometry arguments from the demo's options (:func:`gsrmr_sim.limo.odometry_errors.run_settings`:
    ``--odometry``, ``--odometry-error-scale``, ``--odometry-seed``, ``--no-localization``)."""
    return run_settings(args.odometry, args.odometry_error_scale, args.odometry_seed, args.channel_seed,
                        not args.no_localization, scene.odometry)


def pose_summary(args: argparse.Namespace, rows: list[dict], record_dir: Path) -> dict:
    """The summary's odometry settings and, in hindsight, the keys' pose errors (:mod:`gsrmr_sim.pose_errors`)."""
    truth_log = Path(record_dir) / TRUTH_LOG
    errors = key_pose_errors(rows, read_truth(truth_log)) if truth_log.exists() else key_pose_errors([], None)
    return {"odometry": args.odometry, "odometry_error_scale": args.odometry_error_scale,
            "localization": not args.no_localization, **errors}


def parse_params(items: Sequence[str]) -> dict[str, dict]:
    """``["gsrmr_robot:jpeg_quality=70", …]`` → ``{"gsrmr_robot": {"jpeg_quality": 70}}`` (values parsed as YAML)."""
    out: dict[str, dict] = {}
    for item in items:
        node, sep, rest = item.partition(":")
        name, eq, value = rest.partition("=")
        if not (sep and eq and node and name):
            raise ValueError(f"--param {item!r}: expected NODE:NAME=VALUE")
        out.setdefault(node, {})[name] = yaml.safe_load(value)
    return out


def rounds_demo(args: argparse.Namespace, *, scene_name: str, slots: int, slot_s: float, built: BuiltModel,
                seed: Path, inputs: dict, out: Path, t_start: float) -> int:
    """``--rounds N [--update]``: :func:`gsrmr_sim.rounds.run_rounds`, each round's report in ``out/round<k>``; the
    last stdout line is the summary with ``rounds``."""

    def one_round(k: int, model: Path, loss_map: Path, run_dir: Path, overrides: dict[str, dict]) -> dict:
        run = run_stack(scene=scene_name, model_path=model, loss_map=loss_map, run_dir=run_dir,
                        loss_threshold=args.loss_threshold, slots=slots, method=args.method,
                        timeout_s=slots * slot_s + 120.0, channel_seed=args.channel_seed, overrides=overrides,
                        label=f"round {k}", **odometry_settings(args, load_scene(scene_name)))
        copy_recording(run_dir, run.record_dir, run.first_moving, len(run.rows))
        summary = {**run_summary(args, run.rows, slot_s, built, args.channel_seed), "round": k,
                   "model_path": str(model), "loss_map_path": str(loss_map), "report_dir": str(run_dir)}
        write_report(run_dir, run.rows, summary)
        return summary

    rounds = run_rounds(args, scene_name=scene_name, slots=slots, slot_s=slot_s, model=built.path, loss_map=seed,
                        mapping_dataset=built.folder / "round1", out=out, run_round=one_round,
                        cache_dir=worlds_cache(Path(args.cache), scene_name))
    summary = {"scene": scene_name, "loss_threshold": args.loss_threshold, "channel_seed": args.channel_seed,
               "update": bool(args.update), **inputs, "rounds": rounds, "report_dir": str(out),
               "wall_s": round(time.perf_counter() - t_start, 1)}
    print(f"\ngsrmr demo — scene {scene_name}, {args.rounds} rounds{' with updates' if args.update else ''}, L_th "
          f"{args.loss_threshold} ({summary['wall_s']:.0f} s in all)")
    for r in rounds:
        print(f"  round {r['round']}: {r['images_sent']}/{r['slots']} images, {r['energy_j']:.4g} J, mean loss "
              f"{r['mean_loss']:.4f}, regret {r['regret']:.2f}, on time {r['slots_on_time']}/{r['slots']}, model "
              f"v{r['model_version']} ({r['model_psnr_now_db']:.2f} dB against this round's world), update before "
              f"it {r['update_cpu_s']:.0f} CPU-s")
    (out / "summary.json").write_text(summary_json(summary) + "\n")
    print(summary_json(summary), flush=True)
    return exit_status(rounds)


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
    ap.add_argument("--max-psnr-drop-db", type=float, default=None,
                    help=f"compact the trained model to the smallest one within this held-out PSNR loss (default "
                         f"{LIVE_MAX_PSNR_DROP_DB}; gsrmr-compact; bench/perf/compact.py: sandbox 97k → 17k Gaussians "
                         "at −0.21 dB)")
    ap.add_argument("--no-compact", action="store_true", help="run on the trained (uncompacted) model")
    ap.add_argument("--channel-seed", type=int, default=7,
                    help="seed of the simulated channel: the fading of the k-th slot of round 2 depends only "
                         "on (seed, k), so two runs with one seed see the same channel")
    ap.add_argument("--oracle", action="store_true",
                    help="the oracle-fed upper bound: the scheduler plans with the simulator's future channel "
                         "realisation and a loss map surveyed on the very round being scored (by default it "
                         "plans with the channel's statistics and a map of the mapping round)")
    ap.add_argument("--hosts", type=int, choices=(1, 2), default=1,
                    help="2: the robot's processes and the server's in two network namespaces joined by a veth pair "
                         "(DDS over UDPv4 across it; needs root and iproute2)")
    ap.add_argument("--uplink-mbit", type=float, default=5.0,
                    help="with --hosts 2: the robot → server rate limit in Mbit/s (tbf)")
    ap.add_argument("--link-events", default="",
                    help="with --hosts 2: link changes during the round, e.g. 'down@100,up@120,rate=1.5@150' "
                         "(ACTION@SLOT, SLOT = composed round slots)")
    ap.add_argument("--swap-model", action="append", default=[], metavar="MODEL.ply@SLOT",
                    help="a hot swap inside the round: `ros2 param set /gsrmr_server model_path MODEL.ply` once "
                         "SLOT round slots are composed (turns on the server's live_parameter_changes; one robot, "
                         "one host); the report's model_swaps say where it took over and the slots on time around it")
    ap.add_argument("--swap-loss-map", action="append", default=[], metavar="MAP.json@SLOT",
                    help="the scheduler's seed map follows: `ros2 param set /gsrmr_scheduler loss_map_file MAP.json` "
                         "once SLOT round slots are composed (the new model's gsrmr-survey; turns on the scheduler's "
                         "live_parameter_changes); the report's loss_map_reseeds list what it took")
    ap.add_argument("--robots", type=int, default=None, metavar="N",
                    help="a fleet: N robots at once (namespaces /robot1 … /robotN, each with its own server, "
                         "scheduler and simulated world; channel seed + k - 1 for robot k), one report folder per "
                         "robot and fleet totals (gsrmr_sim.fleet); without it, the single robot in the root "
                         "namespace (default)")
    ap.add_argument("--model", default=None, metavar="PLY",
                    help="run on this 3DGS model in the scene's map frame (e.g. gsrmr-train's, or a GPU model after "
                         "gsrmr-align) instead of building the scene's model from the simulator's round 1")
    ap.add_argument("--loss-map", default=None, metavar="JSON",
                    help="seed the scheduler with this loss map (gsrmr-survey's --out, a LossMap JSON) instead of "
                         "the simulator's survey of the model")
    ap.add_argument("--param", action="append", default=[], metavar="NODE:NAME=VALUE",
                    help="set a node's parameter on top of the stack's (YAML value), e.g. "
                         "gsrmr_robot:hold_images_while_queued=false; repeatable")
    ap.add_argument("--rounds", type=int, default=1, metavar="N",
                    help="N scored rounds after the mapping round, in the world as it is in each (a scene's "
                         "persistent changes stay from their round on; gsrmr_sim.rounds); the last JSON line then "
                         "carries 'rounds'")
    ap.add_argument("--odometry", choices=("realistic", "perfect"), default="realistic",
                    help="the mock LIMO's odometry: the scene's errors (slip, IMU drift, start error; docs/world.md) "
                         "or none")
    ap.add_argument("--odometry-error-scale", type=float, default=1.0, metavar="K",
                    help="every odometry error times K (sweeps)")
    ap.add_argument("--odometry-seed", type=int, default=None, help="seed of the odometry errors (default: the "
                    "channel seed)")
    ap.add_argument("--no-localization", action="store_true",
                    help="the server does not localize the robot (its keys are its odometry's)")
    ap.add_argument("--update", action="store_true",
                    help="with --rounds N >= 2: update the model between rounds from what the server received "
                         "(gsrmr-dataset, gsrmr-update, gsrmr-survey; docs/model_update.md)")
    args = ap.parse_args(argv)
    if args.rounds < 1:
        ap.error("--rounds must be >= 1")
    if not (math.isfinite(args.odometry_error_scale) and args.odometry_error_scale >= 0):
        ap.error("--odometry-error-scale must be >= 0")
    if args.update and args.rounds < 2:
        ap.error("--update needs --rounds N >= 2 (an update follows rounds 1 … N-1)")
    if args.rounds > 1 and (args.robots is not None or args.hosts == 2 or args.oracle):
        ap.error("--rounds N > 1 runs one robot on one host without --oracle")
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
        reason = netns.unavailable_reason()
        if reason:
            print(f"gsrmr-demo --hosts 2: {reason}", file=sys.stderr)
            return 2
        if not args.uplink_mbit > 0:
            ap.error("--uplink-mbit must be > 0")
        if args.oracle:  # the oracle reads the simulator's channel on the server: simulation traffic on the uplink
            ap.error("--oracle reads the simulated radio on the server side; it is not run across two hosts")
    elif link_events:
        ap.error("--link-events needs --hosts 2")
    try:
        model_swaps = [swap_model_event(text) for text in args.swap_model]
        map_swaps = [swap_loss_map_event(text) for text in args.swap_loss_map]
    except ValueError as e:
        ap.error(str(e))
    swap_events = model_swaps + map_swaps
    if swap_events:
        if args.hosts != 1 or args.robots is not None or args.rounds > 1:
            ap.error("--swap-model and --swap-loss-map run in a single robot's round on one host (no --hosts 2, "
                     "--robots, --rounds)")
        for event in swap_events:
            args.overrides.setdefault(event.node, {})["live_parameter_changes"] = True
    if args.model is not None:
        given = [f"--{name.replace('_', '-')}" for name in MODEL_BUILDING_OPTIONS
                 if getattr(args, name) not in (None, False, 0)]
        if given:
            ap.error(f"--model replaces the model building: drop {', '.join(given)}")
    if args.robots is not None and (args.model or args.loss_map):
        ap.error("--model and --loss-map are for one robot: the fleet's summaries do not record them")
    try:  # both outside files are checked before anything is built or started
        outside_model = load_outside_model(args.model) if args.model is not None else None
        outside_map = load_outside_loss_map(args.loss_map) if args.loss_map is not None else None
    except DemoInputError as err:
        print(f"gsrmr-demo: {err}", file=sys.stderr)
        return 2

    scene = load_scene(args.scene)
    slots = args.slots or scene.slots
    out = Path(args.out or REPO / "reports" / f"demo-{time.strftime('%Y%m%d-%H%M%S')}")
    if (out / "recording").exists() or (out / "robot1").exists():  # the server would refuse to record into it
        ap.error(f"--out {out} already holds a run; use a fresh folder")
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    survey_cache = None
    if outside_model is not None:
        built = outside_built_model(Path(args.model), outside_model)
        model_source = "--model"
        survey_cache = Path(args.cache) / f"outside-{file_sha256(built.path)[:12]}"  # never into the model's folder
        log(f"model: {built.path} (--model, {outside_model.num_gaussians} Gaussians, SH degree "
            f"{outside_model.sh_degree})")
    else:
        recipe = live_recipe(args.scene, frames=args.frames or None, train_seconds=args.train_seconds,
                             iterations=args.train_iterations, width=args.train_width, budget=args.budget)
        drop_db = args.max_psnr_drop_db if args.max_psnr_drop_db is not None else LIVE_MAX_PSNR_DROP_DB
        built = live_model(recipe, Path(args.cache), max_psnr_drop_db=None if args.no_compact else drop_db, log=log)
        model_source = "built from the simulator's round 1"
    model = built.path
    if outside_map is not None:
        seed, seed_source = Path(args.loss_map), "--loss-map"
        log(f"loss-map seed: {seed} (--loss-map, {len(outside_map.cells)} cells, image_loss "
            f"{'none' if outside_map.image_loss is None else f'{outside_map.image_loss:.4f}'})")
    else:
        seed = ensure_survey(args.scene, model, slots, round_index=2 if args.oracle else 1, cache_dir=survey_cache)
        seed_source = "round-2 survey (oracle)" if args.oracle else "mapping round"
    inputs = input_record(model, model_source, seed, seed_source)
    if args.rounds > 1:
        return rounds_demo(args, scene_name=args.scene, slots=slots, slot_s=scene.slot_s, built=built, seed=seed,
                           inputs=inputs, out=out, t_start=t_start)
    if args.robots is not None:
        return fleet_demo(args, slots=slots, slot_s=scene.slot_s, out=out, built=built, loss_map=seed,
                          link_events=link_events, t_start=t_start)
    log(f"round 2: {slots} slots in real time ({slots * scene.slot_s:.1f} s) over DDS, L_th = {args.loss_threshold}")
    link_log: dict = {}
    param_log: list[dict] = []
    run = run_stack(scene=args.scene, model_path=model, loss_map=seed, run_dir=out,
                    loss_threshold=args.loss_threshold, slots=slots, method=args.method,
                    timeout_s=slots * scene.slot_s + 120.0, channel_seed=args.channel_seed,
                    oracle_channel=args.oracle, hosts=args.hosts, uplink_mbit=args.uplink_mbit,
                    link_events=link_events, link_log=link_log, overrides=args.overrides,
                    param_events=swap_events, param_log=param_log, **odometry_settings(args, scene))
    rows = run.rows
    copy_recording(out, run.record_dir, run.first_moving, len(rows))
    summary = {**run_summary(args, rows, scene.slot_s, built, args.channel_seed), **inputs,
               **pose_summary(args, rows, run.record_dir),
               **({"model_compacted": None} if outside_model is not None else {}),  # not known of an outside model
               "hosts": args.hosts, **(link_summary(link_log, rows, args.uplink_mbit) if args.hosts == 2 else {}),
               **(swap_summary(param_log, (out / "logs" / "gsrmr_server.log").read_text(errors="replace"), rows,
                               scene.slot_s, scheduler_log=(out / "logs" / "gsrmr_scheduler.log").read_text(
                                   errors="replace")) if swap_events else {}),
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
    print(f"  model {inputs['model_path']} ({model_source}, sha256 {inputs['model_sha256'][:12]}); loss-map seed "
          f"{inputs['loss_map_path']} ({seed_source}, sha256 {inputs['loss_map_sha256'][:12]})")
    if args.hosts == 2:
        print(f"  two hosts: uplink limited to {args.uplink_mbit:g} Mbit/s; {summary['link_uplink_bytes']} B crossed "
              f"robot → server ({summary['link_uplink_mbit_mean']:.2f} Mbit/s mean), "
              f"{summary['link_downlink_bytes']} B server → robot; the robot's ledger sent "
              f"{summary['ledger_bytes_sent']} B in the scored slots")
    print(f"  report: {out}")
    summary.pop("faults", None)
    print(summary_json(summary), flush=True)
    return exit_status([summary])


if __name__ == "__main__":
    sys.exit(main())
