"""gsrmr-planner-replay: gsrmr-demo reports replayed through planner settings (gsrmr_sim.replay; no ROS), one row
per setting, regret against each run's hindsight optimum. Keys, options and how to read the tables:
docs/scheduling.md, "Reading recorded runs: the analysis tools"."""

from __future__ import annotations

import argparse
from dataclasses import fields, replace
import json
import os
from pathlib import Path
import re
import statistics

import numpy as np
import yaml

from gsrmr_common.link_model import LinkBudget
from gsrmr_robot.scene_change import ChangeProbe
from gsrmr_scheduler.loss_map import LossMap
from gsrmr_scheduler.planner import OnlinePlanner, PlannerConfig, RoutePredictor, SlotLossModel
from gsrmr_scheduler.scheduler_params import SchedulerParameters
from gsrmr_server.recording import read_slots_csv
from gsrmr_sim.replay import TruthLossPredictor, recorded_slots, replay
from gsrmr_sim.sim_stack import config_dir

PROG = "gsrmr-planner-replay"
REPLAY_KEYS = {"replan_every", "measurement_delay"}
PLANNER_KEYS = {f.name for f in fields(PlannerConfig)} - {f.name for f, _ in SchedulerParameters.specs()}


def scheduler_params(report: Path) -> SchedulerParameters:
    """config/scheduler.yaml (the package's, :func:`gsrmr_sim.sim_stack.config_dir`) overlaid with the run's own
    scheduler parameters (names that are no parameter of the scheduler any more, e.g. an old run's ``loss_model``, are
    ignored)."""
    values: dict = {}
    for path in (config_dir() / "scheduler.yaml", report / "params" / "gsrmr_scheduler.yaml"):
        if path.exists():
            values.update(yaml.safe_load(path.read_text())["/**"]["ros__parameters"])
    return SchedulerParameters().with_values(values)


def make_planner(params: SchedulerParameters, overrides: dict,
                 loss_model: SlotLossModel | None = None) -> OnlinePlanner:
    """An OnlinePlanner configured as the scheduler node configures it (never the oracle), with ``overrides``
    (scheduler parameters, planner knobs and the replay's own keys, which it ignores)."""
    unknown = set(overrides) - REPLAY_KEYS - PLANNER_KEYS - {f.name for f, _ in SchedulerParameters.specs()}
    if unknown:
        raise SystemExit(f"planner_replay: unknown key(s) {sorted(unknown)}")
    params = params.with_values({**{k: v for k, v in overrides.items() if SchedulerParameters.spec(k)},
                                 "oracle_channel": False})
    loss_map = LossMap.load(params.loss_map_file) if params.loss_map_file else LossMap(prior=params.loss_prior)
    config = replace(params.planner_config(loss_map), **{k: v for k, v in overrides.items() if k in PLANNER_KEYS})
    return OnlinePlanner(config, RoutePredictor(params.waypoints, params.route_speed_mps), loss_map, LinkBudget(),
                         loss_model=loss_model)


SCENE_CHANGE_LINE = re.compile(r"scene change in slot (\d+)")


def scene_changes(report: Path) -> tuple[list[int], int]:
    """(the slots in which the run's robot found a scene change, as its log names them; the robot's
    ``scene_change_wait_slots``: the package's config/robot.yaml overlaid with the run's robot parameters)."""
    log = report / "logs" / "gsrmr_robot.log"
    slots = [int(m.group(1)) for m in SCENE_CHANGE_LINE.finditer(log.read_text())] if log.exists() else []
    wait = 5
    for path in (config_dir() / "robot.yaml", report / "params" / "gsrmr_robot.yaml"):
        if path.exists():
            wait = int(yaml.safe_load(path.read_text())["/**"]["ros__parameters"].get("scene_change_wait_slots", wait))
    return slots, wait


