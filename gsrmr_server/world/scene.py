"""Scene files of the simulated world: YAML schema, defaults, validation and the state at a time.

A scene declares only what it has; everything else takes the defaults documented in
``docs/world.md``. Unknown keys and bad values raise :class:`SceneError` whose message starts with
the key path, e.g. ``objects[2].size: must be 3 positive numbers``.

Frames and units: the world is the ROS ``map`` frame (x forward, y left, z up, metres; REP-103).
Angles in the YAML are in degrees (keys end in ``_deg``) and radians in the dataclasses (``_rad``).
Colours are linear RGB in [0, 1]. Times (``*_s``) are seconds since the start of a round.

Round 1 (mapping) never applies ``events``; round 2 (operating) applies every event whose time span
contains the round time. Pure Python, no ROS.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
import math
from pathlib import Path
import sys
from typing import Any

import yaml

from gsrmr_common.camera import CameraMount, Intrinsics
from gsrmr_server.world.events import Event, WorldState, change_times_s, world_state

TEXTURES = ("flat", "checker", "noise", "stripes")
LIGHT_TYPES = ("directional", "point")
SHAPES = ("box", "cylinder")
EVENT_TYPES = ("move", "add", "remove", "light", "region_light")
__all__ = ["Agent", "AgentPath", "CameraSpec", "Event", "Light", "Material", "PointsWorld", "Room", "Route",
           "Scene", "SceneError", "Shape", "WorldState", "load_scene", "parse_scene", "resolve_scene_path",
           "scene_dirs"]


class SceneError(ValueError):
    """A scene file is invalid; the message starts with the offending key path."""


# ----------------------------------------------------------------------------------------------
# dataclasses


@dataclass(frozen=True)
class Material:
    """Lambertian, view-independent surface: a 2-colour procedural texture at ``scale_m`` metres."""

    texture: str = "flat"
    color: tuple[float, float, float] = (0.6, 0.6, 0.6)
    color2: tuple[float, float, float] = (0.4, 0.4, 0.4)
    scale_m: float = 0.1


@dataclass(frozen=True)
class Shape:
    """A solid: an oriented box (yaw about +z) or an upright cylinder, in the map frame (metres).

    ``position`` is (x, y) of the centre of the footprint, ``base_z_m`` the height of its bottom.
    Boxes use ``size`` (x, y, z extents before yaw); cylinders use ``radius_m`` and ``size[2]``
    as the height.
    """

    id: str
    shape: str
    position: tuple[float, float]
    size: tuple[float, float, float]
    yaw_rad: float = 0.0
    base_z_m: float = 0.0
    radius_m: float = 0.0
    material: Material = field(default_factory=Material)


@dataclass(frozen=True)
class Light:
    """Directional light (``vector`` = direction the light travels) or point light (``vector`` = position).

    Irradiance of a point light falls off as 1 / (1 + (d / range_m)²).
    """

    id: str
    type: str
    vector: tuple[float, float, float]
    color: tuple[float, float, float] = (1.0, 1.0, 1.0)
    intensity: float = 0.6
    range_m: float = 2.0
    shadows: bool = False


@dataclass(frozen=True)
class AgentPath:
    """A virtual agent's motion: constant speed along waypoints (closed loop when ``loop``)."""

    waypoints: tuple[tuple[float, float], ...]
    speed_mps: float
    loop: bool = True


@dataclass(frozen=True)
class Agent:
    """A virtual agent: a shape that exists only in the virtual world (static if ``path`` is None)."""

    body: Shape
    path: AgentPath | None = None


@dataclass(frozen=True)
class Route:
    """The robot's loop: waypoints (map frame, metres), nominal speed and pure-pursuit look-ahead."""

    waypoints: tuple[tuple[float, float], ...]
    speed_mps: float = 0.3
    lookahead_m: float = 0.35
    max_omega_rps: float = 1.5
    start_jitter_m: float = 0.0


@dataclass(frozen=True)
class Room:
    """The lab around the arena: an axis-aligned box seen from inside (floor, walls, ceiling)."""

    min_m: tuple[float, float, float] = (-5.0, -5.0, 0.0)
    max_m: tuple[float, float, float] = (5.0, 5.0, 3.0)
    floor: Material = Material("checker", (0.55, 0.55, 0.5), (0.35, 0.35, 0.32), 0.25)
    walls: Material = Material("noise", (0.75, 0.72, 0.65), (0.55, 0.52, 0.48), 0.3)
    ceiling: Material = Material("flat", (0.85, 0.85, 0.85), (0.85, 0.85, 0.85), 1.0)


