"""gsrmr-plausibility-replay: the plausibility rules replayed over recorded clean rounds (gsrmr-demo reports): what
each would have refused, the false alarms (no ROS, no model). What it offers each rule: docs/scheduling.md, "Reading
recorded runs: the analysis tools"; the rules: docs/security.md, "Plausibility, even from the right writer"."""

from __future__ import annotations

import argparse
import csv
import math
from pathlib import Path

import yaml

from gsrmr_common.channel_band import GainBand
from gsrmr_common.link_model import LinkBudget
from gsrmr_common.plausibility import MR_LOSS_MAX, PoseTrack
from gsrmr_scheduler.loss_map import LossMap
from gsrmr_scheduler.loss_predictor import MAX_LOG_DEVIATION, LossPredictor
from gsrmr_sim.sim_stack import config_dir

PROG = "gsrmr-plausibility-replay"


def link_budget(path: Path) -> tuple[LinkBudget, float]:
    """The link model of a ``link.yaml`` (``/**: ros__parameters:``) and its slot length τ [s]."""
    params = yaml.safe_load(path.read_text())["/**"]["ros__parameters"]
    fields = {f: params[f] for f in ("pathloss_db_at_1m", "pathloss_exponent", "rician_k") if f in params}
    if "server_position_m" in params:
        fields["server_position_m"] = tuple(params["server_position_m"])
    return LinkBudget(**fields), float(params.get("slot_s", 0.1))


def _float(value: str) -> float | None:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def replay(report: Path, link: LinkBudget, slot_s: float, seed: LossMap | None = None) -> dict:
    """What the rules say of one report's scored slots (and, with ``seed``, the robust aggregation)."""
    with open(report / "slots.csv", newline="") as f:
        rows = sorted((r for r in csv.DictReader(f) if r.get("scored") == "1"), key=lambda r: int(r["slot"]))
    track = PoseTrack(max_speed_mps=1.5, slot_s=slot_s)  # the server's and scheduler's default
    band = GainBand(link.rician_k, link.pathloss_exponent)
    out = {"report": report.name, "slots": len(rows), "keys": 0, "pose_jump": 0, "gains": 0, "gain_band": 0,
           "gain_bias": 0, "ratio_db_min": math.inf, "ratio_db_max": -math.inf, "losses": 0, "loss_range": 0,
           "model_dev_x": math.nan, "model_clipped": 0, "cell_dev_x": math.nan, "cell_clipped": 0}
    model = LossPredictor(LossMap.from_json(seed.to_json())) if seed is not None else None
    live = LossMap.from_json(seed.to_json()) if seed is not None else None
    model_dev = cell_dev = 0.0
    for r in rows:
        slot = int(r["slot"])
        a, b = _float(r.get("pose_a_m")), _float(r.get("pose_b_m"))
        if a is not None and b is not None:
            out["keys"] += 1
            out["pose_jump"] += not track.offer(slot, a, b)
        gain = _float(r.get("channel_gain"))
        if gain is not None and gain > 0 and a is not None and b is not None:
            mean, distance = link.mean_gain((a, b)), link.distance_m((a, b))
            out["gains"] += 1
            reason = band.problem(gain, mean, distance)
            if reason:
                out[reason] += 1
            ratio_db = 10 * math.log10(gain / mean)
            out["ratio_db_min"] = min(out["ratio_db_min"], ratio_db)
            out["ratio_db_max"] = max(out["ratio_db_max"], ratio_db)
        loss = _float(r.get("gs_loss"))
        if r.get("source") == "image" and loss is not None:
            out["losses"] += 1
            out["loss_range"] += not 0.0 <= loss <= MR_LOSS_MAX
            theta = _float(r.get("pose_theta_rad"))
            if model is not None and live is not None and a is not None and b is not None and theta is not None:
                pose = (a, b, theta)
                prior = seed.predict(*pose)
                if prior > 1e-4:  # the predictor's own floor (_FLOOR)
                    dev = abs(math.log(max(loss, 1e-4) / prior) - model.level)
                    model_dev = max(model_dev, dev)
                    out["model_clipped"] += dev > MAX_LOG_DEVIATION
                cell = live.cells.get(live.key(*pose))
                if cell is not None and cell.count > 0:
                    ratio = max(loss / max(cell.mean, 1e-3), cell.mean / max(loss, 1e-12))
                    cell_dev = max(cell_dev, ratio)
                    out["cell_clipped"] += ratio > live.outlier_factor
                model.observe(slot, pose, loss)
                live.add(*pose, loss)
    out["relocalisations"] = track.relocalisations
    if model is not None:
        out["model_dev_x"], out["cell_dev_x"] = math.exp(model_dev), cell_dev
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("reports", nargs="+", type=Path, metavar="REPORT_DIR",
                    help="gsrmr-demo report folders (reports/demo-*)")
    ap.add_argument("--link", type=Path, default=config_dir() / "link.yaml",
                    help="the link model's parameter file (default: the package's config/link.yaml)")
    ap.add_argument("--seed-map", type=Path, default=None, help="the scheduler's seed loss map (JSON)")
    args = ap.parse_args(argv)
    seed = LossMap.load(args.seed_map) if args.seed_map else None
    link, slot_s = link_budget(args.link)
    band = GainBand(link.rician_k, link.pathloss_exponent)
    print(f"# gsrmr-plausibility-replay: {len(args.reports)} report(s); link K={link.rician_k}, "
          f"α={link.pathloss_exponent}; gain band [{10 * math.log10(band.low):.1f}, {10 * math.log10(band.high):.1f}] "
          f"dB per sample (before the position widening), clean false-alarm rate ≤ {band.false_alarm_per_sample():.2g} "
          "per sample")
    cols = ("slots", "keys", "pose_jump", "relocalisations", "gains", "gain_band", "gain_bias", "ratio_db_min",
            "ratio_db_max", "losses", "loss_range", "model_dev_x", "model_clipped", "cell_dev_x", "cell_clipped")
    print("| report | " + " | ".join(cols) + " |")
    print("|" + "---|" * (len(cols) + 1))
    total = dict.fromkeys(cols, 0)
    total["ratio_db_min"], total["ratio_db_max"] = math.inf, -math.inf
    total["model_dev_x"] = total["cell_dev_x"] = 0.0
    largest = ("ratio_db_max", "model_dev_x", "cell_dev_x")
    for report in args.reports:
        r = replay(report, link, slot_s, seed)
        print(f"| {r['report']} | " + " | ".join(f"{r[c]:.1f}" if isinstance(r[c], float) else str(r[c])
                                                  for c in cols) + " |")
        for c in cols:
            if isinstance(r[c], float) and math.isnan(r[c]):
                total[c] = math.nan
                continue
            total[c] = (min if c == "ratio_db_min" else max if c in largest else int.__add__)(total[c], r[c])
    print("| **all** | " + " | ".join(f"{total[c]:.1f}" if isinstance(total[c], float) else str(total[c])
                                     for c in cols) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
