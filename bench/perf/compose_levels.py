"""The server's composition levels (``gsrmr_server.compose_levels``): what each costs in time and in MR loss.

Records the sandbox's round 2 (``--slots`` slots of its route, the simulator's true frames), then composes each slot
as a key slot at every level — the GS render at full, half and a quarter of 320×240, enlarged — with the demo's
cached compacted model on one render thread, as the server does. Per level: the compose time (median of each run's
median, and the worst run's), the MR loss of the published image against the true MR image (mean and p95 over the
slots, scored as the simulation's scorer does) and the extra loss against the full level's image. The extra loss is
what a degraded slot costs the round's budget; the time is what it saves. Usage::

    .venv/bin/python bench/perf/compose_levels.py [--slots 96] [--runs 3]
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
import tempfile
import time

import numpy as np

from gsrmr_common.metrics import mr_loss
from gsrmr_common.wire import MRSlotInfo, PoseKey
from gsrmr_server.compose import to_u8
from gsrmr_server.compose_levels import LEVEL_NAMES, RENDER_SCALES
from gsrmr_server.scoring import SlotScorer
from gsrmr_server.slot_core import build_composer
from gsrmr_server.uplink import SlotUploads
from gsrmr_sim.machine_probe import machine_line
from gsrmr_sim.shared_data import garden_model
from gsrmr_sim.world import Round2Record, load_scene, record_round2
from gsrmr_splat.model import GaussianModel

REPO = Path(__file__).resolve().parents[2]


def _default_model() -> tuple[str, GaussianModel]:
    """The demo's cached compacted sandbox model, or (none cached: a fresh machine) the garden test model."""
    found = sorted((REPO / ".cache" / "gsrmr").glob("sandbox-*/model-compact-*.ply"))
    if found:
        return found[0].name, GaussianModel.load_ply(found[0])
    return "no cached sandbox model (`make demo` builds one): the garden test model", garden_model()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--slots", type=int, default=96, help="slots of the route composed per level and run")
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args(argv)
    name, model = _default_model()
    scene = load_scene("sandbox")
    with tempfile.TemporaryDirectory() as tmp:
        record = Round2Record(record_round2(scene, tmp, slots=args.slots, seed=0))
        truths = [to_u8(record[t].image) for t in range(len(record))]
    kw = {"mr_content": scene.mr_content, "mount": record.mount, "background_rgb": tuple(scene.background)}
    composer = build_composer(model, record.intrinsics, render_threads=1, **kw)
    scorer = SlotScorer(build_composer(model, record.intrinsics, render_threads=1, **kw))
    k = record.intrinsics
    print(f"# bench/perf/compose_levels.py: {name} ({model.num_gaussians} Gaussians), {k.width}×{k.height}, sandbox "
          f"round 2, {len(record)} key slots × {args.runs} runs, render on 1 thread (before: {machine_line()})")
    times: dict[int, list[float]] = {level: [] for level in range(len(LEVEL_NAMES))}
    losses: dict[int, list[float]] = {level: [] for level in times}
    extra: dict[int, list[float]] = {level: [] for level in times}
    for run in range(args.runs):  # interleaved level by level, so a change in the machine's speed hits every level
        per_level: dict[int, list[float]] = {level: [] for level in times}
        for t in range(len(record)):
            key = PoseKey(t, *map(float, record.poses[t]))
            full = None
            for level, scale in enumerate(RENDER_SCALES):
                t0 = time.perf_counter()
                out = composer.compose(SlotUploads(t, key=key), None, float(record.times_s[t]), render_scale=scale)
                mr_u8 = to_u8(out.mr)
                per_level[level].append(1e3 * (time.perf_counter() - t0))
                if run == 0:
                    info = MRSlotInfo.of(t, out.source, key, float(record.times_s[t]))
                    losses[level].append(float(scorer.score(info, mr_u8, truths[t]).loss))
                    full = out.mr if level == 0 else full
                    extra[level].append(mr_loss(out.mr, full))
        for level, ms in per_level.items():
            times[level].append(float(np.median(ms)))
    print("| level | render size | compose ms, median of runs (worst run) | MR loss vs truth, mean (p95) | "
          "extra loss vs full, mean (p95) |")
    print("|---|---|---|---|---|")
    for level, scale in enumerate(RENDER_SCALES):
        ms, loss, more = times[level], np.array(losses[level]), np.array(extra[level])
        print(f"| {LEVEL_NAMES[level]} | {round(k.width * scale)}×{round(k.height * scale)} | {np.median(ms):.1f} "
              f"({max(ms):.1f}) | {loss.mean():.4f} ({np.percentile(loss, 95):.4f}) | {more.mean():.4f} "
              f"({np.percentile(more, 95):.4f}) |")
    print(f"(after: load average {os.getloadavg()[0]:.1f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
