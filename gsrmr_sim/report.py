"""``gsrmr-demo``'s output, one robot's or each robot's of a fleet: its log lines, figures and report folder.

The report folder and the summary's keys: README.md, "Main job"; the metrics: docs/experiments.md, "Metrics".
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
import sys
import time
from typing import TYPE_CHECKING

import cv2
from matplotlib.figure import Figure
import numpy as np

from gsrmr_common.metrics import pooled_psnr_db
from gsrmr_server.compose_levels import LEVEL_NAMES
from gsrmr_server.recording import TOPIC_MR_IMAGE, read_mcap, read_slots_csv, write_slots_csv
from gsrmr_sim.hindsight import hindsight_summary
from gsrmr_sim.scores import join_scores

if TYPE_CHECKING:
    from gsrmr_sim.models import BuiltModel


def log(msg: str) -> None:
    """One progress line of the demo on stdout: ``[demo HH:MM:SS] msg``."""
    print(f"[demo {time.strftime('%H:%M:%S')}] {msg}", flush=True)


def summarise(rows: list[dict], slot_s: float) -> dict:
    """Headline figures of a run from its per-slot rows."""

    def col(name: str) -> np.ndarray:
        return np.array([r[name] for r in rows if r[name] is not None], dtype=np.float64)

    energy, upload_all = col("energy_j").sum(), col("energy_upload_all_j").sum()
    on_time = int((col("latency_ms") <= 1e3 * slot_s).sum())
    levels = [r.get("level") for r in rows]
    return {"slots": len(rows), "slots_on_time": on_time, "slots_missed": len(rows) - on_time,
            "slots_degraded": {name: sum(1 for v in levels if v == k) for k, name in enumerate(LEVEL_NAMES) if k},
            "slots_scored": int(col("loss").size),
            "images_sent": int(sum(1 for r in rows if r["source"] == "image")),
            "energy_j": float(energy), "energy_upload_all_j": float(upload_all),
            "energy_ratio_vs_upload_all": float(upload_all / energy) if energy > 0 else math.nan,
            "mean_loss": float(col("loss").mean()) if col("loss").size else math.nan,
            # the two PSNRs of every report (docs/experiments.md, "Metrics"): pooled, and the per-slot mean
            "psnr_db": pooled_psnr_db(col("psnr_db")),
            "psnr_slot_mean_db": float(col("psnr_db").mean()) if col("psnr_db").size else math.nan,
            "ssim": float(col("ssim").mean()) if col("ssim").size else math.nan,
            "faults": sum(1 for r in rows if r["faults"])}


#: the share of a round's composed slots the scorer must score for its figures to stand (README, "Main job")
MIN_SCORED_SHARE = 0.99


def unmeasured(summary: dict) -> str | None:
    """Why a run measured too little to stand for a result (``None``: it measured enough): the scorer scored under
    :data:`MIN_SCORED_SHARE` of the composed slots, or the hindsight optimum had no slot (no regret)."""
    slots, scored = summary["slots"], summary["slots_scored"]
    if slots == 0:
        return "the round composed no slot"
    if scored < MIN_SCORED_SHARE * slots:
        return (f"the scorer scored {scored} of the round's {slots} composed slots (under "
                f"{MIN_SCORED_SHARE:.0%}): its mean loss and PSNR measure too little of the round")
    if not summary.get("hindsight_slots"):
        return "no slot has every hindsight value: the regret is not measured"
    return None


#: gsrmr-demo's exit status when a round measured too little (:func:`unmeasured`)
EXIT_UNMEASURED = 3


def exit_status(summaries: list[dict]) -> int:
    """0, or :data:`EXIT_UNMEASURED` with each reason on stderr when a summary (a round's, a robot's) says
    :func:`unmeasured` (its ``unmeasured`` key)."""
    failed = [s for s in summaries if s.get("unmeasured")]
    for summary in failed:
        where = ", ".join(f"{k} {summary[k]}" for k in ("robot", "round") if k in summary)
        print(f"gsrmr-demo: not measured{f' ({where})' if where else ''}: {summary['unmeasured']}", file=sys.stderr,
              flush=True)
    return EXIT_UNMEASURED if failed else 0


def run_summary(args: argparse.Namespace, rows: list[dict], slot_s: float, built: BuiltModel,
                channel_seed: int | None) -> dict:
    """The summary of one robot's round (the demo's JSON without hosts, link and report folder): headline
    figures, the model, the settings and the hindsight optimum."""
    summary = {"scene": args.scene, "loss_threshold": args.loss_threshold, **summarise(rows, slot_s),
            "model_gaussians": built.model.num_gaussians, "model_heldout_psnr_db": built.heldout_psnr_db,
            "model_compacted": not args.no_compact, "channel_seed": channel_seed, "oracle": args.oracle,
            "method": args.method, "loss_map_seed": "round-2 survey (oracle)" if args.oracle else "mapping round",
            **hindsight_summary(rows, args.loss_threshold)}
    summary["unmeasured"] = unmeasured(summary)
    return summary


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
        every = join_scores(read_slots_csv(recording / "slots.csv"), recording)
        for i, row in enumerate(every):
            row["scored"] = int(first_moving <= i < first_moving + scored)
        write_slots_csv(out / "slots.csv", every)


def _finite_or_none(value: object) -> object:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite_or_none(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite_or_none(v) for v in value]
    return value


def summary_json(summary: dict, indent: int | None = None) -> str:
    """The summary as strict JSON: a figure that is not known (NaN, e.g. the held-out PSNR of a ``--model`` file)
    or not finite is ``null`` — Python's bare ``NaN`` is not JSON, and strict readers (jq, JavaScript) refuse it."""
    return json.dumps(_finite_or_none(summary), indent=indent, allow_nan=False)


def write_report(report_dir: Path, rows: list[dict], summary: dict) -> None:
    """x/p profile plot, MR image strip, CSV copy, summary.json."""
    report_dir.mkdir(parents=True, exist_ok=True)
    slots = np.arange(len(rows))
    x = np.array([r["x"] if r["x"] is not None else np.nan for r in rows], float)
    p = np.array([r["power_w"] if r["power_w"] is not None else np.nan for r in rows], float)
    fig = Figure(figsize=(9, 4.5))  # no pyplot: no global backend, nothing to close
    ax = fig.subplots(2, 1, sharex=True)
    ax[0].step(slots, x, where="post")
    ax[0].set_ylabel("x_t (1 = image)")
    ax[1].semilogy(slots, np.where(p > 0, p, np.nan), ".", ms=3)
    ax[1].set_ylabel("p_t [W]")
    ax[1].set_xlabel("slot")
    fig.suptitle(f"content switching and power (energy ratio vs upload-all "
                 f"{summary['energy_ratio_vs_upload_all']:.1f}×)")
    fig.tight_layout()
    fig.savefig(report_dir / "profile_x_p.png", dpi=120)
    mcap = report_dir / "run.mcap"
    if mcap.exists():
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
    (report_dir / "summary.json").write_text(summary_json(summary, indent=1))
