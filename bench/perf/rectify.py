"""What the robot's rectification costs per camera frame: remap, resize and the JPEG of the result, on one core.

The robot (:class:`gsrmr_robot.camera_rectify.UplinkCamera` over :class:`gsrmr_common.calibration.Rectifier`)
turns each raw frame into the uplink frame with one ``cv2.remap`` at the camera's size (skipped for an
undistorted camera) and one ``cv2.resize`` ``INTER_AREA`` down to ``uplink_width_px``; the JPEG encoder then
takes the result. The raw frame is one view of a world scene (default ``sandbox``) rendered at the camera's size
(default 640×480, a real camera's VGA stream); the calibration is K with fx ≈ 0.81·width and each distortion model's
typical coefficients (``none``: zero distortion). OpenCV runs on one thread (``cv2.setNumThreads(1)``), as on a
loaded robot.

Columns, each ``median / worst`` over ``--repeats`` runs in ms: ``remap`` (:class:`Rectifier` at full size),
``resize`` (its output to the uplink size), ``total`` (:meth:`UplinkCamera.frame`, both in one call as the robot
does them) and ``JPEG q`` (:func:`gsrmr_common.jpeg.encode_jpeg` of the uplink frame, for comparison); ``maps``
is the one-off cost of a new calibration (the :class:`Rectifier` of the uplink width, median).

    .venv/bin/python bench/perf/rectify.py [--width 640 --height 480] [--uplink-width 320] [--repeats 200]
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
import os
import statistics
import time

import cv2
import numpy as np

from gsrmr_common.calibration import CameraCalibration, Rectifier
from gsrmr_common.camera import camera_from_pose
from gsrmr_common.jpeg import encode_jpeg
from gsrmr_robot.camera_rectify import UplinkCamera
from gsrmr_sim.machine_probe import machine_line
from gsrmr_sim.world.kinematics import start_pose
from gsrmr_sim.world.points import make_world
from gsrmr_sim.world.recorder import with_resolution
from gsrmr_sim.world.scene import load_scene

#: distortion model → coefficients (ROS order) of a typical wide-angle camera; "none" is an undistorted camera.
DISTORTIONS: dict[str, tuple[str, tuple[float, ...]]] = {
    "plumb_bob": ("plumb_bob", (-0.28, 0.09, 0.0007, -0.0004, -0.012)),
    "rational_polynomial": ("rational_polynomial", (-0.25, 0.07, 0.0005, -0.0003, 0.01, 0.05, -0.02, 0.004)),
    "equidistant": ("equidistant", (-0.02, 0.01, -0.004, 0.0008)),
    "none": ("plumb_bob", ()),
}


def raw_frame(scene_name: str, width: int, height: int) -> np.ndarray:
    """The scene's world at its route's start pose, rendered at width×height: H×W×3 uint8 RGB."""
    scene = with_resolution(load_scene(scene_name), width, height)
    world = make_world(scene, 1)
    rgb, _ = world.render(camera_from_pose(*start_pose(scene.route), scene.camera.mount, scene.camera.intrinsics), 0.0)
    return np.rint(np.clip(rgb, 0.0, 1.0) * 255.0).astype(np.uint8)


def calibration(model: str, width: int, height: int) -> CameraCalibration:
    """A camera of width×height with fx = 0.8125·width (≈ 74° horizontal), the principal point near the centre."""
    name, d = DISTORTIONS[model]
    f = 0.8125 * width
    k = np.array([[f, 0.0, 0.5 * width + 2.1], [0.0, 0.99 * f, 0.5 * height - 2.1], [0.0, 0.0, 1.0]])
    return CameraCalibration(width, height, k, name, d)


def timings_ms(fn: Callable[[], object], repeats: int) -> tuple[float, float]:
    """(median, worst) wall time of ``fn()`` in ms over ``repeats`` runs, after one warm-up call."""
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(1e3 * (time.perf_counter() - t0))
    return statistics.median(times), max(times)


def cell(t: tuple[float, float]) -> str:
    return f"{t[0]:.2f} / {t[1]:.2f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="sandbox")
    parser.add_argument("--width", type=int, default=640, help="raw camera width [px]")
    parser.add_argument("--height", type=int, default=480, help="raw camera height [px]")
    parser.add_argument("--uplink-width", type=int, default=320, help="the robot's uplink_width_px")
    parser.add_argument("--quality", type=int, default=80, help="JPEG quality (the robot's jpeg_quality)")
    parser.add_argument("--repeats", type=int, default=200)
    args = parser.parse_args()
    cv2.setNumThreads(1)
    raw = raw_frame(args.scene, args.width, args.height)
    load_1, load_5, load_15 = os.getloadavg()
    print(f"# rectification per {args.width}×{args.height} frame ({args.scene}) → uplink width {args.uplink_width}, "
          f"JPEG q{args.quality}; ms, median / worst of {args.repeats} runs")
    print(f"# OpenCV {cv2.__version__} on {cv2.getNumThreads()} thread; {machine_line(render_probe=False)}; "
          f"load average (1, 5, 15 min) {load_1:.2f} {load_5:.2f} {load_15:.2f}")
    print(f"| distortion | uplink size | remap ms | resize ms | total ms | JPEG q{args.quality} ms | JPEG bytes "
          "| maps ms (once) |")
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    for model in DISTORTIONS:
        calib = calibration(model, args.width, args.height)
        full = Rectifier(calib)  # the remap alone (an identity for "none")
        remapped = full(raw)
        camera = UplinkCamera(args.uplink_width)
        camera.offer(calib)
        k = camera.intrinsics
        out = camera.frame(raw)
        remap = timings_ms(lambda f=full: f(raw), args.repeats)
        resize = timings_ms(lambda r=remapped, k=k: cv2.resize(r, (k.width, k.height), interpolation=cv2.INTER_AREA),
                            args.repeats)
        # UplinkCamera.frame keeps its last result for the same raw array: time the rectifier it calls
        total = timings_ms(lambda c=camera: c.rectifier(raw), args.repeats)
        jpeg = timings_ms(lambda o=out: encode_jpeg(o, args.quality), args.repeats)
        maps = timings_ms(lambda c=calib: Rectifier(c, args.uplink_width), max(5, args.repeats // 20))
        print(f"| {model} | {k.width}×{k.height} ({camera.mode}) | {cell(remap)} | {cell(resize)} | {cell(total)} "
              f"| {cell(jpeg)} | {len(encode_jpeg(out, args.quality))} | {maps[0]:.1f} |")
    print(f"# load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
