"""Benchmark of the simulated world on ONE core: real camera, virtual view + mask, garden splatter.

Second table: the round-2 discrepancy profile of each scene — per slot t, the MR loss between the
round-2 MR image and the MR image of the *round-1* world at the same pose (what a perfect GS model of
round 1 would cost, L_t of the paper with Φ = the mapped world), summarised by quantiles and the
fraction of slots above 0.01 / 0.03.

Prints a table: median / p90 milliseconds per frame over the poses of one route lap (each pose
rendered once per repeat), the resulting camera rate, and the configuration. Numba compilation is
excluded (one warm-up frame). Run: ``.venv/bin/python bench/perf/world.py [--width 320 --height 240]``.
Pins the process to one CPU (``os.sched_setaffinity``) and limits numba/BLAS to one thread.
"""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
from collections.abc import Callable
import contextlib
import platform
import time

import numpy as np

from gsrmr_common.camera import Camera, camera_from_pose
from gsrmr_common.metrics import mr_loss
from gsrmr_server.mr.blend import mr_image
from gsrmr_sim.world.kinematics import drive_route, start_pose
from gsrmr_sim.world.points import make_world
from gsrmr_sim.world.recorder import with_resolution
from gsrmr_sim.world.scene import load_scene
from gsrmr_sim.world.virtual import virtual_view


def _time_ms(fn: Callable[[Camera, float], object], cams: list[Camera], times_s: list[float],
             repeats: int) -> np.ndarray:
    fn(cams[0], times_s[0])  # warm-up / JIT
    out = []
    for _ in range(repeats):
        for cam, t in zip(cams, times_s, strict=True):
            t0 = time.perf_counter()
            fn(cam, t)
            out.append((time.perf_counter() - t0) * 1e3)
    return np.asarray(out)


def main() -> None:
    """Print the benchmark table."""
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--poses", type=int, default=36, help="poses sampled over one lap")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--skip-profile", action="store_true", help="timings only")
    args = p.parse_args()
    with contextlib.suppress(AttributeError, OSError):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
    print(f"# bench/perf/world.py  {args.width}x{args.height}, {args.poses} poses over one lap x {args.repeats} "
          f"repeats, 1 core ({platform.processor() or platform.machine()}), "
          f"cpus allowed: {len(os.sched_getaffinity(0))}")
    print(f"{'scene':8s} {'stage':34s} {'median ms':>10s} {'p90 ms':>8s} {'rate Hz':>8s}")
    for name in ("sandbox", "garden"):
        scene = with_resolution(load_scene(name), args.width, args.height)
        lap_s = scene.slots * scene.slot_s
        drive = drive_route(scene.route, args.poses, lap_s / args.poses)
        cams = [camera_from_pose(*pose, scene.camera.mount, scene.camera.intrinsics) for pose in drive.poses]
        times_s = list(drive.times_s)
        world = make_world(scene, 2)
        virtual = virtual_view(scene)

        def real(cam: Camera, t: float) -> object:
            return world.render(cam, t)  # noqa: B023

        def both(cam: Camera, t: float) -> object:
            _, depth = world.render(cam, t)  # noqa: B023
            return virtual.render(cam, time_s=t, real_depth_m=depth)  # noqa: B023

        kind = "point splat" if scene.points is not None else "ray cast"
        for stage, fn in ((f"real camera ({kind})", real), ("real + virtual view + mask", both)):
            ms = _time_ms(fn, cams, times_s, args.repeats)
            med = float(np.median(ms))
            print(f"{name:8s} {stage:34s} {med:10.1f} {np.percentile(ms, 90):8.1f} {1e3 / med:8.1f}")
    if args.skip_profile:
        return
    print(f"\n# round-2 discrepancy: MR loss of the round-1 world vs round 2 at the round-2 poses, "
          f"{args.width}x{args.height}, all T slots, seed 0")
    print(f"{'scene':8s} {'T':>4s} {'median':>8s} {'p90':>8s} {'max':>8s} {'>0.01':>7s} {'>0.03':>7s}  bursts (s)")
    for name in ("sandbox", "garden"):
        scene = with_resolution(load_scene(name), args.width, args.height)
        drive = drive_route(scene.route, scene.slots, scene.slot_s,
                            pose0=start_pose(scene.route, scene.route.start_jitter_m, 0))
        now, mapped = make_world(scene, 2), make_world(scene, 1)
        virtual = virtual_view(scene)
        losses = []
        for t_s, pose in zip(drive.times_s, drive.poses, strict=True):
            cam = camera_from_pose(*pose, scene.camera.mount, scene.camera.intrinsics)
            r2, depth = now.render(cam, t_s)
            r1, _ = mapped.render(cam, t_s)
            v, d = virtual.render(cam, time_s=t_s, real_depth_m=depth)
            losses.append(mr_loss(mr_image(r2, v, d), mr_image(r1, v, d)))
        loss = np.asarray(losses)
        high = loss > 0.01
        edges = np.flatnonzero(np.diff(np.concatenate([[0], high.astype(int), [0]])))
        bursts = " ".join(f"{drive.times_s[a]:.1f}-{drive.times_s[b - 1] + scene.slot_s:.1f}"
                          for a, b in zip(edges[::2], edges[1::2], strict=True))
        print(f"{name:8s} {len(loss):4d} {np.median(loss):8.4f} {np.percentile(loss, 90):8.4f} {loss.max():8.4f} "
              f"{np.mean(loss > 0.01):7.2f} {np.mean(loss > 0.03):7.2f}  {bursts}")


if __name__ == "__main__":
    main()