@dataclass(frozen=True)
class PointsWorld:
    """The 'real' world as coloured points (e.g. the garden), mapped into the map frame.

    ``p_map = scale · R(up→+z, yaw) · (p_file − origin)``; ``origin``/``up`` default to the mean
    camera centre and mean camera up of the file's ``viewmats`` lifted by ``height_m``.
    """

    path: str
    scale: float = 1.0
    yaw_rad: float = 0.0
    origin: tuple[float, float, float] | None = None
    up: tuple[float, float, float] | None = None
    height_m: float = 0.0
    point_size_m: float = 0.02
    max_radius_px: int = 3
    fill_passes: int = 2


@dataclass(frozen=True)
class CameraSpec:
    """Camera intrinsics, mount on the robot and frame rate."""

    intrinsics: Intrinsics
    mount: CameraMount
    rate_hz: float = 10.0


@dataclass(frozen=True)
class Scene:
    """A validated scene. See the module docstring for frames and units."""

    name: str
    camera: CameraSpec
    route: Route
    slot_s: float = 0.1
    slots: int = 288
    frames: int = 144
    ambient: float = 0.4
    background: tuple[float, float, float] = (0.5, 0.55, 0.6)
    room: Room | None = field(default_factory=Room)
    lights: tuple[Light, ...] = ()
    objects: tuple[Shape, ...] = ()
    agents: tuple[Agent, ...] = ()
    events: tuple[Event, ...] = ()
    server_position_m: tuple[float, float, float] = (10.0, 0.0, 1.0)
    points: PointsWorld | None = None
    source: str = ""

    def state_at(self, round_index: int, t_s: float) -> WorldState:
        """Objects, lights and illumination regions of the real world at round time ``t_s``."""
        return world_state(self.objects, self.lights, self.ambient, self.events, round_index, t_s)

    def change_times_s(self) -> list[float]:
        """Sorted times at which the round-2 world changes (event starts and ends)."""
        return change_times_s(self.events)


# ----------------------------------------------------------------------------------------------
# validation helpers


def _fail(path: str, msg: str) -> SceneError:
    return SceneError(f"{path}: {msg}")


def _mapping(value: Any, path: str, allowed: set[str], required: tuple[str, ...] = ()) -> dict:
    if not isinstance(value, dict):
        raise _fail(path, "must be a mapping")
    for key in value:
        if key not in allowed:
            raise _fail(f"{path}.{key}" if path else str(key),
                        f"unknown key (allowed: {', '.join(sorted(allowed))})")
    for key in required:
        if key not in value:
            raise _fail(f"{path}.{key}" if path else key, "is required")
    return value


