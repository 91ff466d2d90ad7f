"""A training run's start: the scene extent (3DGS ``getNerfppNorm``), frames at the training resolution and the initial
points — back-projected depth, a point cloud the dataset names, or random — with their nearest-neighbour scales. Which
source: :func:`choose_init`; design: docs/splatting.md, "Training on what a robot records".
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


INIT_METHODS = ("auto", "depth", "points", "random")


def has_depth(frames: list[DatasetFrame]) -> bool:
    """Whether any frame carries a depth map."""
    return any(f.depth_m is not None for f in frames)


def choose_init(method: str, frames: list[DatasetFrame], point_cloud_given: bool) -> str:
    """The initialisation ``method`` resolves to: ``auto`` → depth when a training frame has depth, else the
    dataset's point cloud when there is one, else random. ValueError when an explicit source is missing."""
    if method not in INIT_METHODS:
        raise ValueError(f"init must be one of {', '.join(INIT_METHODS)}, got {method!r}")
    if method == "auto":
        return "depth" if has_depth(frames) else "points" if point_cloud_given else "random"
    if method == "depth" and not has_depth(frames):
        raise ValueError("init 'depth': no training frame has a depth map (depth_file_path in transforms.json)")
    if method == "points" and not point_cloud_given:
        raise ValueError("init 'points': the dataset names no point cloud (ply_file_path in transforms.json)")
    return method


def depth_points(frames: list[DatasetFrame], n_points: int,
                 rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray] | None:
    """(N×3 points [m], N×3 colours in [0, 1]): about ``n_points`` valid depth pixels (an equal share per frame
    with depth, drawn from ``rng``) back-projected through their pixel centres; None without any valid depth."""
    with_depth = [f for f in frames if f.depth_m is not None]
    if not with_depth:
        return None
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
    if not pts:
        return None
    return np.concatenate(pts), np.concatenate(cols).astype(np.float64)


def random_points(frames: list[DatasetFrame], n_points: int, extent: float,
                  rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(N×3 points [m], N×3 colours in [0.2, 0.8]) uniform in the cameras' bounding box grown by ``extent`` m."""
    centers = np.array([f.camera.center_world for f in frames])
    lo, hi = centers.min(0) - extent, centers.max(0) + extent
    return rng.uniform(lo, hi, size=(n_points, 3)), rng.uniform(0.2, 0.8, size=(n_points, 3))


def cloud_points(points_m: np.ndarray, colors: np.ndarray, n_points: int,
                 rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A point cloud subsampled to at most ``n_points`` (drawn without replacement from ``rng``, kept in file
    order; all of it when it is smaller): (N×3 points [m], N×3 colours in [0, 1])."""
    pts = np.asarray(points_m, np.float64).reshape(-1, 3)
    cols = np.asarray(colors, np.float64).reshape(-1, 3)
    if len(pts) == 0:
        raise ValueError("init 'points': the dataset's point cloud is empty")
    if len(pts) > n_points:
        keep = np.sort(rng.choice(len(pts), size=n_points, replace=False))
        pts, cols = pts[keep], cols[keep]
    return pts, np.clip(cols, 0.0, 1.0)


def init_points(frames: list[DatasetFrame], n_points: int, extent: float,
                rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(N×3 points [m], N×3 colours in [0, 1]) from depth maps if present, else random in a box."""
    from_depth = depth_points(frames, n_points, rng)
    return from_depth if from_depth is not None else random_points(frames, n_points, extent, rng)


def initial_points(method: str, frames: list[DatasetFrame], n_points: int, extent: float, rng: np.random.Generator,
                   point_cloud: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray, str]:
    """(points, colours, the source used) for ``TrainConfig.init`` = ``method`` (:func:`choose_init`). ``auto`` and
    ``depth`` fall back to random points when no depth pixel is valid, as :func:`init_points` does."""
    source = choose_init(method, frames, point_cloud is not None)
    if source == "points" and point_cloud is not None:
        return (*cloud_points(*point_cloud, n_points, rng), "points")
    if source == "random":
        return (*random_points(frames, n_points, extent, rng), "random")
    from_depth = depth_points(frames, n_points, rng)
    if from_depth is None:
        return (*random_points(frames, n_points, extent, rng), "random")
    return (*from_depth, "depth")


def knn_scales(points: np.ndarray) -> np.ndarray:
    """sqrt(mean squared distance to the 3 nearest neighbours), as 3DGS's distCUDA2 initialisation."""
    if len(points) < 4:
        return np.full(len(points), 0.01)
    d, _ = cKDTree(points).query(points, k=4)
    return np.sqrt(np.maximum(np.mean(d[:, 1:] ** 2, axis=1), 1e-14))
