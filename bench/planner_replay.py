"""Planner study on recorded runs: replay demo reports through planner settings (:mod:`gsrmr_sim.replay`).

Usage: ``.venv/bin/python bench/planner_replay.py REPORT_DIR... [--vary horizon=50,100,200]
[--set key=value ...]``. Each REPORT_DIR is a ``gsrmr-demo`` report (its ``slots.csv`` and
``params/gsrmr_scheduler.yaml``). For every setting, every run is replayed with the scheduler's
parameters of that run (``config/scheduler.yaml`` + the run's overrides) changed by ``--set`` and the
varied key; the table gives the median and worst over the runs of mean MR loss, runs within L_th, regret
(against each run's hindsight optimum, computed after the run) and the planner's CPU time per replan.
Keys: the :class:`~gsrmr_server.horizon.OnlinePlanner` keywords (horizon, method, loss_margin,
calibration_quantile, explore_image_fraction, ...) plus ``replan_every`` (slots between timer replans) and
``measurement_delay`` (slots before an image's L_t reaches the planner).
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
import statistics
import sys

import yaml

REPO = Path(__file__).resolve().parents[1]
REPLAY_KEYS = {"replan_every", "measurement_delay"}


def scheduler_params(report: Path) -> dict:
    """config/scheduler.yaml overlaid with the run's own scheduler parameters."""
    params: dict = {}
    for path in (REPO / "config" / "scheduler.yaml", report / "params" / "gsrmr_scheduler.yaml"):
        if path.exists():
            params.update(yaml.safe_load(path.read_text())["/**"]["ros__parameters"])
    return params


def make_planner(params: dict, overrides: dict):
    """An OnlinePlanner configured as the scheduler node configures it, with ``overrides``."""
    from gsrmr_common.link_model import LinkBudget
    from gsrmr_server.horizon import OnlinePlanner, RoutePredictor
    from gsrmr_server.loss_map import LossMap

    flat = params["route_waypoints_m"]
    route = RoutePredictor([(flat[i], flat[i + 1]) for i in range(0, len(flat), 2)], params["route_speed_mps"])
    loss_map = LossMap.load(params["loss_map_file"]) if params.get("loss_map_file") else LossMap(
        prior=params["loss_prior"])
    kw = dict(slot_s=0.1, image_bits=params["image_bits"], pose_bits=params["pose_bits"],
              loss_threshold=params["loss_threshold"], horizon=params["horizon"], method=params["method"],
              options=json.loads(params["solver_options"]), drift_threshold=params["drift_threshold"],
              drift_window=params["drift_window"], loss_margin=params["loss_margin"],
              oracle_channel=False, in_slot_decision=params["in_slot_decision"],
              calibrate=params["calibrate_loss_map"], explore_image_fraction=params["explore_image_fraction"],
              loss_model=params["loss_model"], margin_quantile=params["margin_quantile"],
              burst_time_constant_slots=params["burst_time_constant_slots"],
              probe_gap_slots=params["probe_gap_slots"], round_slots=params["round_slots"],
              image_slot_loss=params["image_slot_loss"])
    kw.update({k: v for k, v in overrides.items() if k not in REPLAY_KEYS})
    if kw["image_slot_loss"] < 0:  # −1: the seed map's measured value, as the node reads it
        kw["image_slot_loss"] = loss_map.image_loss or 0.0
    return OnlinePlanner(route, loss_map, LinkBudget(), **kw)


def parse_value(text: str):
    """``key=value`` values: JSON where it parses (numbers, true/false, objects), else the string."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def main() -> int:
    from gsrmr_server.recording import read_slots_csv
    from gsrmr_sim.replay import TruthLossPredictor, recorded_slots, replay

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("reports", nargs="+", type=Path)
    ap.add_argument("--vary", default="", help="key=v1,v2,... (one row per value)")
    ap.add_argument("--set", action="append", default=[], help="key=value for every row")
    ap.add_argument("--per-run", action="store_true", help="also print every run's figures")
    ap.add_argument("--truth-loss", action="store_true",
                    help="hindsight bound: the planner is given every slot's true L (never available live)")
    args = ap.parse_args()
    fixed = {k: parse_value(v) for k, v in (s.split("=", 1) for s in args.set)}
    key, _, values = args.vary.partition("=")
    settings = [{**fixed, key: parse_value(v)} for v in values.split(",")] if key else [fixed]
    runs = []
    for report in args.reports:
        params = scheduler_params(report)
        runs.append((report.name, params, recorded_slots(read_slots_csv(report / "slots.csv"))))
    print(f"# bench/planner_replay.py: {len(runs)} recorded runs ({os.cpu_count()} CPUs, load average "
          f"{os.getloadavg()[0]:.1f}); fixed {fixed or '{}'}"
          + ("; HINDSIGHT BOUND: the planner knows every slot's true L" if args.truth_loss else ""))
    print("| setting | mean loss median (worst) | ≤ L_th | regret median (worst) | images median | ms per replan |")
    print("|---|---|---|---|---|---|")
    for setting in settings:
        results = []
        for name, params, slots in runs:
            p = {**params, **{k: v for k, v in setting.items() if k in params}}
            planner = make_planner(p, setting)
            if args.truth_loss:
                planner.loss_model, planner.loss_predictor = "burst", TruthLossPredictor(slots)
            r = replay(slots, planner, loss_threshold=p["loss_threshold"],
                       replan_every=int(setting.get("replan_every", round(p["replan_period_s"] / 0.1))),
                       measurement_delay=int(setting.get("measurement_delay", 1)))
            results.append((name, p["loss_threshold"], r))
            if args.per_run:
                print(f"|   {name} | {r.mean_loss:.4f} | {int(r.mean_loss <= p['loss_threshold'])} | {r.regret:.2f} | "
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
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(REPO))
    sys.exit(main())
