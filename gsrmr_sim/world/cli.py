"""``gsrmr-sim``: run the simulated world headless (no ROS).

    gsrmr-sim record --scene sandbox --round 1 --out data/round1 [--frames H] [--width W --height H]
    gsrmr-sim record --scene sandbox --round 2 --out data/round2 [--slots T] [--seed N]
    gsrmr-sim render --scene sandbox --pose A B THETA [--time S] [--round 2] --out view.png
    gsrmr-sim info --scene sandbox
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path
import sys
import time

import cv2
import numpy as np

from gsrmr_common.camera import camera_from_pose
from gsrmr_common.route import LoopPath
from gsrmr_server.mr.blend import mr_image
from gsrmr_sim.world.kinematics import lap_time_s
from gsrmr_sim.world.points import make_world
from gsrmr_sim.world.recorder import record_round1, record_round2, with_resolution
from gsrmr_sim.world.scene import SceneError, load_scene
from gsrmr_sim.world.virtual import virtual_view


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="gsrmr-sim", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)

    def common(sp: argparse.ArgumentParser) -> None:
        sp.add_argument("--scene", default="sandbox", help="scene name (config/scenes/NAME.yaml) or path")
        sp.add_argument("--width", type=int, help="image width in pixels (same FOV)")
        sp.add_argument("--height", type=int, help="image height in pixels")

    rec = sub.add_parser("record", help="record round 1 (nerfstudio dataset) or round 2 (evaluation slots)")
    common(rec)
    rec.add_argument("--round", type=int, choices=(1, 2), required=True,
                     help="1: mapping round (static world) -> nerfstudio dataset; 2: operating round with events")
    rec.add_argument("--out", type=Path, required=True, help="output directory")
    rec.add_argument("--frames", type=int, help="H, round-1 frames (default: the scene's)")
    rec.add_argument("--slots", type=int, help="T, round-2 slots (default: the scene's)")
    rec.add_argument("--seed", type=int, default=0, help="seed of the round-2 start jitter")
    rec.add_argument("--quiet", action="store_true", help="no progress lines")

    ren = sub.add_parser("render", help="render one view (MR image: real + virtual agents) to a PNG")
    common(ren)
    ren.add_argument("--pose", type=float, nargs=3, metavar=("A_M", "B_M", "THETA_RAD"), required=True)
    ren.add_argument("--time", type=float, default=0.0, help="round time in seconds")
    ren.add_argument("--round", type=int, choices=(1, 2), default=1)
    ren.add_argument("--out", type=Path, required=True)

    info = sub.add_parser("info", help="print the scene summary and the route's lap time")
    common(info)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``gsrmr-sim``; returns the process exit code."""
    args = _parser().parse_args(argv)
    try:
        scene = with_resolution(load_scene(args.scene), args.width, args.height)
    except (SceneError, FileNotFoundError) as exc:
        print(f"gsrmr-sim: {exc}", file=sys.stderr)
        return 2
    if args.cmd == "record":
        t0 = time.monotonic()
        if args.round == 1:
            if args.frames is not None and args.frames < 1:
                print("gsrmr-sim: --frames must be ≥ 1", file=sys.stderr)
                return 2
            out = record_round1(scene, args.out, args.frames, args.seed, progress=not args.quiet)
            n = args.frames or scene.frames
        else:
            if args.slots is not None and args.slots < 1:
                print("gsrmr-sim: --slots must be ≥ 1", file=sys.stderr)
                return 2
            out = record_round2(scene, args.out, args.slots, args.seed, progress=not args.quiet)
            n = args.slots or scene.slots
        print(f"gsrmr-sim: round {args.round} of scene {scene.name}: {n} frames in {out} "
              f"({time.monotonic() - t0:.1f} s)")
        return 0
    if args.cmd == "render":
        cam = camera_from_pose(*args.pose, scene.camera.mount, scene.camera.intrinsics)
        world = make_world(scene, args.round)
        rgb, depth = world.render(cam, args.time)
        v, d = virtual_view(scene).render(cam, time_s=args.time, real_depth_m=depth)
        m = mr_image(rgb, v, d)
        cv2.imwrite(str(args.out), cv2.cvtColor(np.clip(np.round(m * 255), 0, 255).astype(np.uint8),
                                                cv2.COLOR_RGB2BGR))
        print(f"gsrmr-sim: wrote {args.out}")
        return 0
    k = scene.camera.intrinsics
    print(f"scene {scene.name} ({scene.source})")
    print(f"camera {k.width}x{k.height} fx={k.fx:.1f} rate {scene.camera.rate_hz} Hz, "
          f"mount {scene.camera.mount}")
    print(f"objects {len(scene.objects)}, virtual agents {len(virtual_view(scene).content.agents)} "
          f"({scene.mr_content}), lights {len(scene.lights)}, "
          f"events {len(scene.events)}")
    print(f"route {LoopPath(scene.route.waypoints).length_m:.2f} m, lap {lap_time_s(scene.route):.2f} s at "
          f"{scene.route.speed_mps} m/s; T = {scene.slots} slots of {scene.slot_s} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
