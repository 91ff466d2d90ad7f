"""The server's slot composition (``MRComposer.compose``) on one thread against the virtual view cast beside it.

Composes image slots of the sandbox route with a GS model (default: the demo's cached compacted model, as ``make
demo`` builds it) and the sandbox's MR content at the scene's 320×240, in two ways interleaved run by run:

* ``beside`` — what the server does: the virtual view's ray cast (``AgentsView.cast``, a kernel that releases the
  GIL) starts on a worker thread before the GS render, and is occluded by the render's depth afterwards;
* ``in sequence`` — the GS render, then the whole virtual view (a source with only ``render``), as before
  2026-11-28.

Prints a table: per way, the median and worst over ``--runs`` runs of each run's median compose time (``--slots``
slots a run after ``--warm`` warm-up slots), and the stage timings. Usage::

    .venv/bin/python bench/perf/compose_slot.py [--model PLY] [--runs 5] [--slots 60]
"""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path
import time

import numpy as np

from gsrmr_common.camera import CameraMount, Intrinsics
from gsrmr_common.jpeg import encode_jpeg
from gsrmr_common.wire import PoseKey
from gsrmr_server.compose import MRComposer
from gsrmr_server.mr.content import AgentsView, load_mr_content
from gsrmr_server.uplink import SlotUploads
from gsrmr_sim.machine_probe import machine_line
from gsrmr_sim.shared_data import garden_model
from gsrmr_splat.model import GaussianModel

REPO = Path(__file__).resolve().parents[2]


class _InSequence:
    """The virtual view with only ``render``: the composer casts it after the GS render, on its own thread."""

    def __init__(self, view: AgentsView) -> None:
        self.view = view

    def render(self, camera, *, time_s=0.0, real_depth_m=None):
        return self.view.render(camera, time_s=time_s, real_depth_m=real_depth_m)


def _default_model() -> tuple[str, GaussianModel]:
    """The demo's cached compacted sandbox model, or (none cached: a fresh machine) the garden test model."""
    found = sorted((REPO / ".cache" / "gsrmr").glob("sandbox-*/model-compact-*.ply"))
    if found:
        return found[0].name, GaussianModel.load_ply(found[0])
    return "no cached sandbox model (`make demo` builds one): the garden test model", garden_model()


def _run(composer: MRComposer, jpeg: bytes, slots: int, warm: int) -> tuple[float, dict[str, float]]:
    """One run along the route's first straight (−1 → 1 m at y = −1.1): median compose ms and stage medians."""
    totals, stages = [], {}
    for i in range(warm + slots):
        a_m = -1.0 + 2.0 * (i % 60) / 60
        uploads = SlotUploads(i, key=PoseKey(i, a_m, -1.1, 0.0), jpeg=jpeg)
        t0 = time.perf_counter()
        out = composer.compose(uploads, None, 0.1 * i)
        if i >= warm:
            totals.append(1e3 * (time.perf_counter() - t0))
            for k, v in out.timings_ms.items():
                stages.setdefault(k, []).append(v)
    return float(np.median(totals)), {k: float(np.median(v)) for k, v in stages.items()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", type=Path, default=None, help="3DGS .ply (default: the demo's cached compacted model)")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--slots", type=int, default=60)
    ap.add_argument("--warm", type=int, default=10)
    args = ap.parse_args(argv)
    name, model = (args.model.name, GaussianModel.load_ply(args.model)) if args.model else _default_model()
    k = Intrinsics.from_fov(320, 240, math.radians(70))
    mount = CameraMount(height_m=0.15, pitch_rad=math.radians(5), forward_m=0.1)
    view = AgentsView(load_mr_content("sandbox"))
    ways = {"beside": MRComposer(model, view, k, mount, (0.5, 0.55, 0.6), render_threads=1),
            "in sequence": MRComposer(model, _InSequence(view), k, mount, (0.5, 0.55, 0.6), render_threads=1)}
    rng = np.random.default_rng(0)
    jpeg = encode_jpeg(rng.integers(0, 255, (240, 320, 3), np.uint8), 80)
    print(f"# bench/perf/compose_slot.py: {name} ({model.num_gaussians} Gaussians), 320×240, render on 1 "
          f"thread, image slots with the sandbox's MR content; {args.runs} runs × {args.slots} slots "
          f"(before: {machine_line()})")
    results: dict[str, list[tuple[float, dict[str, float]]]] = {w: [] for w in ways}
    for _ in range(args.runs):  # interleaved, so a change in the machine's speed hits both ways
        for way, composer in ways.items():
            results[way].append(_run(composer, jpeg, args.slots, args.warm))
    print("| way | compose ms, median of runs (worst run) | render ms | virtual ms after the render | total ms |")
    print("|---|---|---|---|---|")
    for way, runs in results.items():
        med = [m for m, _ in runs]
        stage = {key: float(np.median([s[key] for _, s in runs])) for key in ("render", "virtual", "total")}
        print(f"| {way} | {np.median(med):.1f} ({max(med):.1f}) | {stage['render']:.1f} | {stage['virtual']:.1f} | "
              f"{stage['total']:.1f} |")
    print(f"(after: load average {os.getloadavg()[0]:.1f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
