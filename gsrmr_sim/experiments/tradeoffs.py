"""Speed/accuracy trade-offs, measured on this machine: scheduler, renderer, JPEG quality and GS training
(docs/experiments.md, "What is measured", Trade-offs).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
import time
from typing import Any

import cv2
import numpy as np

from gsrmr_common.camera import Camera
from gsrmr_common.jpeg import decode_jpeg, encode_jpeg
from gsrmr_common.metrics import image_quality, psnr
from gsrmr_scheduler.problem import Problem, Schedule
from gsrmr_scheduler.solve import solve
from gsrmr_server.mr.blend import mr_image
from gsrmr_sim.experiments.data import SceneData, channel_gains
from gsrmr_sim.experiments.plots import plt, save_fig, write_csv
from gsrmr_splat.render import render


@dataclass(frozen=True)
class TradeoffConfig:
    """Sweep values of the trade-off measurements."""

    loss_threshold: float = 0.03
    apo_ns: tuple[int, ...] = (1, 2, 3, 5, 10, 20, 30)
    horizons: tuple[int, ...] = (72, 144, 288, 576)
    horizon_methods: tuple[str, ...] = ("ranking", "rounding", "search", "exchange", "apo", "exact")
    render_slots: int = 6
    render_repeats: int = 5
    scales: tuple[float, ...] = (0.5, 0.75, 1.0, 1.5)
    fractions: tuple[float, ...] = (0.1, 0.25, 0.5, 1.0)
    jpeg_qualities: tuple[int, ...] = (5, 10, 20, 35, 50, 70, 85, 95)
    jpeg_slots: int = 24
    exact_time_limit_s: float = 60.0


def _gap_pct(e: float, e_ref: float) -> float:
    return 100.0 * (e - e_ref) / e_ref


def scheduler_tradeoff(data: SceneData, sols_at_lth: dict[str, Schedule], cfg: TradeoffConfig,
                       out: Path) -> dict[str, Any]:
    """Solve time vs energy gap to ``exact``: APO's N, every method, and the horizon T."""
    p = data.problem(cfg.loss_threshold)
    ex = sols_at_lth["exact"]
    rows_n = []
    for n in cfg.apo_ns:
        s = solve(p, "apo", iterations=n, tol=1e-12)
        rows_n.append({"apo_iterations": n, "iterations_run": s.iterations, "solve_time_s": s.solve_time_s,
                       "energy_j": s.energy_j, "gap_to_exact_pct": _gap_pct(s.energy_j, ex.energy_j),
                       "feasible": s.feasible})
    write_csv(out / "tradeoff_scheduler_apo_n.csv", rows_n)
    rows_m = [{"method": m, "solve_time_s": s.solve_time_s, "energy_j": s.energy_j, "feasible": s.feasible,
               "gap_to_exact_pct": _gap_pct(s.energy_j, ex.energy_j)} for m, s in sols_at_lth.items()]
    write_csv(out / "tradeoff_scheduler_methods.csv", rows_m)
    rows_t = []
    xy = data.record.poses[:, :2]
    for t_n in cfg.horizons:
        reps = int(np.ceil(t_n / len(xy)))
        loss = np.tile(data.gs_loss, reps)[:t_n]
        # laps repeated: round slot k at the k-th pose of the repeated route, its own fading draw (seed, k)
        _, g = channel_gains(data.link, np.tile(xy, (reps, 1))[:t_n])
        pt = Problem(channel_gain=g, gs_loss=loss, loss_threshold=cfg.loss_threshold, slot_s=data.record.slot_s,
                     bandwidth_hz=data.link.bandwidth_hz, noise_w=data.link.noise_w)
        res = {}
        for m in cfg.horizon_methods:
            opts = {"time_limit_s": cfg.exact_time_limit_s} if m == "exact" else {}
            res[m] = solve(pt, m, **opts)
        for m, s in res.items():
            rows_t.append({"slots": t_n, "method": m, "solve_time_s": s.solve_time_s, "energy_j": s.energy_j,
                           "gap_to_exact_pct": _gap_pct(s.energy_j, res["exact"].energy_j), "feasible": s.feasible})
    write_csv(out / "tradeoff_scheduler_horizon.csv", rows_t)
    fig, axs = plt.subplots(1, 3, figsize=(14, 3.8))
    a = axs[0]
    a.plot([r["solve_time_s"] for r in rows_n], [r["gap_to_exact_pct"] for r in rows_n], "o-")
    for r in rows_n:
        a.annotate(f"N={r['apo_iterations']}", (r["solve_time_s"], r["gap_to_exact_pct"]), fontsize=7)
    a.set_xlabel("APO solve time (s)")
    a.set_ylabel("energy gap to exact (%)")
    a.set_title(f"APO iterations N (L_th={cfg.loss_threshold})")
    a = axs[1]
    for r in rows_m:
        a.plot(max(r["solve_time_s"], 1e-5), r["gap_to_exact_pct"], "o" if r["feasible"] else "x")
        a.annotate(r["method"], (max(r["solve_time_s"], 1e-5), r["gap_to_exact_pct"]), fontsize=7)
    a.set_xscale("log")
    a.set_yscale("symlog", linthresh=1.0)
    a.set_xlabel("solve time (s)")
    a.set_ylabel("energy gap to exact (%)")
    a.set_title("every method (x: infeasible)")
    a = axs[2]
    for m in cfg.horizon_methods:
        rr = [r for r in rows_t if r["method"] == m]
        a.loglog([r["slots"] for r in rr], [max(r["solve_time_s"], 1e-5) for r in rr], "o-", label=m)
    a.set_xlabel("horizon T (slots)")
    a.set_ylabel("solve time (s)")
    a.legend(fontsize=7)
    a.set_title("scaling with T")
    save_fig(fig, out / "tradeoff_scheduler.png")
    return {"apo_n": rows_n, "methods": {r["method"]: {"solve_time_s": r["solve_time_s"],
                                                      "gap_to_exact_pct": r["gap_to_exact_pct"]} for r in rows_m},
            "horizon": rows_t}