def parse_value(text: str):
    """``key=value`` values: JSON where it parses (numbers, true/false, objects), else the string."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("reports", nargs="+", type=Path, metavar="REPORT_DIR",
                    help="gsrmr-demo report folders (reports/demo-*)")
    ap.add_argument("--vary", default="", help="key=v1,v2,... (one row per value)")
    ap.add_argument("--set", action="append", default=[], help="key=value for every row")
    ap.add_argument("--per-run", action="store_true", help="also print every run's figures")
    ap.add_argument("--truth-loss", nargs="?", const="frame", choices=("frame", "samples"), default=None,
                    help="hindsight bound: the planner is given every slot's L (never available live): against the "
                    "true frame (default), or as the server's samples read it (against the decoded JPEG)")
    ap.add_argument("--observe-keys", action="store_true",
                    help="hindsight study: the forecast also learns every key slot's L, as if measured")
    ap.add_argument("--no-scene-changes", action="store_true",
                    help="leave out the images the run's robot sent for scene changes (its log names the slots; "
                    "by default they are replayed at the recorded gains)")
    ap.add_argument("--rest-forecast", action="store_true",
                    help="hindsight: also tabulate the planned L of the round's rest over its truth, by slots left")
    args = ap.parse_args(argv)
    fixed = {k: parse_value(v) for k, v in (s.split("=", 1) for s in args.set)}
    key, _, values = args.vary.partition("=")
    settings = [{**fixed, key: parse_value(v)} for v in values.split(",")] if key else [fixed]
    runs = []
    for report in args.reports:
        params = scheduler_params(report)
        changes = ([], 5) if args.no_scene_changes else scene_changes(report)
        runs.append((report.name, params, recorded_slots(read_slots_csv(report / "slots.csv")), changes))
    print(f"# gsrmr-planner-replay: {len(runs)} recorded runs ({os.cpu_count()} CPUs, load average "
          f"{os.getloadavg()[0]:.1f}); fixed {fixed or '{}'}"
          + (f"; HINDSIGHT BOUND: the planner knows every slot's L ({args.truth_loss})" if args.truth_loss else "")
          + ("; HINDSIGHT: the forecast learns every key slot's L" if args.observe_keys else "")
          + f"; scene changes replayed: {sum(len(c[0]) for *_, c in runs)}")
    print("| setting | mean loss median (worst) | ≤ L_th | regret median (worst) | images median | ms per replan |")
    print("|---|---|---|---|---|---|")
    for setting in settings:
        results = []
        rest_ratios: dict[int, list[float]] = {}
        for name, params, slots, (changes, wait) in runs:
            run = params.with_values({k: v for k, v in setting.items() if SchedulerParameters.spec(k)})
            planner = make_planner(run, setting, TruthLossPredictor(slots, as_sampled=args.truth_loss == "samples")
                                   if args.truth_loss else None)
            lth = planner.config.loss_threshold
            on_plan = rest_forecast_recorder(planner, slots, rest_ratios) if args.rest_forecast else None
            r = replay(slots, planner, loss_threshold=lth, on_plan=on_plan,
                       replan_every=int(setting.get("replan_every", round(run.replan_period_s / run.slot_s))),
                       measurement_delay=int(setting.get("measurement_delay", 1)), observe_keys=args.observe_keys,
                       scene_changes=changes, change_probe=ChangeProbe(planner.link.rician_k, wait),
                       mean_gain=lambda pose, link=planner.link: link.mean_gain(pose[:2]))
            results.append((name, lth, r))
            if args.per_run:
                print(f"|   {name} | {r.mean_loss:.4f} | {int(r.mean_loss <= lth)} | {r.regret:.2f} | "
                      f"{r.images} | {1e3 * r.plan_time_s / max(r.replans, 1):.1f} |")
        losses = [r.mean_loss for _, _, r in results]
        regrets = [r.regret for _, _, r in results]
        within = sum(r.mean_loss <= lth for _, lth, r in results)
        label = ", ".join(f"{k}={v}" for k, v in setting.items() if k in ((key,) if key else setting)) or "as run"
        print(f"| {label} | {statistics.median(losses):.4f} ({max(losses):.4f}) | {within}/{len(results)} | "
              f"{statistics.median(regrets):.2f} ({max(regrets):.2f}) | "
              f"{statistics.median(r.images for _, _, r in results):.0f} | "
              f"{1e3 * sum(r.plan_time_s for *_, r in results) / max(1, sum(r.replans for *_, r in results)):.1f} |",
              flush=True)
        if args.rest_forecast:
            print_rest_forecast(rest_ratios)
    return 0


REST_BIN_SLOTS = 25  # --rest-forecast: slots left in the round per row


def rest_forecast_recorder(planner: OnlinePlanner, slots: list, ratios: dict[int, list[float]]):
    """An ``on_plan`` callback of :func:`gsrmr_sim.replay.replay` that appends, per bin of slots left in the round,
    the planned mean L of the round's rest (within the horizon) over its recorded truth (hindsight)."""
    truth = np.array([s.gs_truth_loss for s in slots])

    def on_plan(i: int, result) -> None:
        first = result.schedule.first_slot
        left = planner.budget.round_remaining(first)
        start = i - (slots[i].slot - first)  # the index of the plan's first slot (the one before slot i)
        if not left or start < 0:
            return
        n = min(left, len(result.predicted_loss), len(slots) - start)
        true_mean = float(truth[start:start + n].mean()) if n > 0 else 0.0
        if true_mean > 0:
            ratios.setdefault(left // REST_BIN_SLOTS, []).append(float(result.predicted_loss[:n].mean()) / true_mean)
    return on_plan


def print_rest_forecast(ratios: dict[int, list[float]]) -> None:
    """The --rest-forecast table (hindsight)."""
    print("\n| slots left in the round | replans | planned / true L of the rest: median | quartiles |")
    print("|---|---|---|---|")
    for b in sorted(ratios, reverse=True):
        v = np.array(ratios[b])
        print(f"| {b * REST_BIN_SLOTS}–{(b + 1) * REST_BIN_SLOTS - 1} | {v.size} | {np.median(v):.2f} | "
              f"{np.quantile(v, 0.25):.2f} – {np.quantile(v, 0.75):.2f} |")
    print()


if __name__ == "__main__":
    raise SystemExit(main())
