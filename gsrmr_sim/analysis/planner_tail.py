"""gsrmr-planner-tail: the online planner's regret tail: gsrmr-demo reports' worlds replayed under many channel seeds
with the scheduler node's publish timing (no ROS). The model and the columns: docs/scheduling.md, "Reading recorded
runs: the analysis tools"."""

from __future__ import annotations

import argparse
from dataclasses import replace
import math
import os
from pathlib import Path
import statistics

import numpy as np

from gsrmr_common import link_model as link
from gsrmr_common.link_model import LinkBudget
from gsrmr_server.recording import read_slots_csv
from gsrmr_sim.analysis.planner_replay import make_planner, parse_value, scheduler_params
from gsrmr_sim.hindsight import hindsight_optimum
from gsrmr_sim.replay import RecordedSlot, recorded_slots

PROG = "gsrmr-planner-tail"

DEEP_FADE = 0.1  # an image in a fade below this fraction of the mean gain counts as "deep"


def seeds_arg(text: str) -> list[int]:
    """``1-20`` or ``1,3,5``."""
    if "-" in text:
        lo, hi = text.split("-", 1)
        return list(range(int(lo), int(hi) + 1))
    return [int(v) for v in text.split(",")]


def rechannel(rows: list[dict], slots: list[RecordedSlot], seed: int, budget: LinkBudget) -> list[RecordedSlot]:
    """``slots`` with the channel of ``seed``: the gain of round slot k (absolute slot before the round) at the
    reported position, and each slot's image and key energy at that gain."""
    rounds = {int(r["slot"]): int(r.get("round_slot") if r.get("round_slot") not in (None, "") else -1)
              for r in rows}
    lb = replace(budget, channel_seed=int(seed))
    tb = link.SLOT_S * lb.bandwidth_hz
    out = []
    for s in slots:
        # the bits this slot's image slot carried (JPEG + key), from what they cost at the recorded gain
        bits = tb * math.log2(1.0 + s.gain * (s.energy_image_j / link.SLOT_S) / lb.noise_w)
        k = rounds.get(s.slot, -1)
        g = lb.gain(k if k >= 0 else s.slot, s.pose[:2])
        e_img = link.SLOT_S * lb.required_power_w(bits, g, link.SLOT_S, lb.bandwidth_hz, lb.noise_w)
        e_key = link.SLOT_S * lb.required_power_w(link.KEY_BITS, g, link.SLOT_S, lb.bandwidth_hz, lb.noise_w)
        out.append(replace(s, gain=g, energy_image_j=e_img, energy_key_j=e_key))
    return out


