"""The paper's Section V on our data: Fig. 4a, Fig. 4b, Table 1 and Fig. 5a/5b (docs/experiments.md).

Every function takes a :class:`~gsrmr_sim.experiments.data.SceneData`, writes its CSV/PNG under ``out`` and
returns the numbers that go into ``summary.json``.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from pathlib import Path
from typing import Any

import numpy as np

from gsrmr_common.metrics import image_quality
from gsrmr_scheduler.problem import Problem, Schedule
from gsrmr_scheduler.solve import solve
from gsrmr_sim.experiments.composite import Compositor
from gsrmr_sim.experiments.data import SceneData
from gsrmr_sim.experiments.plots import plt, save_fig, write_csv

#: Fig. 4b order (the paper's baselines, then ours).
FIG4B_METHODS = ("robomr", "ranking", "rounding", "search", "exchange", "maxrate", "fairness", "robogs", "apo", "exact")
TABLE1_METHODS = ("fairness", "maxrate", "apo", "exact")
PAPER_LTH = (0.02, 0.025, 0.03, 0.035, 0.04)
TABLE1_LTH = (0.02, 0.025, 0.03, 0.035)
#: Ours beside Table 1: APO planned with each image slot's JPEG loss (:func:`jpeg_aware_problem`).
APO_JPEG = "apo_jpeg"


@dataclass(frozen=True)
class PaperConfig:
    """Knobs of the paper experiments."""

    thresholds: tuple[float, ...] = PAPER_LTH
    table_thresholds: tuple[float, ...] = TABLE1_LTH
    apo_iterations: int = 10  # N (paper: 10)
    convergence_iterations: int = 30  # Fig. 4a
    convergence_threshold: float = 0.03
    exact_time_limit_s: float = 60.0
    strip_slots: int = 6


def solve_all(data: SceneData, cfg: PaperConfig) -> dict[float, dict[str, Schedule]]:
    """Every Fig. 4b method at every L_th (MaxRate/Fairness get APO's energy as their budget)."""
    out: dict[float, dict[str, Schedule]] = {}
    for lth in sorted(set(cfg.thresholds) | set(cfg.table_thresholds)):
        p = data.problem(lth)
        res: dict[str, Schedule] = {}
        res["apo"] = solve(p, "apo", iterations=cfg.apo_iterations)
        for m in FIG4B_METHODS:
            if m == "apo":
                continue
            if m in ("maxrate", "fairness"):
                res[m] = solve(p, m, energy_budget_j=res["apo"].energy_j)
            elif m == "exact":
                res[m] = solve(p, m, time_limit_s=cfg.exact_time_limit_s)
            else:
                res[m] = solve(p, m)
        out[lth] = {m: res[m] for m in FIG4B_METHODS}
    return out


def fig4a(data: SceneData, cfg: PaperConfig, out: Path) -> dict[str, Any]:
    """APO convergence: ‖Δx‖ and φ(x) = (1/T)Σx(1−x) against the iteration n."""
    p = data.problem(cfg.convergence_threshold)
    s = solve(p, "apo", iterations=cfg.convergence_iterations, tol=1e-12)
    hist = s.history or []
    rows = [{"iteration": h["iteration"], "dx_norm": h["dx_norm"], "phi": h["phi"], "objective_j": h["objective_j"]}
            for h in hist]
    write_csv(out / "fig4a_apo_convergence.csv", rows)
    fig, ax = plt.subplots(figsize=(5, 3.4))
    if rows:
        n = [r["iteration"] for r in rows]
        ax.semilogy(n, [max(r["dx_norm"], 1e-16) for r in rows], "o-", label=r"$\|\Delta x\|$")
        ax.semilogy(n, [max(r["phi"], 1e-16) for r in rows], "s-", label=r"$\phi(x)$")
    ax.axhline(1e-3, color="grey", lw=0.8, ls="--")
    ax.axhline(1e-2, color="grey", lw=0.8, ls=":")
    ax.set_xlabel("iteration n")
    ax.set_title(f"APO convergence, {data.settings.scene}, L_th = {cfg.convergence_threshold}")
    ax.legend()
    save_fig(fig, out / "fig4a_apo_convergence.png")

    def first_below(key: str, level: float) -> int | None:
        return next((r["iteration"] for r in rows if r[key] < level), None)

    return {"iterations_run": len(rows), "dx_below_1e-3_at": first_below("dx_norm", 1e-3),
            "phi_below_1e-2_at": first_below("phi", 1e-2),
            "final_dx_norm": rows[-1]["dx_norm"] if rows else None, "final_phi": rows[-1]["phi"] if rows else None}


def fig4b(data: SceneData, sols: dict[float, dict[str, Schedule]], cfg: PaperConfig, out: Path) -> dict[str, Any]:
    """Energy against L_th for every method (log scale) and the GS energy-saving factor."""
    rows = []
    for lth in cfg.thresholds:
        for m, s in sols[lth].items():
            rows.append({"scene": data.settings.scene, "loss_threshold": lth, "method": m, "energy_j": s.energy_j,
                         "mean_loss_predicted": s.mean_loss, "feasible": s.feasible,
                         "images": int(sum(d == "image" for d in s.delivered)),
                         "keys": int(sum(d == "key" for d in s.delivered)),
                         "undelivered": int(sum(d == "none" for d in s.delivered)),
                         "solve_time_s": s.solve_time_s,
                         "optimality_gap": "" if s.optimality_gap is None else s.optimality_gap})
    write_csv(out / f"fig4b_energy_{data.settings.scene}.csv", rows)
    fig, ax = plt.subplots(figsize=(6, 4))
    markers = dict(zip(FIG4B_METHODS, "o^v<>*sdPX", strict=True))
    for m in FIG4B_METHODS:
        xs = list(cfg.thresholds)
        es = [sols[lth][m].energy_j for lth in xs]
        feas = [sols[lth][m].feasible for lth in xs]
        ax.semilogy(xs, es, "-", marker=markers[m], label=m, alpha=0.85)
        bad = [(x, e) for x, e, f in zip(xs, es, feas, strict=True) if not f]
        if bad:
            ax.plot(*zip(*bad, strict=True), "x", color="red", ms=10, mew=2)
    for lth in cfg.thresholds:  # GS energy-saving factor RoboMR / APO above each APO point
        e_apo = sols[lth]["apo"].energy_j
        ax.annotate(f"{sols[lth]['robomr'].energy_j / e_apo:.3g}x", (lth, e_apo), textcoords="offset points",
                    xytext=(0, 8), ha="center", fontsize=7, color="k")
    ax.set_xlabel(r"$L_{th}$")
    ax.set_ylabel("uplink energy over the round (J); labels: RoboMR/APO")
    ax.set_title(f"Energy vs loss threshold, {data.settings.scene} (red x: infeasible)")
    ax.legend(ncol=3, fontsize=7)
    save_fig(fig, out / f"fig4b_energy_{data.settings.scene}.png")
    per = {}
    for lth in cfg.thresholds:
        s = sols[lth]
        e = {m: s[m].energy_j for m in FIG4B_METHODS}
        feasible_others = {m: e[m] for m in FIG4B_METHODS if m not in ("exact",) and s[m].feasible}
        second = min((m for m in feasible_others if m not in ("apo", "maxrate", "fairness")),
                     key=lambda m: e[m], default=None)
        per[f"{lth:g}"] = {
            "energy_j": e, "feasible": {m: bool(s[m].feasible) for m in FIG4B_METHODS},
            "saving_factor_apo": e["robomr"] / e["apo"], "saving_factor_exact": e["robomr"] / e["exact"],
            "saving_db_apo": 10 * math.log10(e["robomr"] / e["apo"]),
            "apo_below_search_pct": 100.0 * (e["search"] - e["apo"]) / e["search"],
            "apo_gap_to_exact_pct": 100.0 * (e["apo"] - e["exact"]) / e["exact"],
            "exact_certified_gap": s["exact"].optimality_gap,
            "best_heuristic_besides_apo": second,
            "apo_images": int(sum(d == "image" for d in s["apo"].delivered)),
        }
    return {"per_threshold": per}


def jpeg_aware_problem(data: SceneData, loss_threshold: float) -> Problem | None:
    """Ours, not the paper's: P_GS with image slots charged their JPEG loss J_t, as the live planner does.
    Σ_t [(1−x_t)·L_t + x_t·J_t] ≤ T·L_th  ⇔  Σ_t (1−x_t)·(L_t − J_t) ≤ T·L_th − Σ_t J_t; slots with
    L_t < J_t get L_t − J_t clipped at 0 (conservative). None when even uploading every image exceeds L_th."""
    j = np.nan_to_num(data.image_loss, nan=0.0)
    cap = loss_threshold - float(j.mean())
    if cap <= 0:
        return None
    return Problem(channel_gain=data.channel_gain, gs_loss=np.maximum(data.gs_loss - j, 0.0), loss_threshold=cap,
                   slot_s=data.record.slot_s, bandwidth_hz=data.link.bandwidth_hz, noise_w=data.link.noise_w)


def table1(data: SceneData, sols: dict[float, dict[str, Schedule]], cfg: PaperConfig, comp: Compositor,
           out: Path) -> dict[str, Any]:
    """Loss/PSNR/SSIM of the MR images the live slot core composes under each method's schedule, and the
    split of each measured loss against the plan (:class:`~gsrmr_sim.experiments.composite.CompositeResult`)."""
    rows, per = [], {}
    for lth in cfg.table_thresholds:
        per[f"{lth:g}"] = {}
        scheds = {m: sols[lth][m] for m in TABLE1_METHODS}
        pj = jpeg_aware_problem(data, lth)
        if pj is not None:
            scheds[APO_JPEG] = solve(pj, "apo", iterations=cfg.apo_iterations)
        for m, s in scheds.items():
            r = comp.evaluate(s.delivered)
            per[f"{lth:g}"][m] = {"loss": r.mean_loss, "psnr_db": r.pooled_psnr_db,
                                  "psnr_slot_mean_db": r.mean_psnr_db, "ssim": r.mean_ssim,
                                  "energy_j": s.energy_j, "predicted_loss": s.mean_loss,
                                  "plan_loss": r.plan_loss, "jpeg_loss": r.jpeg_loss, "pose_loss": r.pose_loss,
                                  "fallback_loss": r.fallback_loss, "composited_minus_plan": r.mean_loss - r.plan_loss,
                                  "parts_sum": r.parts_sum, "images": int(sum(d == "image" for d in s.delivered)),
                                  "undelivered": int(sum(d == "none" for d in s.delivered))}
            rows.append({"scene": data.settings.scene, "loss_threshold": lth, "method": m, **per[f"{lth:g}"][m]})
        d = per[f"{lth:g}"]
        d["apo_psnr_gain_db"] = d["apo"]["psnr_db"] - max(d["maxrate"]["psnr_db"], d["fairness"]["psnr_db"])
        d["apo_psnr_gain_slot_mean_db"] = d["apo"]["psnr_slot_mean_db"] - max(d["maxrate"]["psnr_slot_mean_db"],
                                                                              d["fairness"]["psnr_slot_mean_db"])
    write_csv(out / f"table1_{data.settings.scene}.csv", rows)
    return {"per_threshold": per}


def table1_markdown(t1: dict[str, Any]) -> str:
    """Table 1 in the paper's layout (Loss | PSNR | SSIM, Fairness/MaxRate/APO/Exact, then ours: APO planned
    with the JPEG loss; PSNR pooled over slots), every value measured on the live core's composites."""
    ms = TABLE1_METHODS + ((APO_JPEG,) if any(APO_JPEG in d for d in t1["per_threshold"].values()) else ())
    head = "| L_th | " + " | ".join(f"loss {m}" for m in ms) + " | " + " | ".join(f"PSNR {m}" for m in ms) + \
        " | " + " | ".join(f"SSIM {m}" for m in ms) + " |"
    lines = [head, "|" + "---|" * (1 + 3 * len(ms))]
    for lth, d in t1["per_threshold"].items():
        cell = {m: d.get(m) for m in ms}
        lines.append(f"| {lth} | " + " | ".join(f"{c['loss']:.4f}" if c else "–" for c in cell.values()) + " | " +
                     " | ".join(f"{c['psnr_db']:.2f}" if c else "–" for c in cell.values()) + " | " +
                     " | ".join(f"{c['ssim']:.3f}" if c else "–" for c in cell.values()) + " |")
    return "\n".join(lines)


def loss_split_markdown(t1: dict[str, Any], methods: tuple[str, ...] = ("apo", "exact", APO_JPEG)) -> str:
    """Measured loss against the plan: plan (Σ L_t of key/none slots) + JPEG + pose + fallback parts."""
    lines = ["| L_th | method | images | plan loss | + JPEG (image slots) | + pose (key slots) | + fallback | "
             "= composed loss |", "|---|---|---|---|---|---|---|---|"]
    for lth, d in t1["per_threshold"].items():
        for m in methods:
            if m in d:
                r = d[m]
                lines.append(f"| {lth} | {m} | {r['images']} | {r['plan_loss']:.4f} | {r['jpeg_loss']:+.4f} | "
                             f"{r['pose_loss']:+.5f} | {r['fallback_loss']:+.4f} | {r['loss']:.4f} |")
    return "\n".join(lines)


def _strip_slots(loss: np.ndarray, n: int) -> list[int]:
    """n slots: the worst GS slots (spread ≥ T/(2n) apart) plus evenly spaced others."""
    t_n = loss.size
    sep = max(1, t_n // (2 * n))
    picked: list[int] = []
    for t in np.argsort(-loss):
        if len(picked) >= n // 2:
            break
        if all(abs(int(t) - p) >= sep for p in picked):
            picked.append(int(t))
    for t in np.linspace(0, t_n - 1, n + 2)[1:-1].astype(int):
        if len(picked) >= n:
            break
        if all(abs(int(t) - p) >= sep for p in picked):
            picked.append(int(t))
    return sorted(picked)[:n]


def fig5(data: SceneData, sols: dict[float, dict[str, Schedule]], cfg: PaperConfig, comp: Compositor,
         out: Path) -> dict[str, Any]:
    """Fig. 5a (truth / RoboGS / APO strip + route map) and Fig. 5b (x_t, p_t of APO) at L_th = 0.03."""
    lth = cfg.convergence_threshold
    apo, robogs = sols[lth]["apo"], sols[lth]["robogs"]
    slots = _strip_slots(data.gs_loss, cfg.strip_slots)
    n = len(slots)
    fig = plt.figure(figsize=(2.2 * n + 3.2, 6.2))
    gsp = fig.add_gridspec(3, n + 1, width_ratios=[1.6] + [1] * n)
    axm = fig.add_subplot(gsp[:, 0])
    poses = data.record.poses
    axm.plot(poses[:, 0], poses[:, 1], "b-", lw=1)
    img = np.array([d == "image" for d in apo.delivered])
    axm.plot(poses[img, 0], poses[img, 1], "gs", ms=3, label="APO image slots")
    axm.plot(poses[[0, -1], 0], poses[[0, -1], 1], "rs", ms=7, label="start/end")
    for i, t in enumerate(slots):
        axm.annotate("ABCDEFGHIJ"[i], poses[t, :2], color="k", fontsize=9, weight="bold")
    axm.set_aspect("equal", adjustable="datalim")
    axm.set_title("route (map frame, m)")
    axm.legend(fontsize=6, loc="lower left")
    rows = []
    for j, t in enumerate(slots):
        truth, gs_img = comp.images(robogs.delivered, t)
        _, apo_img = comp.images(apo.delivered, t)
        q_gs, q_apo = image_quality(truth, gs_img), image_quality(truth, apo_img)
        rows.append({"label": "ABCDEFGHIJ"[j], "slot": t, "gs_loss": q_gs["loss"], "gs_psnr_db": q_gs["psnr_db"],
                     "apo_delivered": apo.delivered[t], "apo_loss": q_apo["loss"], "apo_psnr_db": q_apo["psnr_db"]})
        for i, (im, name) in enumerate(((truth, "RoboMR (truth)"), (gs_img, f"RoboGS L={q_gs['loss']:.3f}"),
                                        (apo_img, f"APO ({apo.delivered[t]}) L={q_apo['loss']:.3f}"))):
            ax = fig.add_subplot(gsp[i, j + 1])
            ax.imshow(np.clip(im, 0, 1))
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(f"{'ABCDEFGHIJ'[j]} t={t}: {name}" if i == 0 else name, fontsize=7)
    save_fig(fig, out / "fig5a_strip.png")
    write_csv(out / "fig5a_strip.csv", rows)
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(6, 4), sharex=True)
    tt = np.arange(apo.x.size)
    a1.step(tt, apo.x, where="mid")
    a1.set_ylabel("x_t (1 = image)")
    a1b = a1.twinx()
    a1b.plot(tt, data.gs_loss, "r-", lw=0.7, alpha=0.6)
    a1b.set_ylabel("L_t", color="r")
    a2.semilogy(tt, np.maximum(apo.power_w, 1e-12), "k-", lw=0.8)
    a2.set_ylabel("p_t (W)")
    a2.set_xlabel("slot t")
    a1.set_title(f"APO content switching and power, L_th = {lth}")
    save_fig(fig, out / "fig5b_profile.png")
    write_csv(out / "fig5b_profile.csv",
              [{"slot": int(t), "x": int(apo.x[t]), "power_w": float(apo.power_w[t]),
                "gs_loss": float(data.gs_loss[t]), "channel_gain": float(data.channel_gain[t])} for t in tt])
    return {"slots": slots, "apo_images": int(img.sum())}


def sensitivity(data: SceneData, cfg: PaperConfig, out: Path, scales: tuple[float, ...] = (1.0, 0.5, 0.25, 0.1)
                ) -> dict[str, Any]:
    """What-if: the GS energy-saving factor if every L_t were ``scale``× ours (a better GS model).

    Same channel, same schedulers (APO with N = ``apo_iterations``, and exact); only ``gs_loss`` is
    scaled. Answers "how good must the GS model be for the paper's 10×/100× savings" on our route.
    """
    rows = []
    for sc in scales:
        for lth in cfg.thresholds:
            p = Problem(channel_gain=data.channel_gain, gs_loss=data.gs_loss * sc, loss_threshold=lth,
                        slot_s=data.record.slot_s, bandwidth_hz=data.link.bandwidth_hz, noise_w=data.link.noise_w)
            e_mr = solve(p, "robomr").energy_j
            apo = solve(p, "apo", iterations=cfg.apo_iterations)
            ex = solve(p, "exact", time_limit_s=cfg.exact_time_limit_s)
            rows.append({"scene": data.settings.scene, "loss_scale": sc, "loss_threshold": lth,
                         "mean_gs_loss": float(np.mean(data.gs_loss * sc)), "saving_factor_apo": e_mr / apo.energy_j,
                         "saving_factor_exact": e_mr / ex.energy_j, "apo_images": int(apo.x.sum())})
    write_csv(out / f"sensitivity_loss_scale_{data.settings.scene}.csv", rows)
    fig, ax = plt.subplots(figsize=(6, 3.8))
    for sc in scales:
        rr = [r for r in rows if r["loss_scale"] == sc]
        ax.semilogy([r["loss_threshold"] for r in rr], [r["saving_factor_apo"] for r in rr], "o-",
                    label=f"L_t x {sc:g} (mean {rr[0]['mean_gs_loss']:.3f})")
    ax.axhline(10, color="grey", ls="--", lw=0.8)
    ax.axhline(100, color="grey", ls=":", lw=0.8)
    ax.set_xlabel(r"$L_{th}$")
    ax.set_ylabel("GS energy-saving factor (RoboMR / APO)")
    ax.set_title(f"What-if: a better GS model, {data.settings.scene}")
    ax.legend(fontsize=7)
    save_fig(fig, out / f"sensitivity_loss_scale_{data.settings.scene}.png")
    return {f"{sc:g}": {f"{r['loss_threshold']:g}": r["saving_factor_apo"] for r in rows if r["loss_scale"] == sc}
            for sc in scales}
