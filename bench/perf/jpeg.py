"""JPEG uplink payload vs quality on simulated-world camera frames, and the cost of guarded decoding.

Renders frames along the route of a world scene (default ``sandbox``, 320×240 as configured), encodes
each with :func:`gsrmr_common.jpeg.encode_jpeg` at several qualities and prints median bytes, bits
(= payload of an image slot), PSNR, SSIM and encode/decode times. Then times the header-only checks.

    .venv/bin/python bench/perf/jpeg.py [--scene sandbox] [--frames 6] [--repeats 5]
"""

from __future__ import annotations

import argparse
import statistics
import struct
import time

import numpy as np

from gsrmr_common import wire
from gsrmr_common.camera import camera_from_pose
from gsrmr_common.jpeg import ImageRejected, check_jpeg_structure, decode_jpeg, encode_jpeg, jpeg_dimensions
from gsrmr_common.metrics import psnr, ssim
from gsrmr_sim.world.kinematics import drive_route, start_pose
from gsrmr_sim.world.points import make_world
from gsrmr_sim.world.scene import load_scene

QUALITIES = (10, 25, 40, 55, 70, 80, 90, 95)


def frames(scene_name: str, count: int) -> tuple[list[np.ndarray], str]:
    """``count`` RGB uint8 frames evenly spaced over the scene's operating round."""
    scene = load_scene(scene_name)
    drive = drive_route(scene.route, count, scene.slots * scene.slot_s / count, pose0=start_pose(scene.route))
    world = make_world(scene, 1)
    out = []
    for t_s, pose in zip(drive.times_s, drive.poses, strict=True):
        rgb, _ = world.render(camera_from_pose(*pose, scene.camera.mount, scene.camera.intrinsics), float(t_s))
        out.append(np.rint(np.clip(rgb, 0, 1) * 255).astype(np.uint8))
    k = scene.camera.intrinsics
    return out, f"{scene.name} {k.width}×{k.height}"


def timed_ms(fn: object, repeats: int) -> float:
    """Median wall time of ``fn()`` in milliseconds over ``repeats`` runs."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()  # type: ignore[operator]
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="sandbox")
    parser.add_argument("--frames", type=int, default=6)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    imgs, label = frames(args.scene, args.frames)
    print(f"# JPEG on {args.frames} frames of {label}; medians over frames, times over {args.repeats} runs")
    print(f"# a pose key is {wire.POSE_KEY_BITS} bits")
    print("| quality | bytes | bits | bits/px | PSNR dB | SSIM | encode ms | decode_jpeg ms |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    for q in QUALITIES:
        rows = []
        for img in imgs:
            data = encode_jpeg(img, q)
            out = decode_jpeg(data)
            a, b = img / 255.0, out / 255.0
            enc_ms = timed_ms(lambda i=img, qq=q: encode_jpeg(i, qq), args.repeats)
            dec_ms = timed_ms(lambda d=data: decode_jpeg(d), args.repeats)
            rows.append((len(data), psnr(a, b), ssim(a, b), enc_ms, dec_ms))
        med = [statistics.median(c) for c in zip(*rows, strict=True)]
        px = imgs[0].shape[0] * imgs[0].shape[1]
        print(f"| {q} | {med[0]:.0f} | {8 * med[0]:.0f} | {8 * med[0] / px:.3f} | {med[1]:.2f} | {med[2]:.4f} "
              f"| {med[3]:.2f} | {med[4]:.2f} |")

    data = encode_jpeg(imgs[0], 80)
    at = min(o for o in (data.find(b"\xff\xc0"), data.find(b"\xff\xc2")) if o >= 0) + 5
    forged = data[:at] + struct.pack(">HH", 20000, 20000) + data[at + 4:]

    def refuse() -> None:
        try:
            decode_jpeg(forged)
        except ImageRejected:
            return
        raise AssertionError("forged header accepted")

    n = 2000
    print(f"\n# header checks on one q=80 frame ({len(data)} bytes), median of {args.repeats} × {n} calls")
    print("| operation | µs per call |")
    print("|---|---:|")
    for name, fn in (("jpeg_dimensions", lambda: jpeg_dimensions(data)),
                     ("check_jpeg_structure", lambda: check_jpeg_structure(data)),
                     ("decode_jpeg refusing a 20000×20000 header", refuse)):
        per = timed_ms(lambda f=fn: [f() for _ in range(n)], args.repeats) * 1e3 / n
        print(f"| {name} | {per:.1f} |")


if __name__ == "__main__":
    main()
