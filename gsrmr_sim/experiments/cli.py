"""``gsrmr-experiments``: regenerate the paper's Section V (and our trade-offs) into a report folder.

Usage, options and the report's files and stable keys: docs/experiments.md.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import asdict
import datetime as dt
import glob
import json
import math
import os
from pathlib import Path
import shlex
import subprocess
import sys
import time
from typing import Any

import numpy as np

from gsrmr_common.metrics import pooled_psnr_db
from gsrmr_sim.experiments import paper, tradeoffs
from gsrmr_sim.experiments.composite import Compositor
from gsrmr_sim.experiments.data import DataSettings, SceneData, build_scene_data
from gsrmr_sim.experiments.report import claims, write_summary
from gsrmr_sim.world.scene import SceneError

REPO = Path(__file__).resolve().parents[2]

#: ``--quick``: the live camera size (320×240) and pipeline, tiny counts (10 frames, 32 slots, 15 training steps at
#: 32 px, no compaction).
QUICK_DATA = dict(frames=10, slots=32, train_iterations=15, train_width=32, budget=5000, max_psnr_drop_db=None)
QUICK_PAPER = paper.PaperConfig(convergence_iterations=10, exact_time_limit_s=10.0, strip_slots=4)
QUICK_TRADEOFF = tradeoffs.TradeoffConfig(apo_ns=(1, 3, 10), horizons=(16, 32, 64), render_slots=2, render_repeats=1,
                                          scales=(0.5, 1.0), fractions=(0.25, 1.0), jpeg_qualities=(10, 50, 90),
                                          jpeg_slots=4, exact_time_limit_s=10.0)


def _log(msg: str) -> None:
    print(f"[experiments {time.strftime('%H:%M:%S')}] {msg}", flush=True)


def _git() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True,
                              timeout=5).stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def data_summary(d: SceneData, thresholds: Sequence[float]) -> dict[str, Any]:
    """Headline facts of one scene's data."""
    s = d.settings
    hist = d.train.get("history", [])
    p = d.problem(0.03)
    ok = p.image_ok & p.key_ok
    k = d.record.intrinsics
    return {"width": k.width, "height": k.height, "train_width": d.train.get("config", {}).get("resolution"),
            "frames": d.train.get("train_frames", 0) + d.train.get("heldout_frames", 0), "slots": len(d.record),
            "train_iterations": hist[-1]["iteration"] if hist else None, "train_wall_s": d.train.get("wall_s"),
            "heldout_psnr_db": d.heldout_psnr_db, "gaussians": d.model.num_gaussians,
            "heldout_psnr_live_res_db": d.model_info.get("heldout_psnr_full_res_after_db"),
            "trained_heldout_psnr_db": hist[-1]["heldout_psnr_db"] if hist else None,
            "trained_gaussians": d.train.get("gaussians"), "compacted": s.max_psnr_drop_db is not None,
            "jpeg_quality": d.jpeg_quality, "image_loss_mean": float(np.nanmean(d.image_loss)),
            "min_achievable_loss": float(np.mean(np.fmin(d.gs_loss, d.image_loss))),
            "pose_error": d.pose_error, "channel_seed": d.link.channel_seed,
            "gs_loss_mean": float(d.gs_loss.mean()), "gs_loss_median": float(np.median(d.gs_loss)),
            "gs_loss_p90": float(np.quantile(d.gs_loss, 0.9)), "gs_loss_max": float(d.gs_loss.max()),
            "gs_psnr_db_mean": float(d.gs_psnr_db.mean()), "gs_ssim_mean": float(d.gs_ssim.mean()),
            "gs_psnr_db": pooled_psnr_db(d.gs_psnr_db), "gs_psnr_slot_mean_db": float(d.gs_psnr_db.mean()),
            "distance_m_mean": float(d.distance_m.mean()), "channel_gain_mean": float(d.channel_gain.mean()),
            "image_key_energy_ratio": float(np.median(p.energy_image_j[ok] / p.energy_key_j[ok])),
            "share_lt_below": {f"{t:g}": float(np.mean(d.gs_loss <= t)) for t in thresholds},
            "cache_folder": str(d.folder)}


