"""gsrmr-key-estimates: how well the scheduler knew the loss its round spent, after the run (hindsight): each
gsrmr-demo report's key-slot estimates and slot bookings, four ways, against the scorer's loss. The bookings and
the table: docs/scheduling.md, "Reading recorded runs: the analysis tools"."""

from __future__ import annotations

import argparse
import os
from pathlib import Path
import statistics

from gsrmr_scheduler.loss_predictor import LossPredictor
from gsrmr_scheduler.planner.budget import LossBudget
from gsrmr_server.recording import read_slots_csv
from gsrmr_sim.analysis.planner_replay import make_planner, scene_changes, scheduler_params

PROG = "gsrmr-key-estimates"


def change_slots(report: Path, rows: list[dict]) -> list[int]:
    """The slots the run's robot found a scene change in: its ledger's column, else its log."""
    if any(r.get("scene_change") is not None for r in rows):
        return [int(r["slot"]) for r in rows if r.get("scene_change")]
    return scene_changes(report)[0]


def booking_errors(report: Path) -> dict[str, float]:
    """{booking: (Σ booked − Σ left) over the scored slots / their number} for one report (docs/scheduling.md)."""
    rows = [r for r in read_slots_csv(report / "slots.csv") if r.get("slot") is not None]
    planner = make_planner(scheduler_params(report), {})
    seed, offset = planner.forecast.model.seed_map, planner.forecast.sample_offset
    scored = [r for r in rows if r.get("scored") and r.get("loss") is not None and r.get("x") is not None]
    if not scored:
        raise SystemExit(f"key_estimates: {report} has no scored slot with its loss")
    posed = [r for r in rows if r.get("pose_a_m") is not None]
    out = {}
    for name, told in (("interpolated", ()), ("stepped", change_slots(report, rows))):
        model = LossPredictor(seed)
        for r in posed:
            if r["x"] == 1 and r.get("gs_loss") is not None:
                model.observe(int(r["slot"]), (r["pose_a_m"], r["pose_b_m"], r["pose_theta_rad"]),
                              max(r["gs_loss"] - offset, 0.0))
        for slot in told:
            model.note_change(slot)

        def key_loss(slot: int, pose, model=model) -> float:
            return model.estimate(slot, pose)

        for composed in (False, True):
            budget = LossBudget(key_loss, image_slot_loss=planner.config.image_slot_loss)
            booked, pose = 0.0, (posed[0]["pose_a_m"], posed[0]["pose_b_m"], posed[0]["pose_theta_rad"])
            for r in scored:
                if composed and r.get("source"):
                    budget.record_composed(int(r["slot"]), r["source"])
                if r.get("pose_a_m") is not None:  # a slot composed at no pose: charged at the last one
                    pose = (r["pose_a_m"], r["pose_b_m"], r["pose_theta_rad"])
                booked += budget.slot_loss(int(r["slot"]), int(r["x"]), pose)
            left = sum(r["loss"] for r in scored)
            out[name + (" + composed" if composed else "")] = (booked - left) / len(scored)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("reports", nargs="+", type=Path, metavar="REPORT_DIR",
                    help="gsrmr-demo report folders (reports/demo-*)")
    ap.add_argument("--per-run", action="store_true")
    args = ap.parse_args(argv)
    runs = [(report, booking_errors(report)) for report in args.reports]
    names = list(runs[0][1])
    print(f"# gsrmr-key-estimates: {len(runs)} reports ({os.cpu_count()} CPUs, load average "
          f"{os.getloadavg()[0]:.1f}); HINDSIGHT: the booked loss against the scorer's, after the runs")
    if args.per_run:
        print("| run | " + " | ".join(names) + " |")
        print("|---" * (len(names) + 1) + "|")
        for report, e in runs:
            print(f"| {report.name} | " + " | ".join(f"{e[n]:+.5f}" for n in names) + " |")
    print("| booking | mean error of the round's mean loss | sd over runs | most under | most over | mean abs |")
    print("|---|---|---|---|---|---|")
    for name in names:
        v = [e[name] for _, e in runs]
        print(f"| {name} | {statistics.fmean(v):+.5f} | {statistics.pstdev(v):.5f} | {min(v):+.5f} | "
              f"{max(v):+.5f} | {statistics.fmean(abs(x) for x in v):.5f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
