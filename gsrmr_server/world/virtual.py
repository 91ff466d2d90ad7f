"""Virtual view v_t and mask d_t: the scene's virtual agents rendered at the robot camera's pose.

``d_t`` (paper Eq. 1) is 1 where the MR image shows the real image and 0 where it shows the virtual
one: a pixel is virtual when a virtual agent is hit there *and* is nearer than the real surface
(depth test against the real depth map, camera-space z in metres), so an agent behind a real box
is hidden. ``v_t`` is the agents' Lambertian render (lit by the scene's round-1 lights — the virtual
world does not see the real world's round-2 lighting changes) and 0 (black) wherever no agent is
hit; only ``(1 − d_t) ⊙ v_t`` enters the MR image, so the black background never shows.

Agents with a path move at constant speed along its waypoints (closed polygon when ``loop``; a
two-point loop goes there and back), heading along the segment they are on. Pure numpy/numba, no ROS.
"""

from __future__ import annotations

from dataclasses import replace
import math
from typing import TYPE_CHECKING

import numpy as np

from gsrmr_common.camera import Camera
from gsrmr_server.world.raycast import render_shapes
from gsrmr_server.world.scene import Agent, Scene, Shape

if TYPE_CHECKING:
    from gsrmr_server.world.points import RealWorld


def agent_pose(agent: Agent, t_s: float) -> tuple[float, float, float]:
    """(x_m, y_m, yaw_rad) of an agent at round time ``t_s`` (map frame)."""
    body = agent.body
    if agent.path is None:
        return body.position[0], body.position[1], body.yaw_rad
    pts = np.asarray(agent.path.waypoints, dtype=np.float64)
    if agent.path.loop:
        pts = np.vstack([pts, pts[:1]])
    seg = np.diff(pts, axis=0)
    lengths = np.hypot(seg[:, 0], seg[:, 1])
    total = float(lengths.sum())
    if total <= 0:
        return float(pts[0, 0]), float(pts[0, 1]), body.yaw_rad
    s = agent.path.speed_mps * max(0.0, t_s)
    s = s % total if agent.path.loop else min(s, total - 1e-9)
    cum = np.concatenate([[0.0], np.cumsum(lengths)])
    i = int(np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(lengths) - 1))
    frac = (s - cum[i]) / lengths[i] if lengths[i] > 0 else 0.0
    p = pts[i] + frac * seg[i]
    return float(p[0]), float(p[1]), math.atan2(seg[i, 1], seg[i, 0]) + body.yaw_rad


def agents_at(scene: Scene, t_s: float) -> list[Shape]:
    """The virtual agents' bodies placed at round time ``t_s``."""
    out = []
    for agent in scene.agents:
        x, y, yaw = agent_pose(agent, t_s)
        out.append(replace(agent.body, position=(x, y), yaw_rad=yaw))
    return out


def compose_mask(virtual_depth_m: np.ndarray, real_depth_m: np.ndarray) -> np.ndarray:
    """d_t: 1.0 where the real surface is nearer than (or no) virtual agent, 0.0 where an agent shows.

    Real depth +inf, NaN or ≤ 0 means "no real surface" (0 is the no-depth value of depth PNGs).
    """
    real = np.where(np.isfinite(real_depth_m) & (real_depth_m > 0), real_depth_m, np.inf)
    return np.where(np.isfinite(virtual_depth_m) & (virtual_depth_m < real), 0.0, 1.0).astype(np.float32)


def mr_image(real: np.ndarray, virtual: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The MR image m_t = d ⊙ r + (1 − d) ⊙ v (paper Eq. 1); H×W×3 float32."""
    d = np.asarray(mask, np.float32)[..., None]
    return (d * np.asarray(real, np.float32) + (1.0 - d) * np.asarray(virtual, np.float32)).astype(np.float32)


class VirtualViewSource:
    """Virtual view and mask at a camera pose: ``render(camera) -> (v H×W×3 f32, d H×W f32 in {0, 1})``.

    The real depth used for occlusion is ``real_depth_m`` if given, else the depth of ``real_world``
    (a :class:`~gsrmr_server.world.points.RealWorld`, e.g. the digital twin
    ``make_world(scene, round)``) at ``time_s``. Set ``time_s`` (round seconds)
    before rendering so moving agents are where they should be.
    """

    def __init__(self, scene: Scene, real_world: RealWorld | None = None, time_s: float = 0.0) -> None:
        self.scene = scene
        self.real_world = real_world
        self.time_s = float(time_s)
        self._state = scene.state_at(1, 0.0)

    def render(self, camera: Camera, *, time_s: float | None = None,
               real_depth_m: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(v_t, d_t) at ``camera``; see the class docstring for the real depth used for occlusion."""
        t = self.time_s if time_s is None else float(time_s)
        if real_depth_m is None:
            if self.real_world is None:
                real_depth_m = np.full((camera.height, camera.width), np.inf, np.float32)
            else:
                real_depth_m = self.real_world.render(camera, t)[1]
        if real_depth_m.shape != (camera.height, camera.width):
            raise ValueError(f"real depth is {real_depth_m.shape}, camera is {camera.height}×{camera.width}")
        shapes = agents_at(self.scene, t)
        if not shapes:
            return (np.zeros((camera.height, camera.width, 3), np.float32),
                    np.ones((camera.height, camera.width), np.float32))
        rgb, depth = render_shapes(camera, shapes, self._state)
        mask = compose_mask(depth, real_depth_m)
        v = np.where(mask[..., None] < 0.5, rgb, 0.0).astype(np.float32)
        return v, mask
