"""The experiments' channel before and after it became the simulator's realisation (one link model).

Before (until 2026-11-24): ``ChannelModel(seed).gains(d_t)`` — one random stream over the round, d_t the 3-D
distance from the robot (a_t, b_t, 0) to the scene's server (10, 0, 1) m, minimum 1e-3 m. After: the simulated
radio's rule, ``LinkBudget.gain(k, (a_t, b_t))`` — round slot k's fading drawn from (seed, k), the planar
distance to ``config/link.yaml``'s server (10, 0) m, minimum 1 m. Same statistics (ρ0 −30 dB, α 3, Rician K 1),
other draws. For seeds 1…N this prints the exact optimum's energy, RoboMR's and their ratio at each L_th on the
sandbox's experiment data (L_t of the live pipeline, the cached live model), and the median over seeds.

    .venv/bin/python bench/perf/channel_models.py [--seeds 10] [--scene sandbox]
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
import sys

import numpy as np

from gsrmr_common.channel import ChannelModel
from gsrmr_scheduler.problem import Problem
from gsrmr_scheduler.solve import solve
from gsrmr_sim.experiments.data import DataSettings, build_scene_data, channel_gains
from gsrmr_sim.sim_stack import config_dir, link_budget

REPO = Path(__file__).resolve().parents[2]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--scene", default="sandbox")
    ap.add_argument("--cache", default=str(REPO / ".cache" / "gsrmr"))
    a = ap.parse_args()
    d = build_scene_data(DataSettings(scene=a.scene), a.cache, log=lambda m: print(f"# {m}"))
    poses = d.record.poses
    server3 = np.array([10.0, 0.0, 1.0])
    robot3 = np.c_[poses[:, :2], np.zeros(len(poses))]
    d3 = np.maximum(np.linalg.norm(robot3 - server3, axis=1), 1e-3)
    lths = (0.02, 0.03, 0.04)
    print(f"# {a.scene}: T = {len(poses)}, mean L_t {d.gs_loss.mean():.4f}; load average "
          f"{', '.join(f'{v:.2f}' for v in os.getloadavg())}")
    print("| channel | seed | " + " | ".join(f"exact J @ {t} | RoboMR/exact @ {t}" for t in lths) + " |")
    print("|---|---|" + "---|---|" * len(lths))
    ratios: dict[str, list[list[float]]] = {"before": [], "after": []}
    for seed in range(1, a.seeds + 1):
        old = ChannelModel(seed=seed).gains(d3)
        _, new = channel_gains(link_budget(str(config_dir() / "link.yaml"), seed), poses[:, :2])
        for name, g in (("before", old), ("after", new)):
            row = []
            cells = []
            for t in lths:
                p = Problem(channel_gain=g, gs_loss=d.gs_loss, loss_threshold=t, slot_s=d.record.slot_s)
                ex, mr = solve(p, "exact", time_limit_s=30.0), solve(p, "robomr")
                row.append(mr.energy_j / ex.energy_j)
                cells.append(f"{ex.energy_j:.3e} | {mr.energy_j / ex.energy_j:.1f}x")
            ratios[name].append(row)
            print(f"| {name} | {seed} | " + " | ".join(cells) + " |")
    for name, rows in ratios.items():
        arr = np.array(rows)
        print(f"| {name} | median (worst) | " + " | ".join(
            f" | {np.median(arr[:, i]):.1f}x ({arr[:, i].min():.1f}x)" for i in range(len(lths))) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
