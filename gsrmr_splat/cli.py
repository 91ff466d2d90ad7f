"""``gsrmr-render``: a 3DGS .ply rendered to PNGs (numba, no torch); ``gsrmr-train`` and ``gsrmr-compact`` are
:mod:`~gsrmr_splat.train_cli`.

Renders every camera of ``--cameras CAMERAS.json`` (a list of ``{"width", "height", "K", "world_to_camera"}``: K 3×3 in
pixels with pixel centres at +0.5, world→camera 4×4 in OpenCV axes) or every robot pose ``--pose a,b,θ`` (metres,
metres, radians; the camera from the mount and intrinsics options) to DIR/000.png, 001.png, … in list order.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
import sys
import time

import cv2
import numpy as np

from gsrmr_common.camera import Camera, CameraMount, Intrinsics, camera_from_pose
from gsrmr_splat.model import GaussianModel
from gsrmr_splat.render import render


def _floats(text: str, n: int, what: str) -> tuple[float, ...]:
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"{what}: expected {n} comma-separated numbers, got {text!r}") from exc
    if len(vals) != n or not all(math.isfinite(v) for v in vals):
        raise argparse.ArgumentTypeError(f"{what}: expected {n} finite comma-separated numbers, got {text!r}")
    return vals


def _pose(text: str) -> tuple[float, ...]:
    return _floats(text, 3, "--pose a,b,theta")


def rgb_arg(text: str) -> tuple[float, ...]:
    """argparse type of a ``--background r,g,b`` colour (three finite numbers)."""
    return _floats(text, 3, "--background r,g,b")


def load_cameras_json(path: str | Path) -> list[Camera]:
    """Parse a CAMERAS.json list; raises ValueError naming the bad entry."""
    data = json.loads(Path(path).read_text())
    if not isinstance(data, list):
        raise ValueError(f"{path}: expected a JSON list of cameras")
    cams = []
    for i, entry in enumerate(data):
        try:
            k = np.asarray(entry["K"], dtype=np.float64)
            w2c = np.asarray(entry["world_to_camera"], dtype=np.float64)
            if k.shape != (3, 3) or w2c.shape != (4, 4):
                raise ValueError("K must be 3×3 and world_to_camera 4×4")
            cams.append(Camera(Intrinsics.from_k(k, int(entry["width"]), int(entry["height"])), w2c))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{path}: camera {i}: {exc}") from exc
    return cams


def render_main(argv: list[str] | None = None) -> int:
    """Entry point of ``gsrmr-render``."""
    ap = argparse.ArgumentParser(prog="gsrmr-render", description=__doc__.split("\n\n")[1],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("model", help="3DGS .ply model")
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--cameras", help="CAMERAS.json (list of width/height/K/world_to_camera)")
    src.add_argument("--pose", type=_pose, action="append", help="robot pose a_m,b_m,theta_rad (repeatable)")
    ap.add_argument("--out", required=True, help="output directory (000.png, 001.png, …)")
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--hfov-deg", type=float, default=70.0, help="horizontal field of view for --pose")
    ap.add_argument("--mount-height-m", type=float, default=CameraMount.height_m)
    ap.add_argument("--mount-pitch-rad", type=float, default=CameraMount.pitch_rad)
    ap.add_argument("--mount-forward-m", type=float, default=CameraMount.forward_m)
    ap.add_argument("--mount-left-m", type=float, default=CameraMount.left_m)
    ap.add_argument("--background", type=rgb_arg, default=(0.0, 0.0, 0.0), help="r,g,b in [0, 1]")
    ap.add_argument("--depth", action="store_true", help="also write DIR/NNN_depth.png (uint16 mm)")
    args = ap.parse_args(argv)
    try:
        model = GaussianModel.load_ply(args.model)
        if args.cameras:
            cams = load_cameras_json(args.cameras)
        else:
            mount = CameraMount(args.mount_height_m, args.mount_pitch_rad, args.mount_forward_m, args.mount_left_m)
            k = Intrinsics.from_fov(args.width, args.height, math.radians(args.hfov_deg))
            cams = [camera_from_pose(a, b, th, mount, k) for a, b, th in args.pose]
    except (ValueError, FileNotFoundError) as exc:
        print(f"gsrmr-render: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for i, cam in enumerate(cams):
        t0 = time.perf_counter()
        res = render(model, cam, args.background)
        dt = time.perf_counter() - t0
        u8 = np.clip(np.round(res.rgb * 255.0), 0, 255).astype(np.uint8)
        cv2.imwrite(str(out / f"{i:03d}.png"), cv2.cvtColor(u8, cv2.COLOR_RGB2BGR))
        if args.depth:
            mm = np.clip(np.round(res.depth * 1000.0), 0, 65535).astype(np.uint16)
            cv2.imwrite(str(out / f"{i:03d}_depth.png"), mm)
        print(f"{out / f'{i:03d}.png'}: {cam.width}×{cam.height}, {res.num_visible} visible Gaussians, "
              f"{dt * 1000:.1f} ms")
    return 0