def _camera_scaled(cam: Camera, scale: float) -> Camera:
    w = max(8, round(cam.width * scale))
    h = max(8, round(cam.height * scale))
    return Camera(cam.intrinsics.scaled(w, h), cam.world_to_camera)


def _resize(img: np.ndarray, width: int, height: int) -> np.ndarray:
    if img.shape[1] == width and img.shape[0] == height:
        return img
    interp = cv2.INTER_AREA if img.shape[1] > width else cv2.INTER_LINEAR
    return cv2.resize(np.ascontiguousarray(img, np.float32), (width, height), interpolation=interp)


def renderer_tradeoff(data: SceneData, cfg: TradeoffConfig, out: Path) -> dict[str, Any]:
    """fps vs PSNR over K round-2 slots: resolution scale, opacity-ranked Gaussian subsets, SH degree.

    PSNR is taken at the record resolution (renders resized back) against the real round-2 image r_t
    (``psnr_vs_real_db``) and against the full-quality render (``psnr_vs_full_db``).
    """
    model, bg = data.model, data.background
    slots = np.linspace(0, len(data.record) - 1, cfg.render_slots).astype(int)
    recs = [data.record[int(t)] for t in slots]
    order = np.argsort(-model.opacities)
    configs: list[tuple[str, float, float, int]] = []
    configs += [("resolution", s, 1.0, model.sh_degree) for s in cfg.scales]
    configs += [("gaussians", 1.0, f, model.sh_degree) for f in cfg.fractions]
    configs += [("sh_degree", 1.0, 1.0, d) for d in range(model.sh_degree + 1)]
    full = {int(r.t): render(model, r.camera, bg).rgb for r in recs}
    rows = []
    for axis, scale, frac, deg in configs:
        sub = model if frac >= 1.0 else model.subset(np.sort(order[: max(1, int(round(frac * model.num_gaussians)))]))
        times, p_real, p_full = [], [], []
        for r in recs:
            cam = _camera_scaled(r.camera, scale)
            render(sub, cam, bg, sh_degree=deg)  # warm-up (numba, caches)
            ts = []
            for _ in range(cfg.render_repeats):
                t0 = time.perf_counter()
                img = render(sub, cam, bg, sh_degree=deg).rgb
                ts.append(time.perf_counter() - t0)
            times.append(float(np.median(ts)))
            img = _resize(img, r.camera.width, r.camera.height)
            p_real.append(psnr(img, r.image))
            p_full.append(psnr(img, full[int(r.t)]))
        ms = 1000.0 * float(np.median(times))
        rows.append({"axis": axis, "scale": scale, "gaussian_fraction": frac, "gaussians": sub.num_gaussians,
                     "sh_degree": deg, "width": _camera_scaled(recs[0].camera, scale).width,
                     "height": _camera_scaled(recs[0].camera, scale).height, "median_ms": ms, "fps": 1000.0 / ms,
                     "psnr_vs_real_db": float(np.mean(p_real)), "psnr_vs_full_db": float(np.mean(p_full))})
    write_csv(out / "tradeoff_renderer.csv", rows)
    fig, ax = plt.subplots(figsize=(6, 4))
    for axis, mk in (("resolution", "o-"), ("gaussians", "s-"), ("sh_degree", "^-")):
        rr = [r for r in rows if r["axis"] == axis]
        ax.plot([r["fps"] for r in rr], [r["psnr_vs_real_db"] for r in rr], mk, label=axis)
        for r in rr:
            lab = {"resolution": f"{r['width']}x{r['height']}", "gaussians": f"{r['gaussians']}",
                   "sh_degree": f"deg {r['sh_degree']}"}[axis]
            ax.annotate(lab, (r["fps"], r["psnr_vs_real_db"]), fontsize=6)
    ax.set_xlabel("render rate (frames/s, one process)")
    ax.set_ylabel("PSNR vs real r_t (dB)")
    ax.set_title(f"GS renderer trade-offs, {data.settings.scene}")
    ax.legend(fontsize=7)
    save_fig(fig, out / "tradeoff_renderer.png")
    return {"rows": rows}


