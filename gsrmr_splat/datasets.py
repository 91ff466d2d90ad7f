"""Synthetic training data rendered with the engine itself, for the training tests and benchmarks: :func:`orbit_cameras`
(a circle around a target, world z up) and :func:`render_views` (nerfstudio frames with depth).
"""

from __future__ import annotations

import math

import numpy as np

from gsrmr_common.camera import Camera, Intrinsics
from gsrmr_common.nerfstudio import DatasetFrame
from gsrmr_splat.model import GaussianModel
from gsrmr_splat.render import render


def look_at(eye_m: np.ndarray, target_m: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """World→camera 4×4 (OpenCV axes) of a camera at ``eye_m`` looking at ``target_m``, world ``up``."""
    eye, target = np.asarray(eye_m, np.float64), np.asarray(target_m, np.float64)
    fwd = target - eye
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, np.asarray(up, np.float64))
    if np.linalg.norm(right) < 1e-9:
        raise ValueError("look_at: viewing direction is parallel to up")
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    rot = np.stack([right, down, fwd])  # rows: camera axes in the world
    w2c = np.eye(4)
    w2c[:3, :3] = rot
    w2c[:3, 3] = -rot @ eye
    return w2c


def orbit_cameras(n: int, intrinsics: Intrinsics, radius_m: float = 1.1, heights_m=(0.35, 0.6),
                  target_m=(0.0, 0.0, 0.1)) -> list[Camera]:
    """``n`` cameras evenly spaced in azimuth, alternating between the given heights, facing the target."""
    cams = []
    for i in range(n):
        phi = 2.0 * math.pi * i / n
        eye = np.array([radius_m * math.cos(phi), radius_m * math.sin(phi), heights_m[i % len(heights_m)]])
        cams.append(Camera(intrinsics, look_at(eye, np.asarray(target_m))))
    return cams


def render_views(model: GaussianModel, cameras: list[Camera], background=(0.0, 0.0, 0.0),
                 with_depth: bool = True) -> list[DatasetFrame]:
    """Render ``model`` from every camera: RGB (quantised to 8 bit like a saved PNG) and depth [m]."""
    frames = []
    for i, cam in enumerate(cameras):
        out = render(model, cam, background)
        img = np.round(out.rgb * 255.0) / 255.0
        depth = np.where(out.alpha > 0.5, out.depth, 0.0).astype(np.float32) if with_depth else None
        frames.append(DatasetFrame(cam, img.astype(np.float32), depth, None, f"images/frame_{i:05d}.png"))
    return frames