def _num(value: Any, path: str, *, lo: float | None = None, hi: float | None = None,
         positive: bool = False, integer: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise _fail(path, "must be a finite number")
    if integer and int(value) != value:
        raise _fail(path, "must be an integer")
    if positive and value <= 0:
        raise _fail(path, "must be > 0")
    if lo is not None and value < lo:
        raise _fail(path, f"must be ≥ {lo}")
    if hi is not None and value > hi:
        raise _fail(path, f"must be ≤ {hi}")
    return float(value)


def _vec(value: Any, path: str, n: int, *, positive: bool = False, unit: bool = False) -> tuple[float, ...]:
    what = f"{n} {'positive ' if positive else ''}numbers{' in [0, 1]' if unit else ''}"
    if not isinstance(value, list | tuple) or len(value) != n:
        raise _fail(path, f"must be {what}")
    out = []
    for v in value:
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise _fail(path, f"must be {what}")
        if (positive and v <= 0) or (unit and not 0.0 <= v <= 1.0):
            raise _fail(path, f"must be {what}")
        out.append(float(v))
    return tuple(out)


def _str(value: Any, path: str, choices: tuple[str, ...] | None = None) -> str:
    if not isinstance(value, str) or not value:
        raise _fail(path, "must be a non-empty string")
    if choices is not None and value not in choices:
        raise _fail(path, f"must be one of {', '.join(choices)}")
    return value


def _list(value: Any, path: str) -> list:
    if not isinstance(value, list):
        raise _fail(path, "must be a list")
    return value


def _material(value: Any, path: str, default: Material) -> Material:
    if value is None:
        return default
    m = _mapping(value, path, {"texture", "color", "color2", "scale_m"})
    color = _vec(m["color"], f"{path}.color", 3, unit=True) if "color" in m else default.color
    color2 = _vec(m["color2"], f"{path}.color2", 3, unit=True) if "color2" in m else \
        tuple(0.6 * c for c in color)
    return Material(
        texture=_str(m.get("texture", default.texture), f"{path}.texture", TEXTURES),
        color=color,  # type: ignore[arg-type]
        color2=color2,  # type: ignore[arg-type]
        scale_m=_num(m.get("scale_m", default.scale_m), f"{path}.scale_m", positive=True),
    )


_SHAPE_KEYS = {"id", "shape", "position", "size", "yaw_deg", "base_z_m", "radius_m", "height_m", "material"}


def _shape(value: Any, path: str, default_id: str) -> Shape:
    m = _mapping(value, path, _SHAPE_KEYS, ("position",))
    kind = _str(m.get("shape", "box"), f"{path}.shape", SHAPES)
    if kind == "box":
        if "radius_m" in m or "height_m" in m:
            raise _fail(f"{path}.radius_m" if "radius_m" in m else f"{path}.height_m",
                        "not allowed for a box (use size)")
        size = _vec(m.get("size", [0.3, 0.3, 0.3]), f"{path}.size", 3, positive=True)
        radius = 0.0
    else:
        if "size" in m:
            raise _fail(f"{path}.size", "not allowed for a cylinder (use radius_m and height_m)")
        radius = _num(m.get("radius_m", 0.1), f"{path}.radius_m", positive=True)
        height = _num(m.get("height_m", 0.5), f"{path}.height_m", positive=True)
        size = (2 * radius, 2 * radius, height)
    return Shape(
        id=_str(m.get("id", default_id), f"{path}.id"),
        shape=kind,
        position=_vec(m["position"], f"{path}.position", 2),  # type: ignore[arg-type]
        size=size,  # type: ignore[arg-type]
        yaw_rad=math.radians(_num(m.get("yaw_deg", 0.0), f"{path}.yaw_deg")),
        base_z_m=_num(m.get("base_z_m", 0.0), f"{path}.base_z_m"),
        radius_m=radius,
        material=_material(m.get("material"), f"{path}.material", Material("checker", (0.7, 0.3, 0.2),
                                                                           (0.5, 0.2, 0.15), 0.08)),
    )


def _waypoints(value: Any, path: str, min_n: int) -> tuple[tuple[float, float], ...]:
    pts = _list(value, path)
    if len(pts) < min_n:
        raise _fail(path, f"needs at least {min_n} waypoints")
    return tuple(_vec(p, f"{path}[{i}]", 2) for i, p in enumerate(pts))  # type: ignore[misc]


def _camera(value: Any, path: str) -> CameraSpec:
    m = _mapping(value or {}, path, {"width", "height", "hfov_deg", "rate_hz", "mount"})
    width = int(_num(m.get("width", 320), f"{path}.width", lo=8, hi=4096, integer=True))
    height = int(_num(m.get("height", 240), f"{path}.height", lo=8, hi=4096, integer=True))
    hfov = _num(m.get("hfov_deg", 70.0), f"{path}.hfov_deg", lo=10.0, hi=170.0)
    rate = _num(m.get("rate_hz", 10.0), f"{path}.rate_hz", positive=True, hi=1000.0)
    mm = _mapping(m.get("mount") or {}, f"{path}.mount", {"height_m", "pitch_deg", "forward_m", "left_m"})
    mount = CameraMount(
        height_m=_num(mm.get("height_m", 0.15), f"{path}.mount.height_m"),
        pitch_rad=math.radians(_num(mm.get("pitch_deg", 5.0), f"{path}.mount.pitch_deg", lo=-80, hi=80)),
        forward_m=_num(mm.get("forward_m", 0.1), f"{path}.mount.forward_m"),
        left_m=_num(mm.get("left_m", 0.0), f"{path}.mount.left_m"),
    )
    return CameraSpec(Intrinsics.from_fov(width, height, math.radians(hfov)), mount, rate)


def _light(value: Any, path: str, index: int) -> Light:
    m = _mapping(value, path, {"id", "type", "direction", "position", "color", "intensity", "range_m",
                               "shadows"}, ("type",))
    kind = _str(m["type"], f"{path}.type", LIGHT_TYPES)
    key = "direction" if kind == "directional" else "position"
    if key not in m:
        raise _fail(f"{path}.{key}", f"is required for a {kind} light")
    other = "position" if kind == "directional" else "direction"
    if other in m:
        raise _fail(f"{path}.{other}", f"not allowed for a {kind} light")
    vec = _vec(m[key], f"{path}.{key}", 3)
    if kind == "directional":
        norm = math.sqrt(sum(v * v for v in vec))
        if norm == 0:
            raise _fail(f"{path}.direction", "must be a non-zero vector")
        vec = tuple(v / norm for v in vec)
    shadows = m.get("shadows", False)
    if not isinstance(shadows, bool):
        raise _fail(f"{path}.shadows", "must be true or false")
    return Light(
        id=_str(m.get("id", f"light{index}"), f"{path}.id"), type=kind, vector=vec,  # type: ignore[arg-type]
        color=_vec(m.get("color", [1, 1, 1]), f"{path}.color", 3, unit=True),  # type: ignore[arg-type]
        intensity=_num(m.get("intensity", 0.6), f"{path}.intensity", lo=0.0),
        range_m=_num(m.get("range_m", 2.0), f"{path}.range_m", positive=True),
        shadows=shadows,
    )


def _agent(value: Any, path: str, index: int) -> Agent:
    body = _shape({k: v for k, v in value.items() if k != "path"} if isinstance(value, dict) else value,
                  path, f"agent{index}")
    if isinstance(value, dict) and "material" not in value:
        body = replace(body, material=Material("stripes", (0.2, 0.4, 0.9), (0.9, 0.9, 0.95), 0.1))
    p = value.get("path")
    agent_path = None
    if p is not None:
        pm = _mapping(p, f"{path}.path", {"waypoints", "speed_mps", "loop"}, ("waypoints",))
        loop = pm.get("loop", True)
        if not isinstance(loop, bool):
            raise _fail(f"{path}.path.loop", "must be true or false")
        agent_path = AgentPath(_waypoints(pm["waypoints"], f"{path}.path.waypoints", 2),
                               _num(pm.get("speed_mps", 0.3), f"{path}.path.speed_mps", positive=True), loop)
    return Agent(body, agent_path)


def _event(value: Any, path: str, objects: dict[str, Shape], lights: set[str]) -> Event:
    allowed = {"type", "from_s", "to_s", "object", "light", "position", "yaw_deg", "shape",
               "intensity_scale", "color", "region_min", "region_max", "gain"}
    m = _mapping(value, path, allowed, ("type", "from_s"))
    kind = _str(m["type"], f"{path}.type", EVENT_TYPES)
    from_s = _num(m["from_s"], f"{path}.from_s", lo=0.0)
    to_s = _num(m["to_s"], f"{path}.to_s") if "to_s" in m else math.inf
    if to_s <= from_s:
        raise _fail(f"{path}.to_s", "must be > from_s")
    ev = Event(type=kind, from_s=from_s, to_s=to_s)
    per_type = {"move": {"object", "position", "yaw_deg"}, "add": {"shape"}, "remove": {"object"},
                "light": {"light", "intensity_scale", "color"},
                "region_light": {"region_min", "region_max", "gain"}}
    for key in m:
        if key not in {"type", "from_s", "to_s"} and key not in per_type[kind]:
            raise _fail(f"{path}.{key}", f"not allowed for a {kind} event")
    if kind in ("move", "remove"):
        target = _str(m.get("object"), f"{path}.object")
        if target not in objects:
            raise _fail(f"{path}.object", f"no object with id {target!r}")
        ev = replace(ev, target=target)
        if kind == "move":
            if "position" not in m and "yaw_deg" not in m:
                raise _fail(f"{path}.position", "a move needs position and/or yaw_deg")
            ev = replace(ev, position=_vec(m["position"], f"{path}.position", 2) if "position" in m else None,
                         yaw_rad=math.radians(_num(m["yaw_deg"], f"{path}.yaw_deg")) if "yaw_deg" in m
                         else None)
    elif kind == "add":
        if "shape" not in m:
            raise _fail(f"{path}.shape", "is required for an add event")
        ev = replace(ev, shape=_shape(m["shape"], f"{path}.shape", f"added{len(objects)}"))
    elif kind == "light":
        target = _str(m.get("light"), f"{path}.light")
        if target not in lights and target != "ambient":
            raise _fail(f"{path}.light", f"no light with id {target!r} (or 'ambient')")
        ev = replace(ev, target=target,
                     intensity_scale=_num(m.get("intensity_scale", 1.0), f"{path}.intensity_scale", lo=0.0),
                     color=_vec(m["color"], f"{path}.color", 3, unit=True) if "color" in m else None)
    else:
        for key in ("region_min", "region_max"):
            if key not in m:
                raise _fail(f"{path}.{key}", "is required for a region_light event")
        lo = _vec(m["region_min"], f"{path}.region_min", 3)
        hi = _vec(m["region_max"], f"{path}.region_max", 3)
        if any(b <= a for a, b in zip(lo, hi, strict=True)):
            raise _fail(f"{path}.region_max", "must exceed region_min on every axis")
        gain = m.get("gain", 1.5)
        g3 = (float(_num(gain, f"{path}.gain", lo=0.0)),) * 3 if not isinstance(gain, list) else \
            _vec(gain, f"{path}.gain", 3)
        if any(g < 0 for g in g3):
            raise _fail(f"{path}.gain", "must be ≥ 0")
        ev = replace(ev, region_min=lo, region_max=hi, gain=g3)  # type: ignore[arg-type]
    return ev


_TOP_KEYS = {"name", "camera", "slot_s", "slots", "frames", "ambient", "background", "room", "lights",
             "objects", "virtual_agents", "route", "events", "server", "points"}


def parse_scene(data: Any, source: str = "", base_dir: Path | None = None) -> Scene:
    """Validate a scene mapping (as loaded from YAML) and build a :class:`Scene`."""
    m = _mapping(data, "", _TOP_KEYS, ("route",))
    name = _str(m.get("name", Path(source).stem if source else "scene"), "name")
    camera = _camera(m.get("camera"), "camera")
    slot_s = _num(m.get("slot_s", 0.1), "slot_s", positive=True)
    slots = int(_num(m.get("slots", 288), "slots", lo=1, integer=True))
    frames = int(_num(m.get("frames", 144), "frames", lo=1, integer=True))
    ambient = _num(m.get("ambient", 0.4), "ambient", lo=0.0, hi=2.0)
    background = _vec(m.get("background", [0.5, 0.55, 0.6]), "background", 3, unit=True)

    room: Room | None = Room()
    if "room" in m:
        if m["room"] is None:
            room = None
        else:
            rm = _mapping(m["room"], "room", {"min", "max", "floor", "walls", "ceiling"})
            d = Room()
            lo = _vec(rm.get("min", list(d.min_m)), "room.min", 3)
            hi = _vec(rm.get("max", list(d.max_m)), "room.max", 3)
            if any(b <= a for a, b in zip(lo, hi, strict=True)):
                raise _fail("room.max", "must exceed room.min on every axis")
            room = Room(lo, hi, _material(rm.get("floor"), "room.floor", d.floor),  # type: ignore[arg-type]
                        _material(rm.get("walls"), "room.walls", d.walls),
                        _material(rm.get("ceiling"), "room.ceiling", d.ceiling))

    lights = tuple(_light(v, f"lights[{i}]", i) for i, v in enumerate(_list(m.get("lights", []), "lights")))
    _unique([lt.id for lt in lights], "lights")
    objects = tuple(_shape(v, f"objects[{i}]", f"object{i}") for i, v in
                    enumerate(_list(m.get("objects", []), "objects")))
    _unique([o.id for o in objects], "objects")
    agents = tuple(_agent(v, f"virtual_agents[{i}]", i) for i, v in
                   enumerate(_list(m.get("virtual_agents", []), "virtual_agents")))
    _unique([a.body.id for a in agents], "virtual_agents")

    rt = _mapping(m["route"], "route", {"waypoints", "speed_mps", "lookahead_m", "max_omega_rps",
                                        "start_jitter_m"}, ("waypoints",))
    route = Route(_waypoints(rt["waypoints"], "route.waypoints", 3),
                  _num(rt.get("speed_mps", 0.3), "route.speed_mps", positive=True, hi=2.0),
                  _num(rt.get("lookahead_m", 0.35), "route.lookahead_m", positive=True),
                  _num(rt.get("max_omega_rps", 1.5), "route.max_omega_rps", positive=True),
                  _num(rt.get("start_jitter_m", 0.0), "route.start_jitter_m", lo=0.0, hi=0.5))

    obj_map = {o.id: o for o in objects}
    light_ids = {lt.id for lt in lights}
    events = tuple(_event(v, f"events[{i}]", obj_map, light_ids) for i, v in
                   enumerate(_list(m.get("events", []), "events")))

    server = _mapping(m.get("server") or {}, "server", {"position"})
    server_pos = _vec(server.get("position", [10.0, 0.0, 1.0]), "server.position", 3)

    points = None
    if m.get("points") is not None:
        pm = _mapping(m["points"], "points", {"path", "scale", "yaw_deg", "origin", "up", "height_m",
                                              "point_size_m", "max_radius_px", "fill_passes"}, ("path",))
        raw = Path(_str(pm["path"], "points.path"))
        if not raw.is_absolute() and base_dir is not None:
            raw = (base_dir / raw).resolve()
        points = PointsWorld(
            path=str(raw), scale=_num(pm.get("scale", 1.0), "points.scale", positive=True),
            yaw_rad=math.radians(_num(pm.get("yaw_deg", 0.0), "points.yaw_deg")),
            origin=_vec(pm["origin"], "points.origin", 3) if "origin" in pm else None,  # type: ignore[arg-type]
            up=_vec(pm["up"], "points.up", 3) if "up" in pm else None,  # type: ignore[arg-type]
            height_m=_num(pm.get("height_m", 0.0), "points.height_m"),
            point_size_m=_num(pm.get("point_size_m", 0.02), "points.point_size_m", positive=True),
            max_radius_px=int(_num(pm.get("max_radius_px", 3), "points.max_radius_px", lo=0, hi=16,
                                   integer=True)),
            fill_passes=int(_num(pm.get("fill_passes", 2), "points.fill_passes", lo=0, hi=8, integer=True)),
        )
    return Scene(name=name, camera=camera, route=route, slot_s=slot_s, slots=slots, frames=frames,
                 ambient=ambient, background=background, room=room, lights=lights,  # type: ignore[arg-type]
                 objects=objects, agents=agents, events=events,
                 server_position_m=server_pos, points=points, source=source)  # type: ignore[arg-type]


def _unique(ids: list[str], path: str) -> None:
    seen: set[str] = set()
    for i, ident in enumerate(ids):
        if ident in seen:
            raise _fail(f"{path}[{i}].id", f"duplicate id {ident!r}")
        seen.add(ident)


# ----------------------------------------------------------------------------------------------
# finding and loading scene files


REPO_SCENES_DIR = Path(__file__).resolve().parents[2] / "config" / "scenes"


def scene_dirs() -> list[Path]:
    """Where scene names are looked up: ``<repo>/config/scenes``, the ament share dir of ``gsrmr``,
    then ``<sys.prefix>/share/gsrmr/config/scenes`` (where setup.py installs ``config/**/*.yaml``)."""
    dirs = [REPO_SCENES_DIR]
    try:
        from ament_index_python.packages import get_package_share_directory

        dirs.append(Path(get_package_share_directory("gsrmr")) / "config" / "scenes")
    except Exception:  # ament_index not installed, or gsrmr not in an ament prefix
        pass
    dirs.append(Path(sys.prefix) / "share" / "gsrmr" / "config" / "scenes")
    return dirs


def resolve_scene_path(name_or_path: str) -> Path:
    """A scene file path from a path or a bare name (``sandbox`` → ``…/config/scenes/sandbox.yaml``)."""
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml") or p.exists():
        if not p.exists():
            raise FileNotFoundError(f"scene file {p} does not exist")
        return p
    for d in scene_dirs():
        cand = d / f"{name_or_path}.yaml"
        if cand.exists():
            return cand
    raise FileNotFoundError(f"no scene named {name_or_path!r} in {', '.join(str(d) for d in scene_dirs())}")


def load_scene(name_or_path: str, overrides: Callable[[dict], None] | None = None) -> Scene:
    """Load and validate a scene by name or path; ``overrides`` may edit the raw mapping first."""
    path = resolve_scene_path(name_or_path)
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise SceneError(f"{path}: not valid YAML: {exc}") from exc
    if overrides is not None:
        overrides(data)
    try:
        return parse_scene(data, str(path), path.parent)
    except SceneError as exc:
        raise SceneError(f"{path}: {exc}") from exc