def consistency_checks(scenes: dict[str, Any], sols: dict[str, dict], datas: dict[str, SceneData]
                       ) -> dict[str, bool]:
    """Internal consistency of the results (the test asserts every one is True)."""
    ok_exact = ok_robomr = ok_pos = ok_apo = ok_split = ok_plan = ok_jpeg = True
    for sc, by_lth in sols.items():
        for lth, res in by_lth.items():
            ex = res["exact"]
            for m, s in res.items():
                if not (math.isfinite(s.energy_j) and s.energy_j > 0):
                    ok_pos = False
                if s.feasible and m != "exact" and ex.energy_j > s.energy_j * (1 + 1e-9):
                    ok_exact = False
            if res["robomr"].mean_loss != 0.0 or not res["robomr"].feasible:
                ok_robomr = False
            if not res["apo"].feasible or res["apo"].mean_loss > lth * (1 + 1e-9):
                ok_apo = False
        jpeg_floor = float(np.nanmin(datas[sc].image_loss))
        for row in scenes[sc]["table1"]["per_threshold"].values():
            for m, r in row.items():
                if not isinstance(r, dict):
                    continue
                if abs(r["parts_sum"] - r["loss"]) > 1e-9:  # plan + JPEG + pose + fallback = measured
                    ok_split = False
                if m != paper.APO_JPEG and abs(r["plan_loss"] - r["predicted_loss"]) > 1e-9:
                    ok_plan = False  # the solver's loss is Σ L_t over the slots without an image
                if r["images"] and r["jpeg_loss"] < r["images"] * jpeg_floor / len(datas[sc].record) - 1e-12:
                    ok_jpeg = False  # image slots carry at least the smallest J_t the survey measured
    return {"exact_le_every_feasible_method": ok_exact, "robomr_loss_zero": ok_robomr,
            "energies_positive_finite": ok_pos, "apo_feasible_every_lth": ok_apo,
            "table1_loss_split_adds_up": ok_split, "table1_plan_is_solver_loss": ok_plan,
            "table1_image_slots_carry_jpeg_loss": ok_jpeg}


def node_suite_runs(pattern: str) -> dict[str, Any]:
    """Headline numbers of the node suite's recorded runs (``gsrmr-demo`` report folders), if any."""
    keys = ("slots", "images_sent", "energy_j", "energy_upload_all_j", "energy_ratio_vs_upload_all", "mean_loss",
            "psnr_db", "psnr_slot_mean_db", "ssim", "slots_on_time", "faults")
    runs = {}
    for folder in sorted(glob.glob(pattern)):
        path = Path(folder) / "summary.json"
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
        runs[Path(folder).name] = {k: data.get(k) for k in keys}
    return runs


