"""summary.json (stable keys) and summary.md (the paper's claims beside ours) of an experiments run."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from gsrmr_sim.experiments.paper import FIG4B_METHODS, loss_split_markdown, table1_markdown

#: The paper's headline claims (Sec. V), keyed as in ``summary.json["claims"][scene]``.
PAPER_CLAIMS = {
    "saving_10x_every_lth": "GS energy-saving factor (RoboMR energy / APO energy) >= 10 at every L_th",
    "saving_100x_at_0.04": "GS energy-saving factor > 100 at L_th = 0.04",
    "apo_psnr_gain_6db": "APO PSNR >= 6 dB above MaxRate and Fairness at equal energy (every Table 1 L_th)",
    "apo_20pct_below_search_at_0.04": "APO energy > 20% below Search at L_th = 0.04",
}


def _f(v: Any, fmt: str = ".4g") -> str:
    if v is None:
        return "n/a"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return "inf" if math.isinf(v) else format(v, fmt)
    return str(v)


def claims(scene_res: dict[str, Any]) -> dict[str, Any]:
    """Evaluate the paper's claims on one scene's results (numbers, thresholds, holds)."""
    per = scene_res["fig4b"]["per_threshold"]
    factors = {k: v["saving_factor_apo"] for k, v in per.items()}
    out: dict[str, Any] = {}
    mn = min(factors.values())
    out["saving_10x_every_lth"] = {"paper": ">= 10", "ours": mn, "per_threshold": factors, "holds": mn >= 10}
    f04 = factors.get("0.04")
    out["saving_100x_at_0.04"] = {"paper": "> 100", "ours": f04, "holds": None if f04 is None else f04 > 100}
    gains = {k: v["apo_psnr_gain_db"] for k, v in scene_res["table1"]["per_threshold"].items()}
    gains_slot = {k: v["apo_psnr_gain_slot_mean_db"] for k, v in scene_res["table1"]["per_threshold"].items()}
    g = min(gains.values()) if gains else None
    out["apo_psnr_gain_6db"] = {"paper": ">= 6 dB", "ours": g, "per_threshold": gains,
                                "per_threshold_slot_mean_psnr": gains_slot,
                                "holds": None if g is None else g >= 6}
    s04 = per.get("0.04", {}).get("apo_below_search_pct")
    out["apo_20pct_below_search_at_0.04"] = {"paper": "> 20 %", "ours": s04,
                                             "holds": None if s04 is None else s04 > 20}
    return out


def _why(scene: str, res: dict[str, Any]) -> list[str]:
    """Plain explanations of where our numbers differ, derived from the data."""
    d = res["data"]
    lines = []
    c = res["claims"]
    share = d["share_lt_below"]
    lines.append(f"* `{scene}`: GS loss L_t has mean {d['gs_loss_mean']:.4f}, median {d['gs_loss_median']:.4f}, "
                 f"p90 {d['gs_loss_p90']:.4f} (held-out PSNR of the GS model {_f(d['heldout_psnr_db'], '.2f')} dB at "
                 f"its training width {_f(d['train_width'])} px, {_f(d.get('heldout_psnr_live_res_db'), '.2f')} dB at "
                 f"the live {d['width']} px, "
                 f"{d['gaussians']} Gaussians, {d['width']}x{d['height']} px). Share of slots with L_t <= L_th: "
                 + ", ".join(f"{k}: {v:.2f}" for k, v in share.items()) + ".")
    per = res["fig4b"]["per_threshold"]
    t_n = d["slots"]
    imgs = ", ".join(f"{k}: {v['apo_images']}/{t_n} (T/#images {t_n / max(v['apo_images'], 1):.2g}, saving "
                     f"{v['saving_factor_apo']:.3g}x)" for k, v in per.items())
    lines.append(f"  APO uploads images in {imgs} slots. An image costs ~{d['image_key_energy_ratio']:.3g}x a key "
                 "in the same slot, and Rician fading (K = 1) makes the per-slot image energy vary by orders of "
                 "magnitude, so APO spends its loss budget on the deep-fade slots: the saving exceeds T/#images.")
    if not c["saving_10x_every_lth"]["holds"] or not c["saving_100x_at_0.04"]["holds"]:
        lines.append("  The saving claims fail here because our CPU-trained GS model's L_t is large relative to "
                     f"L_th (median {d['gs_loss_median']:.3f}, i.e. most single slots already exceed every L_th), "
                     "so the budget T·L_th turns only part of the slots into keys; the paper's GS model (GPU, "
                     "30k iterations) renders most views at a loss well below L_th.")
    t1 = res["table1"]["per_threshold"]
    und = {k: (v["maxrate"]["undelivered"], v["fairness"]["undelivered"]) for k, v in t1.items()}
    lines.append("  Table 1: MaxRate/Fairness undelivered slots (MaxRate, Fairness) at APO's energy: "
                 + ", ".join(f"{k}: {a}, {b}" for k, (a, b) in und.items())
                 + ". PSNR in the claims is the pooled PSNR −10·log10(mean over slots of the MSE): a mean of per-slot "
                 "PSNRs is dominated by image slots (identical images score the 100 dB cap); both are in "
                 "table1_*.csv. The paper does not state its averaging.")
    diff = {k: (v["apo"]["loss"] - v["apo"]["predicted_loss"], v["apo"]["jpeg_loss"], v["apo"]["pose_loss"])
            for k, v in t1.items()}
    lines.append("  Table 1 is measured on composed images: APO's composed loss exceeds its plan by " + ", ".join(
        f"{k}: {d:+.4f} (JPEG {j:+.4f}, pose {p:+.5f})" for k, (d, j, p) in diff.items())
        + " — the paper scores image slots as lossless and key slots at the true pose; the robot's JPEG "
        f"(q{d['jpeg_quality']}, mean J_t {d['image_loss_mean']:.4f}) and its odometry (mean error "
        f"{1e3 * d['pose_error']['position_mean_m']:.2f} mm) are what the plan leaves out.")
    floor = d["min_achievable_loss"]
    if floor > min(float(k) for k in t1):
        lines.append(f"  Here an image slot itself loses {d['image_loss_mean']:.4f} on average (JPEG "
                     f"q{d['jpeg_quality']} of this scene's texture): the lowest mean loss any schedule can compose "
                     f"(each slot its better option, min(L_t, J_t)) is {floor:.4f}, so every L_th below it is out of "
                     "reach of any schedule at this JPEG quality.")
    within = [float(k) >= v["apo_jpeg"]["loss"] for k, v in t1.items() if "apo_jpeg" in v]
    if within:
        lines.append(f"  `apo_jpeg` (APO planned with J_t, ours) composes within L_th at {sum(within)} of "
                     f"{len(within)} thresholds where it is feasible.")
    if c["apo_psnr_gain_6db"]["holds"] is False:
        gs = c["apo_psnr_gain_6db"]
        fair = {k: v["fairness"]["psnr_db"] for k, v in t1.items()}
        lines.append("  The PSNR claim fails on the pooled PSNR (gains " + ", ".join(
            f"{k}: {v:+.2f} dB" for k, v in gs["per_threshold"].items()) + "): at APO's small energy Fairness "
            "delivers a key in every slot (i.e. RoboGS, pooled " + ", ".join(f"{v:.2f}" for v in fair.values()) +
            " dB), which is already good where the GS model is good; the pooled MSE is dominated by the few "
            "worst GS slots that APO also leaves as keys when L_th is loose. With the mean of per-slot PSNRs "
            "the gains are " + ", ".join(f"{k}: {v:+.2f} dB" for k, v in gs["per_threshold_slot_mean_psnr"].items())
            + ".")
    if c["apo_20pct_below_search_at_0.04"]["holds"] is False:
        lines.append(f"  Search reaches {_f(per.get('0.04', {}).get('apo_below_search_pct'), '.3g')} % vs APO at "
                     "0.04: our Search (randomized local search from ranking: random flips and 1-for-1 swaps, our "
                     "reading of the paper's citation) finds near-optimal knapsack solutions on this instance, "
                     "so APO's margin over it is small or negative; the exact optimum (certified) and Exchange "
                     "(1-for-k exchanges) show how close both are.")
    return lines


def write_summary(out: Path, summary: dict[str, Any]) -> None:
    """Write ``summary.json`` and ``summary.md`` into ``out``."""
    (out / "summary.json").write_text(json.dumps(summary, indent=1, default=float))
    quick = " (QUICK mode: tiny, not representative)" if summary["quick"] else ""
    L = [f"# gsrmr experiments: paper Section V on our data{quick}",
         "", f"Command: `{summary['command']}`  ", f"Started {summary['started_utc']}, wall time "
         f"{summary['elapsed_s']:.0f} s, git {summary['git']}, load average {summary['load_average']} "
         "(timings share the 2 cores with whatever else ran). Every number below is in `summary.json` and the "
         "CSV files next to it and was produced by this command (models cached under "
         f"`{summary['cache']}`, keyed by scene file + settings).", "",
         "The live pipeline: the model `gsrmr-demo` renders, round 2 at the live camera's size, every MR image "
         "composed and scored by the server's slot core (`gsrmr_sim.offline_server`), the simulator's channel "
         "realisation. The offline solvers are given L_t (key slot at the true pose) and g_t, as the paper "
         "assumes; the composed images carry what the paper leaves out (the JPEG of image slots, the reported "
         "pose of key slots, the live fallback).", "",
         "Link (`config/link.yaml`, the paper's constants): tau 0.1 s, I 67.2 kbit, S 192 bit, B 1 MHz, "
         "sigma^2 -60 dBm, Rician K=1, rho0 -30 dB, alpha 3, server at (10, 0) m; g_t of round slot k drawn from "
         f"(channel seed {summary['channel_seed']}, k) at the robot's true position, as the simulated radio of "
         "`gsrmr-demo --channel-seed` draws it.", "", "## Data", "",
         "| scene | px | H | T | train px | GS iterations | train s | held-out PSNR dB at train px / at live px "
         "(model used) | Gaussians | mean L_t | median L_t | mean J_t (JPEG q) | pose error mean / max mm "
         "| mean distance m |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for sc, r in summary["scenes"].items():
        d = r["data"]
        L.append(f"| {sc} | {d['width']}x{d['height']} | {d['frames']} | {d['slots']} | {_f(d['train_width'])} | "
                 f"{d['train_iterations']} | {_f(d['train_wall_s'], '.0f')} | {_f(d['heldout_psnr_db'], '.2f')} / "
                 f"{_f(d.get('heldout_psnr_live_res_db'), '.2f')} | {d['gaussians']} | "
                 f"{d['gs_loss_mean']:.4f} | {d['gs_loss_median']:.4f} | {d['image_loss_mean']:.4f} "
                 f"(q{d['jpeg_quality']}) | {1e3 * d['pose_error']['position_mean_m']:.2f} / "
                 f"{1e3 * d['pose_error']['position_max_m']:.2f} | {d['distance_m_mean']:.2f} |")
    L += ["", "## Claims: paper vs ours", "", "| scene | claim (paper) | paper | ours | holds |",
          "|---|---|---|---|---|"]
    for sc, r in summary["scenes"].items():
        for k, c in r["claims"].items():
            L.append(f"| {sc} | {PAPER_CLAIMS[k]} | {c['paper']} | {_f(c['ours'], '.3g')} | {_f(c['holds'])} |")
    L += ["", "Why ours differ:", ""]
    for sc, r in summary["scenes"].items():
        L += _why(sc, r)
    L += ["", "What-if (`sensitivity_loss_scale_<scene>.png/.csv`): the saving factor RoboMR/APO if every L_t "
          "were scaled (a better GS model; same channel and schedulers):", "",
          "| scene | L_t scale | " + " | ".join(f"L_th {k}" for k in next(iter(summary["scenes"].values()))
                                                ["sensitivity_saving_factor"]["1"]) + " |",
          "|---|---|" + "---|" * len(next(iter(summary["scenes"].values()))["sensitivity_saving_factor"]["1"])]
    for sc, r in summary["scenes"].items():
        for scale, per in r["sensitivity_saving_factor"].items():
            L.append(f"| {sc} | {scale} | " + " | ".join(f"{v:.3g}x" for v in per.values()) + " |")
    main = summary["main_scene"]
    fa = summary["scenes"][main].get("fig4a")
    if fa:
        L += ["", f"## Fig. 4a: APO convergence ({main}, `fig4a_apo_convergence.png/.csv`)", "",
              f"{fa['iterations_run']} iterations; ||dx|| < 1e-3 first at n = {_f(fa['dx_below_1e-3_at'])} (paper: "
              f"after 30); phi < 0.01 first at n = {_f(fa['phi_below_1e-2_at'])} (paper: after 10); final ||dx|| "
              f"{_f(fa['final_dx_norm'], '.3g')}, phi {_f(fa['final_phi'], '.3g')}."]
    for sc, r in summary["scenes"].items():
        per = r["fig4b"]["per_threshold"]
        L += ["", f"## Fig. 4b: energy (J) vs L_th, {sc} (`fig4b_energy_{sc}.png/.csv`; * = infeasible)", "",
              "| L_th | " + " | ".join(FIG4B_METHODS) + " | saving RoboMR/APO | APO vs Search % | APO gap to exact % |",
              "|" + "---|" * (len(FIG4B_METHODS) + 4)]
        for k, v in per.items():
            L.append(f"| {k} | " + " | ".join(f"{v['energy_j'][m]:.3e}{'' if v['feasible'][m] else '*'}"
                                               for m in FIG4B_METHODS) +
                     f" | {v['saving_factor_apo']:.3g}x ({v['saving_db_apo']:.1f} dB) | "
                     f"{v['apo_below_search_pct']:.2f} | {v['apo_gap_to_exact_pct']:.3f} |")
        L += ["", f"## Table 1: composed MR images at APO's energy, {sc} (`table1_{sc}.csv`)", "",
              "Measured on the MR images the live slot core composes (image slot: the robot's JPEG; key slot: GS "
              "render at the reported pose; undelivered slot: the live fallback), against m_t, averaged over "
              "slots. MaxRate and Fairness get APO's energy, Exact its own (lower or equal); `apo_jpeg` (ours) "
              "is APO planned with each image slot's JPEG loss J_t, as the live planner does.", "",
              table1_markdown(r["table1"]), "",
              "Composed loss against the plan (the paper's model charges L_t for key slots and nothing for image "
              "slots):", "", loss_split_markdown(r["table1"])]
    if summary.get("fig5"):
        L += ["", f"## Fig. 5 ({main}): `fig5a_strip.png` (slots {summary['fig5']['slots']}), `fig5b_profile.png` "
              f"(APO uploads {summary['fig5']['apo_images']} images)"]
    tr = summary.get("tradeoffs", {})
    if tr:
        L += ["", "## Trade-offs (`tradeoff_*.png/.csv`)", "", "APO iterations N (L_th 0.03):", "",
              "| N | run | time s | gap to exact % |", "|---|---|---|---|"]
        for row in tr["scheduler"]["apo_n"]:
            L.append(f"| {row['apo_iterations']} | {row['iterations_run']} | {row['solve_time_s']:.3f} | "
                     f"{row['gap_to_exact_pct']:.3f} |")
        L += ["", "Every method (L_th 0.03): " + ", ".join(
            f"{m} {v['solve_time_s'] * 1000:.1f} ms / {v['gap_to_exact_pct']:.3g} %"
            for m, v in tr["scheduler"]["methods"].items()), "",
            "Renderer (one process; PSNR vs real r_t at record resolution):", "",
            "| axis | size | Gaussians | SH | ms | fps | PSNR vs real | PSNR vs full |",
            "|---|---|---|---|---|---|---|---|"]
        for row in tr["renderer"]["rows"]:
            L.append(f"| {row['axis']} | {row['width']}x{row['height']} | {row['gaussians']} | "
                     f"{row['sh_degree']} | {row['median_ms']:.1f} | {row['fps']:.1f} | {row['psnr_vs_real_db']:.2f} | "
                     f"{row['psnr_vs_full_db']:.2f} |")
        L += ["", "JPEG (composited MR loss vs m_t):", "", "| quality | mean kbit | MR loss | PSNR dB | fits I |",
              "|---|---|---|---|---|"]
        for row in tr["jpeg"]["rows"]:
            L.append(f"| {row['quality']} | {row['mean_bits'] / 1000:.1f} | {row['mean_loss']:.4f} | "
                     f"{row['mean_psnr_db']:.2f} | {_f(row['fits_image_bits'])} |")
        L += ["", "GS training: " + "; ".join(
            f"{sc}: {_f(v['final_heldout_psnr_db'], '.2f')} dB after {v['iterations']} iterations / "
            f"{_f(v['train_wall_s'], '.0f')} s (from {_f(v['initial_heldout_psnr_db'], '.2f')} dB)"
            for sc, v in tr["training"].items())]
    ns = summary.get("node_suite") or {}
    L += ["", "## Node suite runs (online, `gsrmr-demo` recordings)", ""]
    if ns:
        L += ["| run | slots | images | energy J | upload-all J | ratio | mean loss | PSNR dB |",
              "|---|---|---|---|---|---|---|---|"]
        for name, v in ns.items():
            L.append(f"| {name} | {_f(v['slots'])} | {_f(v['images_sent'])} | {_f(v['energy_j'])} | "
                     f"{_f(v['energy_upload_all_j'])} | {_f(v['energy_ratio_vs_upload_all'], '.3g')} | "
                     f"{_f(v['mean_loss'])} | {_f(v['psnr_db'], '.2f')} |")
    else:
        L.append("No `gsrmr-demo` report folder found (`--demo-reports`); the numbers above are offline only.")
    L += ["", "## Consistency checks", ""] + [f"* {k}: {_f(v)}" for k, v in summary["checks"].items()]
    L += ["", "## Files", ""] + [f"* `{f}`" for f in summary["files"]]
    (out / "summary.md").write_text("\n".join(L) + "\n")
