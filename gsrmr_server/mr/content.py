"""MR content (pure numpy/numba, no ROS): the virtual agents, their lighting and their YAML (``config/mr/<name>.yaml``).

The virtual world is the server's: its agents exist only there, it is lit by its own lights and it never sees the
real world's changes. The file (:func:`parse_mr_content`): ``docs/world.md``, "Virtual view v_t and mask d_t".
Frames: ``map`` (x forward, y left, z up, metres); an agent's time is seconds since the round began.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
import math
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import yaml

from gsrmr_common.camera import Camera
from gsrmr_common.config_files import resolve_config
from gsrmr_common.pose2d import Pose2D
from gsrmr_server.mr.blend import compose_mask
from gsrmr_shapes.raycast import render_shapes
from gsrmr_shapes.spec import (
    Material,
    Shape,
    SpecError,
    StaticLighting,
    listing,
    mapping,
    number,
    parse_light,
    parse_shape,
    parse_waypoints,
    string,
    unique,
)

MRContentError = SpecError  # an invalid MR content file; the message starts with the key path


@dataclass(frozen=True)
class AgentPath:
    """A virtual agent's motion: constant speed along waypoints (closed polygon when ``loop``; a two-point loop goes
    there and back), heading along the segment it is on."""

    waypoints: tuple[tuple[float, float], ...]
    speed_mps: float
    loop: bool = True


@dataclass(frozen=True)
class Agent:
    """A virtual agent: a shape that exists only in the virtual world (static if ``path`` is None)."""

    body: Shape
    path: AgentPath | None = None


@dataclass(frozen=True)
class MRContent:
    """A validated MR content file: the agents and the virtual world's lighting."""

    name: str
    agents: tuple[Agent, ...] = ()
    lighting: StaticLighting = field(default_factory=StaticLighting)
    source: str = ""


def _agent(value: Any, path: str, index: int) -> Agent:
    body = parse_shape({k: v for k, v in value.items() if k != "path"} if isinstance(value, dict) else value,
                       path, f"agent{index}")
    if isinstance(value, dict) and "material" not in value:
        body = replace(body, material=Material("stripes", (0.2, 0.4, 0.9), (0.9, 0.9, 0.95), 0.1))
    p = value.get("path")
    agent_path = None
    if p is not None:
        pm = mapping(p, f"{path}.path", {"waypoints", "speed_mps", "loop"}, ("waypoints",))
        loop = pm.get("loop", True)
        if not isinstance(loop, bool):
            raise SpecError(f"{path}.path.loop: must be true or false")
        agent_path = AgentPath(parse_waypoints(pm["waypoints"], f"{path}.path.waypoints", 2),
                               number(pm.get("speed_mps", 0.3), f"{path}.path.speed_mps", positive=True), loop)
    return Agent(body, agent_path)


def parse_mr_content(data: Any, source: str = "") -> MRContent:
    """Validate an MR content mapping (as loaded from YAML). A file holds::

        name: sandbox
        ambient: 0.45                       # ambient light level, ≥ 0
        lights: [...]                       # directional / point lights (gsrmr_shapes.spec.parse_light)
        virtual_agents:                     # boxes / cylinders (gsrmr_shapes.spec.parse_shape), plus
          - {id: walker, shape: cylinder, position: [x_m, y_m], ...,
             path: {waypoints: [[x_m, y_m], ...], speed_mps: 0.2, loop: true}}   # optional motion

    The built-in files copy the mapping round's lights of the scene they belong to, so that the agents look like
    part of the room.
    """
    m = mapping(data if data is not None else {}, "", {"name", "ambient", "lights", "virtual_agents"})
    name = string(m.get("name", Path(source).stem if source else "mr"), "name")
    lights = tuple(parse_light(v, f"lights[{i}]", i) for i, v in enumerate(listing(m.get("lights", []), "lights")))
    unique([lt.id for lt in lights], "lights")
    agents = tuple(_agent(v, f"virtual_agents[{i}]", i)
                   for i, v in enumerate(listing(m.get("virtual_agents", []), "virtual_agents")))
    unique([a.body.id for a in agents], "virtual_agents")
    ambient = number(m.get("ambient", 0.4), "ambient", lo=0.0, hi=2.0)
    return MRContent(name, agents, StaticLighting(lights, ambient), source)