def jpeg_tradeoff(data: SceneData, cfg: TradeoffConfig, image_bits: float, out: Path) -> dict[str, Any]:
    """JPEG quality vs bits per image and MR loss of the composited image (decoded r̂_t in d_t)."""
    slots = np.linspace(0, len(data.record) - 1, cfg.jpeg_slots).astype(int)
    recs = [data.record[int(t)] for t in slots]
    rows = []
    for q in cfg.jpeg_qualities:
        bits, loss, ps = [], [], []
        for r in recs:
            blob = encode_jpeg(r.image, int(q))
            dec = decode_jpeg(blob).astype(np.float32) / 255.0
            truth = mr_image(r.image, r.virtual, r.mask)
            got = mr_image(dec, r.virtual, r.mask)
            m = image_quality(truth, got)
            bits.append(8 * len(blob))
            loss.append(m["loss"])
            ps.append(m["psnr_db"])
        rows.append({"quality": q, "mean_bits": float(np.mean(bits)), "max_bits": float(np.max(bits)),
                     "mean_loss": float(np.mean(loss)), "mean_psnr_db": float(np.mean(ps)),
                     "fits_image_bits": bool(np.max(bits) <= image_bits)})
    write_csv(out / "tradeoff_jpeg.csv", rows)
    fig, a1 = plt.subplots(figsize=(6, 3.8))
    a1.plot([r["quality"] for r in rows], [r["mean_bits"] / 1000 for r in rows], "o-b")
    a1.axhline(image_bits / 1000, color="b", ls="--", lw=0.8)
    a1.set_xlabel("JPEG quality")
    a1.set_ylabel("kbit per image (dashed: paper I)", color="b")
    a2 = a1.twinx()
    a2.plot([r["quality"] for r in rows], [r["mean_loss"] for r in rows], "s-r")
    a2.set_ylabel("MR loss of the composited image", color="r")
    w, h = recs[0].camera.width, recs[0].camera.height
    a1.set_title(f"JPEG at {w}x{h}, {data.settings.scene}")
    save_fig(fig, out / "tradeoff_jpeg.png")
    fit = [r for r in rows if r["fits_image_bits"]]
    return {"rows": rows, "best_quality_within_image_bits": max((r["quality"] for r in fit), default=None),
            "loss_at_that_quality": max(fit, key=lambda r: r["quality"])["mean_loss"] if fit else None}


def training_tradeoff(datas: list[SceneData], out: Path) -> dict[str, Any]:
    """Held-out PSNR against training wall time (Trainer history stored when the model was built)."""
    rows, res = [], {}
    fig, ax = plt.subplots(figsize=(6, 3.8))
    for d in datas:
        hist = d.train.get("history", [])
        for h in hist:
            rows.append({"scene": d.settings.scene, **h})
        ax.plot([h["elapsed_s"] for h in hist], [h["heldout_psnr_db"] for h in hist], "o-", label=d.settings.scene)
        res[d.settings.scene] = {"final_heldout_psnr_db": hist[-1]["heldout_psnr_db"] if hist else None,
                                 "iterations": hist[-1]["iteration"] if hist else None,
                                 "train_wall_s": d.train.get("wall_s"), "gaussians": d.model.num_gaussians,
                                 "initial_heldout_psnr_db": d.train.get("initial_heldout_psnr_db")}
    ax.set_xlabel("training wall time (s)")
    ax.set_ylabel("held-out PSNR (dB)")
    ax.set_title("GS training time vs quality (round-1 held-out views)")
    ax.legend()
    save_fig(fig, out / "tradeoff_training.png")
    write_csv(out / "tradeoff_training.csv", rows)
    return res
