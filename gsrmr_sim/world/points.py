"""A "real" world made of coloured points (e.g. the garden capture), drawn by a z-buffered splatter.

A point-cloud stand-in for a photograph, not a Gaussian-splatting render. The splatter: docs/world.md,
"Rendering"; the file format and its mapping into ``map``: docs/world.md, "Points files".
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Protocol

import numba
import numpy as np

from gsrmr_common.camera import Camera
from gsrmr_sim.shared_data import data_file
from gsrmr_sim.world.raycast import RayCastWorld
from gsrmr_sim.world.scene import PointsWorld, Scene, WorldState


def _rotation_to_z(up: np.ndarray) -> np.ndarray:
    """Rotation taking unit vector ``up`` onto +z (Rodrigues)."""
    u = up / np.linalg.norm(up)
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(u, z)
    c = float(u @ z)
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx * (1.0 / (1.0 + c))


def find_points_file(path: str) -> Path:
    """The points file: ``path`` itself where it exists, else its name in ``$GSRMR_DATA_DIR``."""
    p = Path(path)
    return p if p.exists() else data_file(p.name)


def load_points(spec: PointsWorld) -> tuple[np.ndarray, np.ndarray]:
    """(N×3 float64 points in the map frame, N×3 float32 colours in [0, 1]) from ``spec.path``."""
    path = find_points_file(spec.path)
    with np.load(path) as data:
        pts = np.asarray(data["means3d"], dtype=np.float64).reshape(-1, 3)
        cols = np.asarray(data["colors"]).reshape(-1, 3)
        viewmats = np.asarray(data["viewmats"], np.float64) if "viewmats" in data else None
    cols = cols.astype(np.float32) / 255.0 if cols.dtype == np.uint8 else cols.astype(np.float32)
    if spec.up is not None:
        up = np.asarray(spec.up, np.float64)
    elif viewmats is not None:  # mean camera "up" (−y of the OpenCV camera) of the capture
        up = -np.mean([vm[:3, :3].T @ np.array([0.0, 1.0, 0.0]) for vm in viewmats], axis=0)
    else:
        up = np.array([0.0, 0.0, 1.0])
    origin = np.asarray(spec.origin, np.float64) if spec.origin is not None else np.zeros(3)
    c, s = math.cos(spec.yaw_rad), math.sin(spec.yaw_rad)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ _rotation_to_z(up)
    out = spec.scale * (pts - origin) @ rot.T + np.array([0.0, 0.0, spec.height_m])
    return np.ascontiguousarray(out), np.ascontiguousarray(np.clip(cols, 0.0, 1.0))


@numba.njit(cache=True)
def splat_kernel(cam_pts: np.ndarray, cols: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                 size_m: float, max_r: int, near_m: float, out_rgb: np.ndarray,
                 out_depth: np.ndarray) -> None:
    """Z-buffered square splats of camera-frame points into out_rgb / out_depth (pre-filled)."""
    H, W = out_depth.shape
    for i in range(cam_pts.shape[0]):
        z = cam_pts[i, 2]
        if z <= near_m:
            continue
        u = fx * cam_pts[i, 0] / z + cx
        v = fy * cam_pts[i, 1] / z + cy
        r = int(min(max_r, max(0, round(0.5 * fx * size_m / z))))
        iu = math.floor(u)
        iv = math.floor(v)
        if iu + r < 0 or iu - r >= W or iv + r < 0 or iv - r >= H:
            continue
        for yy in range(max(0, iv - r), min(H, iv + r + 1)):
            for xx in range(max(0, iu - r), min(W, iu + r + 1)):
                if z < out_depth[yy, xx]:
                    out_depth[yy, xx] = z
                    out_rgb[yy, xx, 0] = cols[i, 0]
                    out_rgb[yy, xx, 1] = cols[i, 1]
                    out_rgb[yy, xx, 2] = cols[i, 2]


class PointsWorldRenderer:
    """The real world of a points scene; same ``render(camera, t_s)`` contract as RayCastWorld."""

    NEAR_M = 0.05

    def __init__(self, scene: Scene, round_index: int = 1) -> None:
        if scene.points is None:
            raise ValueError(f"scene {scene.name!r} has no 'points' section")
        self.scene = scene
        self.round_index = int(round_index)
        self.points_m, self.colors = load_points(scene.points)

    def state(self, t_s: float) -> WorldState:
        """The real world's state at round time ``t_s``."""
        return self.scene.state_at(self.round_index, t_s)

    def _colors_at(self, state: WorldState) -> np.ndarray:
        cols = self.colors
        gain = state.ambient / self.scene.ambient if self.scene.ambient > 0 else 1.0
        if gain != 1.0 or state.regions:
            cols = cols * np.float32(gain)
            for lo, hi, g in state.regions:
                inside = np.all((self.points_m >= lo) & (self.points_m <= hi), axis=1)
                cols[inside] *= np.asarray(g, np.float32)
            cols = np.clip(cols, 0.0, 1.0).astype(np.float32)
        return cols

    def render(self, camera: Camera, t_s: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Colour (H×W×3 float32 in [0, 1]) and depth (H×W float32, camera z in metres, +inf = nothing)."""
        state = self.state(t_s)
        k = camera.intrinsics
        rgb = np.empty((k.height, k.width, 3), np.float32)
        rgb[:] = np.asarray(self.scene.background, np.float32)
        depth = np.full((k.height, k.width), np.inf, np.float32)
        cam_pts = camera.to_camera(self.points_m)
        splat_kernel(cam_pts, self._colors_at(state), k.fx, k.fy, k.cx, k.cy, self.scene.points.point_size_m,
                     self.scene.points.max_radius_px, self.NEAR_M, rgb, depth)
        for _ in range(self.scene.points.fill_passes):
            fill_holes_kernel(rgb, depth, 5)
        return rgb, depth


@numba.njit(cache=True)
def fill_holes_kernel(rgb: np.ndarray, depth: np.ndarray, min_neighbours: int) -> None:
    """One pass: an empty pixel with ≥ ``min_neighbours`` filled 8-neighbours takes the nearest one.

    Closes the pin-holes between splats on surfaces without growing silhouettes into empty space.
    """
    H, W = depth.shape
    src_d = depth.copy()
    src_c = rgb.copy()
    for y in range(H):
        for x in range(W):
            if np.isfinite(src_d[y, x]):
                continue
            count = 0
            best = np.inf
            by = -1
            bx = -1
            for dy in range(-1, 2):
                for dx in range(-1, 2):
                    yy = y + dy
                    xx = x + dx
                    if (dy == 0 and dx == 0) or yy < 0 or yy >= H or xx < 0 or xx >= W:
                        continue
                    z = src_d[yy, xx]
                    if np.isfinite(z):
                        count += 1
                        if z < best:
                            best = z
                            by = yy
                            bx = xx
            if count >= min_neighbours:
                depth[y, x] = best
                rgb[y, x, 0] = src_c[by, bx, 0]
                rgb[y, x, 1] = src_c[by, bx, 1]
                rgb[y, x, 2] = src_c[by, bx, 2]


class RealWorld(Protocol):
    """What renders the real world: RayCastWorld or PointsWorldRenderer."""

    scene: Scene
    round_index: int

    def state(self, t_s: float) -> WorldState:
        """The real world's state at round time ``t_s``."""
        ...

    def render(self, camera: Camera, t_s: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """(rgb H×W×3 float32 in [0, 1], depth H×W float32 camera z in metres, +inf = nothing)."""
        ...


def make_world(scene: Scene, round_index: int = 1) -> RealWorld:
    """The real-world renderer a scene asks for: points if it has ``points``, else ray casting."""
    if scene.points is not None:
        return PointsWorldRenderer(scene, round_index)
    return RayCastWorld(scene, round_index)