def resolve_mr_content_path(name_or_path: str) -> Path:
    """An MR content file from a path or a bare name (``sandbox`` → ``…/config/mr/sandbox.yaml``)."""
    return resolve_config(name_or_path, "mr", "MR content")


def load_mr_content(name_or_path: str) -> MRContent:
    """Load and validate an MR content file by name or path."""
    path = resolve_mr_content_path(name_or_path)
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise MRContentError(f"{path}: not valid YAML: {exc}") from exc
    try:
        return parse_mr_content(data, str(path))
    except SpecError as exc:
        raise MRContentError(f"{path}: {exc}") from exc


def agent_pose(agent: Agent, t_s: float) -> Pose2D:
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


def agents_at(content: MRContent, t_s: float) -> list[Shape]:
    """The virtual agents' bodies placed at round time ``t_s``."""
    out = []
    for agent in content.agents:
        x, y, yaw = agent_pose(agent, t_s)
        out.append(replace(agent.body, position=(x, y), yaw_rad=yaw))
    return out


class VirtualViewSource(Protocol):
    """What the server composites: the virtual view v_t and the mask d_t at a camera pose.

    ``render(camera, time_s=…, real_depth_m=…)`` returns (v H×W×3 float32 in [0, 1], d H×W float32 in
    {0, 1}, 1 = real). ``real_depth_m`` (H×W, camera-space z in metres, +inf = no surface) is the real
    world's depth the virtual objects are occluded against; None means nothing real occludes them.
    """

    def render(self, camera: Camera, *, time_s: float = 0.0,
               real_depth_m: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]: ...


class AgentsView:
    """The built-in :class:`VirtualViewSource`: the content's agents, ray cast and Lambertian-lit by its
    lighting, black wherever no agent is hit (only ``(1 − d) ⊙ v`` enters the MR image)."""

    def __init__(self, content: MRContent) -> None:
        self.content = content

    def render(self, camera: Camera, *, time_s: float = 0.0,
               real_depth_m: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(v_t, d_t) at ``camera`` and round time ``time_s``; see :class:`VirtualViewSource`."""
        return self.occlude(camera, self.cast(camera, time_s=time_s), real_depth_m)

    def cast(self, camera: Camera, *, time_s: float = 0.0) -> tuple[np.ndarray, np.ndarray] | None:
        """The agents alone at ``camera`` and ``time_s``: (rgb H×W×3 float32, depth H×W float32 in metres, +inf on
        a miss), or None when no agent exists then. Needs no real depth, so it can run while the GS render does (its
        ray-cast kernel releases the GIL)."""
        shapes = agents_at(self.content, float(time_s))
        return render_shapes(camera, shapes, self.content.lighting) if shapes else None

    @staticmethod
    def occlude(camera: Camera, cast: tuple[np.ndarray, np.ndarray] | None,
                real_depth_m: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """(v_t, d_t) from a :meth:`cast` and the real depth (None = no real surface); see :meth:`render`."""
        if real_depth_m is None:
            real_depth_m = np.full((camera.height, camera.width), np.inf, np.float32)
        if real_depth_m.shape != (camera.height, camera.width):
            raise ValueError(f"real depth is {real_depth_m.shape}, camera is {camera.height}×{camera.width}")
        if cast is None:
            return (np.zeros((camera.height, camera.width, 3), np.float32),
                    np.ones((camera.height, camera.width), np.float32))
        rgb, depth = cast
        mask = compose_mask(depth, real_depth_m)
        v = np.where(mask[..., None] < 0.5, rgb, 0.0).astype(np.float32)
        return v, mask