def replay_timed(slots: list[RecordedSlot], planner, *, loss_threshold: float, late: float, rng: np.random.Generator,
                 replan_every: int = 5, measurement_delay: int = 1) -> dict:
    """The live loop over ``slots`` with the node's publish timing (docs/scheduling.md); figures of the scored slots."""
    x = np.zeros(len(slots), np.int8)
    pending: list[tuple[int, RecordedSlot]] = []
    pose = None
    replan_due, since_plan, misses = True, 0, 0
    for i, s in enumerate(slots):
        for item in [p for p in pending if p[0] <= i]:
            pending.remove(item)
            if planner.observe(item[1].slot, *item[1].pose, item[1].measured_gs_loss):
                replan_due = True
        if replan_due or since_plan >= replan_every or planner.active is None:
            timer = not replan_due and planner.active is not None
            if timer and rng.random() < late:
                planner.plan(s.slot, pose)  # now_slot = s, published before slot s starts
            else:
                planner.plan(s.slot - 1, pose)
            planner.clear_drift()
            replan_due, since_plan = False, 0
        since_plan += 1
        sched = planner.active
        entry = sched.lookup(s.slot)
        threshold = sched.threshold(s.slot)
        if entry is None:
            misses += 1
            x[i] = 1  # no entry for the slot: the robot's default_upload_image
        elif threshold is not None:
            x[i] = int(s.gain >= threshold)
        else:
            x[i] = entry[0]
        pose = s.pose
        planner.record_pose(s.slot, *s.pose)
        planner.record_action(s.slot, int(x[i]))
        if x[i]:
            pending.append((i + measurement_delay, s))
    sc = np.array([s.scored for s in slots], bool)
    e_img, e_key = np.array([s.energy_image_j for s in slots]), np.array([s.energy_key_j for s in slots])
    l_img, l_gs = np.array([s.image_truth_loss for s in slots]), np.array([s.gs_truth_loss for s in slots])
    energy = np.where(x == 1, e_img, e_key)[sc]
    loss = np.where(x == 1, l_img, l_gs)[sc]
    best = hindsight_optimum(e_img[sc], e_key[sc], l_img[sc], l_gs[sc], loss_threshold)
    budget = LinkBudget()
    fade = np.array([s.gain / budget.mean_gain(s.pose[:2]) for s in slots])[sc]
    deep = (x[sc] == 1) & (fade < DEEP_FADE)
    total = math.fsum(energy.tolist())
    return {"regret": total / best.energy_j, "mean_loss": float(loss.mean()), "images": int(x[sc].sum()),
            "deep": int(deep.sum()), "deep_share": float(energy[deep].sum() / total) if total > 0 else 0.0,
            "misses": misses}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("reports", nargs="+", type=Path, metavar="REPORT_DIR",
                    help="gsrmr-demo report folders (reports/demo-*)")
    ap.add_argument("--seeds", type=seeds_arg, default=seeds_arg("1-20"))
    ap.add_argument("--late", default="0,0.3", help="P1,P2,...: probability that a timer replan is published "
                                                     "before the slot boundary (one row each)")
    ap.add_argument("--set", action="append", default=[], help="key=value: a planner setting (gsrmr-planner-replay)")
    ap.add_argument("--per-run", action="store_true")
    args = ap.parse_args(argv)
    overrides = {k: parse_value(v) for k, v in (s.split("=", 1) for s in args.set)}
    worlds = []
    for report in args.reports:
        rows = read_slots_csv(report / "slots.csv")
        worlds.append((report, scheduler_params(report), rows, recorded_slots(rows)))
    print(f"# gsrmr-planner-tail: {len(worlds)} recorded worlds, channel seeds {args.seeds[0]}–{args.seeds[-1]} "
          f"({os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}); set {overrides or '{}'}")
    print("| late | regret median (worst) | mean loss median (worst) | ≤ L_th | images median | deep images "
          "(runs with any) | deep share worst | schedule misses |")
    print("|---|---|---|---|---|---|---|---|")
    for late in (float(v) for v in args.late.split(",")):
        figs = []
        for seed in args.seeds:
            report, params, rows, slots = worlds[(seed - 1) % len(worlds)]
            planner = make_planner(params, overrides)
            lth = planner.config.loss_threshold
            f = replay_timed(rechannel(rows, slots, seed, LinkBudget()), planner, loss_threshold=lth, late=late,
                             rng=np.random.default_rng(1000 + seed))
            f["ok"] = f["mean_loss"] <= lth
            figs.append(f)
            if args.per_run:
                print(f"|   seed {seed} ({report.name}) | {f['regret']:.2f} | {f['mean_loss']:.4f} | {int(f['ok'])} | "
                      f"{f['images']} | {f['deep']} | {f['deep_share']:.2f} | {f['misses']} |", flush=True)
        reg, loss = [f["regret"] for f in figs], [f["mean_loss"] for f in figs]
        print(f"| {late:g} | {statistics.median(reg):.2f} ({max(reg):.2f}) | {statistics.median(loss):.4f} "
              f"({max(loss):.4f}) | {sum(f['ok'] for f in figs)}/{len(figs)} | "
              f"{statistics.median(f['images'] for f in figs):.0f} | {sum(f['deep'] for f in figs)} "
              f"({sum(f['deep'] > 0 for f in figs)}) | {max(f['deep_share'] for f in figs):.2f} | "
              f"{sum(f['misses'] for f in figs)} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
