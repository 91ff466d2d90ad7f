"""What slipping odometry costs and what the server's localization wins back: ``gsrmr-demo`` per seed with realistic
odometry and localization (the default), with ``--odometry perfect`` and with ``--no-localization``.

Usage: ``.venv/bin/python bench/acceptance/localization.py [--seeds 1-5] [--scales 1] [--modes default,perfect,off]
[-- DEMO_ARGS...]``.
Prints one row per run: images, energy ratio vs upload-all, mean loss and whether it is within L_th, slots on time,
regret (hindsight, after the run) and the pose keys' errors against the mock base's true poses (hindsight, after the
run: median and p95, cm and degrees); then per seed the default run's energy ratio over the perfect run's (the
acceptance asks ≥ 0.8). ``--scales 0.5,1,2,4`` sweeps ``--odometry-error-scale`` (the default mode's rows only).
"""

from __future__ import annotations

import argparse
import signal
import statistics
import sys

from gsrmr_sim.demo_runs import run_once
from gsrmr_sim.machine_probe import machine_line

MODES = {"default": [], "perfect": ["--odometry", "perfect"], "off": ["--no-localization"]}
COLUMNS = ("images_sent", "energy_ratio_vs_upload_all", "mean_loss", "within", "slots_on_time", "regret",
           "pose_cm_median", "pose_cm_p95", "pose_deg_median", "pose_deg_p95")


def _exit_on_sigterm(signum: int, _frame: object) -> None:
    raise SystemExit(128 + signum)


def seed_list(text: str) -> list[int]:
    """``1-5`` or ``1,3,4``."""
    if "-" in text:
        a, b = text.split("-", 1)
        return list(range(int(a), int(b) + 1))
    return [int(v) for v in text.split(",")]


def row(s: dict) -> dict:
    """The table's cells of one run's summary."""
    return {"images_sent": s["images_sent"], "energy_ratio_vs_upload_all": s["energy_ratio_vs_upload_all"],
            "mean_loss": s["mean_loss"], "within": s["mean_loss"] <= s["loss_threshold"],
            "slots_on_time": f"{s['slots_on_time']}/{s['slots']}", "regret": s.get("regret", float("nan")),
            "pose_cm_median": 100 * s["pose_error_m_median"], "pose_cm_p95": 100 * s["pose_error_m_p95"],
            "pose_deg_median": s["pose_error_deg_median"], "pose_deg_p95": s["pose_error_deg_p95"]}


def cell(v: object) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def main() -> int:
    signal.signal(signal.SIGTERM, _exit_on_sigterm)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="1-5", help="channel seeds (the odometry draw follows them)")
    ap.add_argument("--scales", default="1", help="--odometry-error-scale values for the default mode")
    ap.add_argument("--modes", default="default,perfect,off", help=f"of {', '.join(MODES)}")
    ap.add_argument("demo_args", nargs="*", help="passed to gsrmr-demo (after --)")
    args = ap.parse_args()
    seeds, scales = seed_list(args.seeds), [float(v) for v in args.scales.split(",")]
    modes = args.modes.split(",")
    print(f"# bench/acceptance/localization.py: seeds {seeds}, modes {modes}, scales {scales}, gsrmr-demo "
          f"{' '.join(args.demo_args)} (before the runs: {machine_line()})", flush=True)
    print("| seed | mode | scale | " + " | ".join(COLUMNS) + " | wall s |")
    print("|" + "---|" * (len(COLUMNS) + 4))
    ratios: dict[tuple[int, str, float], float] = {}
    rows: dict[tuple[str, float], list[dict]] = {}
    for seed in seeds:
        for mode in modes:
            for scale in scales if mode == "default" else [1.0]:
                extra = ["--odometry-error-scale", str(scale)] if mode == "default" and scale != 1.0 else []
                s = run_once([*args.demo_args, *MODES[mode], *extra, "--channel-seed", str(seed)])
                r = row(s)
                rows.setdefault((mode, scale), []).append(r)
                ratios[(seed, mode, scale)] = s["energy_ratio_vs_upload_all"]
                print(f"| {seed} | {mode} | {scale:g} | " + " | ".join(cell(r[c]) for c in COLUMNS)
                      + f" | {s['wall_s']:.0f} |", flush=True)
    for (mode, scale), rs in rows.items():
        med = {c: statistics.median(r[c] for r in rs) for c in COLUMNS
               if c not in ("within", "slots_on_time")}
        print(f"| median | {mode} | {scale:g} | " + " | ".join(cell(med.get(c, "")) if c in med else
                                                            f"{sum(bool(r[c]) for r in rs)}/{len(rs)}"
                                                            if c == "within" else "" for c in COLUMNS) + " | |")
    if "perfect" in modes and "default" in modes:
        print("\n| seed | scale | energy ratio, default / perfect |\n|---|---|---|")
        for seed in seeds:
            for scale in scales:
                ratio = ratios[(seed, "default", scale)] / ratios[(seed, "perfect", 1.0)]
                print(f"| {seed} | {scale:g} | {ratio:.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
