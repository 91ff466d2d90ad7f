"""A training run's start: scene extent (3DGS ``getNerfppNorm``), frames at the training resolution, initial
points back-projected from the training views, and their nearest-neighbour scales.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial import cKDTree

from gsrmr_common.camera import Camera
from gsrmr_common.nerfstudio import DatasetFrame


def scene_extent(cameras: list[Camera]) -> float:
    """3DGS ``getNerfppNorm`` radius: 1.1 × the largest camera distance from the cameras' mean (≥ 1e-3 m)."""
    centers = np.array([c.center_world for c in cameras])
    return float(max(1.1 * np.linalg.norm(centers - centers.mean(0), axis=1).max(), 1e-3))


def resize_frames(frames: list[DatasetFrame], width: int | None) -> list[DatasetFrame]:
    if width is None:
        return frames
    out = []
    for f in frames:
        k = f.camera.intrinsics
        if k.width == width:
            out.append(f)
            continue
        height = max(1, round(k.height * width / k.width))
        cam = Camera(k.scaled(width, height), f.camera.world_to_camera)
        img = cv2.resize(f.image, (width, height), interpolation=cv2.INTER_AREA)
        depth = None if f.depth_m is None else cv2.resize(f.depth_m, (width, height),
                                                           interpolation=cv2.INTER_NEAREST)
        out.append(DatasetFrame(cam, img, depth, f.pose, f.file_path))
    return out


def init_points(frames: list[DatasetFrame], n_points: int, extent: float,
                rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(N×3 points [m], N×3 colours in [0, 1]) from depth maps if present, else random in a box."""
    with_depth = [f for f in frames if f.depth_m is not None]
    if with_depth:
        pts, cols = [], []
        per = max(1, n_points // len(with_depth))
        for f in with_depth:
            valid = np.argwhere(np.isfinite(f.depth_m) & (f.depth_m > 0))
            if valid.size == 0:
                continue
            pick = valid[rng.choice(len(valid), size=min(per, len(valid)), replace=False)]
            z = f.depth_m[pick[:, 0], pick[:, 1]].astype(np.float64)
            k = f.camera.intrinsics
            x = (pick[:, 1] + 0.5 - k.cx) / k.fx * z
            y = (pick[:, 0] + 0.5 - k.cy) / k.fy * z
            c2w = f.camera.camera_to_world
            pts.append(np.stack([x, y, z], 1) @ c2w[:3, :3].T + c2w[:3, 3])
            cols.append(f.image[pick[:, 0], pick[:, 1]])
        if pts:
            return np.concatenate(pts), np.concatenate(cols).astype(np.float64)
    centers = np.array([f.camera.center_world for f in frames])
    lo, hi = centers.min(0) - extent, centers.max(0) + extent
    return rng.uniform(lo, hi, size=(n_points, 3)), rng.uniform(0.2, 0.8, size=(n_points, 3))


def knn_scales(points: np.ndarray) -> np.ndarray:
    """sqrt(mean squared distance to the 3 nearest neighbours), as 3DGS's distCUDA2 initialisation."""
    if len(points) < 4:
        return np.full(len(points), 0.01)
    d, _ = cKDTree(points).query(points, k=4)
    return np.sqrt(np.maximum(np.mean(d[:, 1:] ** 2, axis=1), 1e-14))