def run(out: Path, *, quick: bool, cache: Path, scenes: Sequence[str], channel_seed: int | None, seed: int,
        train_seconds: float | None, skip_tradeoffs: bool, argv: Sequence[str],
        demo_glob: str = "", train_iterations: int | None = None) -> dict[str, Any]:
    """Run every experiment and write the report into ``out``; returns the summary dict."""
    t_start = time.perf_counter()
    started = dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")
    out.mkdir(parents=True, exist_ok=True)
    pcfg = QUICK_PAPER if quick else paper.PaperConfig()
    tcfg = QUICK_TRADEOFF if quick else tradeoffs.TradeoffConfig()
    extra: dict[str, Any] = {"channel_seed": channel_seed, "seed": seed}
    if train_seconds is not None or train_iterations is not None:
        extra.update(train_seconds=train_seconds, train_iterations=train_iterations)
    datas: dict[str, SceneData] = {}
    for sc in scenes:
        t0 = time.perf_counter()
        datas[sc] = build_scene_data(DataSettings(scene=sc, **{**(QUICK_DATA if quick else {}), **extra}), cache, _log)
        _log(f"{sc}: data ready ({time.perf_counter() - t0:.1f} s)")
    main = scenes[0]
    summary: dict[str, Any] = {"command": "gsrmr-experiments " + shlex.join(argv), "argv": list(argv),
                               "quick": quick, "started_utc": started, "git": _git(), "cache": str(cache),
                               "channel_seed": datas[main].link.channel_seed, "seed": seed, "main_scene": main,
                               "resolution": {sc: f"{d.record.intrinsics.width}x{d.record.intrinsics.height}"
                                              for sc, d in datas.items()},
                               "settings": {sc: asdict(d.settings) for sc, d in datas.items()},
                               "paper_config": asdict(pcfg), "scenes": {}}
    sols: dict[str, dict] = {}
    comps: dict[str, Compositor] = {}
    for sc, d in datas.items():
        t0 = time.perf_counter()
        sols[sc] = paper.solve_all(d, pcfg)
        comps[sc] = Compositor(d.server, d.gs_loss)
        res: dict[str, Any] = {"data": data_summary(d, pcfg.thresholds)}
        res["fig4b"] = paper.fig4b(d, sols[sc], pcfg, out)
        res["table1"] = paper.table1(d, sols[sc], pcfg, comps[sc], out)
        if sc == main:
            res["fig4a"] = paper.fig4a(d, pcfg, out)
        res["claims"] = claims(res)
        res["sensitivity_saving_factor"] = paper.sensitivity(d, pcfg, out)
        summary["scenes"][sc] = res
        _log(f"{sc}: Fig. 4b + Table 1 done ({time.perf_counter() - t0:.1f} s)")
    summary["fig5"] = paper.fig5(datas[main], sols[main], pcfg, comps[main], out)
    if not skip_tradeoffs:
        t0 = time.perf_counter()
        d = datas[main]
        lth = tcfg.loss_threshold
        summary["tradeoffs"] = {
            "scheduler": tradeoffs.scheduler_tradeoff(d, sols[main][lth], tcfg, out),
            "renderer": tradeoffs.renderer_tradeoff(d, tcfg, out),
            "jpeg": tradeoffs.jpeg_tradeoff(d, tcfg, d.problem(lth).image_bits, out),
            "training": tradeoffs.training_tradeoff(list(datas.values()), out),
        }
        _log(f"trade-offs done ({time.perf_counter() - t0:.1f} s)")
    summary["node_suite"] = node_suite_runs(demo_glob) if demo_glob else {}
    summary["checks"] = consistency_checks(summary["scenes"], sols, datas)
    summary["load_average"] = [round(v, 2) for v in os.getloadavg()]
    summary["elapsed_s"] = time.perf_counter() - t_start
    summary["files"] = sorted({*(p.name for p in out.iterdir() if p.is_file()), "summary.json", "summary.md"})
    write_summary(out, summary)
    _log(f"report written to {out} ({summary['elapsed_s']:.0f} s)")
    return summary


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point (``gsrmr-experiments``)."""
    args_list = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(prog="gsrmr-experiments", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="report folder (created)")
    ap.add_argument("--quick", action="store_true", help="tiny sizes for a smoke run (≤ 2 min)")
    ap.add_argument("--cache", default=str(REPO / ".cache" / "gsrmr"),
                    help="where models and round records are cached (keyed by scene file + recipe; the default is "
                         "gsrmr-demo's cache, so both use one model)")
    ap.add_argument("--scenes", default="sandbox,garden", help="comma-separated scene names; the first is the main one")
    ap.add_argument("--channel-seed", type=int, default=None,
                    help="seed of the simulated channel realisation (default: config/link.yaml's, as gsrmr-demo)")
    ap.add_argument("--seed", type=int, default=0, help="round-2 start jitter and trainer seed")
    ap.add_argument("--train-seconds", type=float, default=None,
                    help="GS training wall-time budget for every scene (default: each scene's model section)")
    ap.add_argument("--train-iterations", type=int, default=None, help="GS training steps for every scene")
    ap.add_argument("--skip-tradeoffs", action="store_true", help="only the paper's figures and table")
    ap.add_argument("--demo-reports", default=str(REPO / "reports" / "demo-*"),
                    help="glob of gsrmr-demo report folders whose summary.json is quoted (empty: none)")
    a = ap.parse_args(args_list)
    scenes = [s.strip() for s in a.scenes.split(",") if s.strip()]
    if not scenes:
        ap.error("--scenes is empty")
    try:
        run(Path(a.out), quick=a.quick, cache=Path(a.cache), scenes=scenes, channel_seed=a.channel_seed,
            seed=a.seed, train_seconds=a.train_seconds, skip_tradeoffs=a.skip_tradeoffs, argv=args_list,
            demo_glob=a.demo_reports, train_iterations=a.train_iterations)
    except (SceneError, FileNotFoundError) as exc:
        print(f"gsrmr-experiments: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
