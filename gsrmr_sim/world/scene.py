"""Scene files of the simulated world: YAML schema, defaults, validation and the state at a time (pure, no ROS).

Keys and defaults: docs/world.md, "Scene files"; frames, units and colours: docs/world.md, "Conventions". Angles
are degrees in the YAML (keys end in ``_deg``) and radians in the dataclasses (``_rad``). Unknown keys and bad
values raise :class:`SceneError`, its message starting with the key path.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, fields, replace
import hashlib
import math
from pathlib import Path
from typing import Any

import yaml

from gsrmr_common.camera import CameraMount, Intrinsics
from gsrmr_common.config_files import REPO_CONFIG_DIR, config_dirs, resolve_config
from gsrmr_shapes.spec import TEXTURES, Light, Material, Shape, SpecError
from gsrmr_shapes.spec import fail as _fail
from gsrmr_shapes.spec import listing as _list
from gsrmr_shapes.spec import mapping as _mapping
from gsrmr_shapes.spec import number as _num
from gsrmr_shapes.spec import parse_light as _light
from gsrmr_shapes.spec import parse_material as _material
from gsrmr_shapes.spec import parse_shape as _shape
from gsrmr_shapes.spec import parse_waypoints as _waypoints
from gsrmr_shapes.spec import string as _str
from gsrmr_shapes.spec import unique as _unique
from gsrmr_shapes.spec import vector as _vec
from gsrmr_sim.limo.odometry_errors import OdometryErrors
from gsrmr_sim.world.events import Event, WorldState, change_times_s, world_state

EVENT_TYPES = ("move", "add", "remove", "light", "region_light", "walker", "flicker")
__all__ = ["TEXTURES", "CameraSpec", "Event", "Light", "Material", "PointsWorld", "Room", "Route",
           "Scene", "SceneError", "Shape", "WorldState", "load_scene", "parse_scene", "resolve_scene_path",
           "scene_dirs"]


SceneError = SpecError  # a scene file's entry is invalid; the message starts with the key path


# ----------------------------------------------------------------------------------------------
# dataclasses


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

    ``p_map = scale · R(up→+z, yaw) · (p_file − origin) + (0, 0, height_m)``; ``origin`` defaults to 0, ``up`` to
    the mean camera up of the file's ``viewmats`` (else +z).
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
    mr_content: str = ""  # the MR content (gsrmr_server.mr) composited in this scene: name or path
    events: tuple[Event, ...] = ()
    server_position_m: tuple[float, float, float] = (10.0, 0.0, 1.0)
    points: PointsWorld | None = None
    source: str = ""
    model_iterations: int | None = None  # GS training of the live model: a fixed step count (deterministic) …
    model_train_seconds: float | None = None  # … or a wall-time budget (s); neither: 2000 steps
    model_train_width_px: int | None = None  # training resolution (None: 160 px)
    model_budget: int | None = None  # max Gaussians (None: 100k)
    model_init_points: int | None = None  # Gaussians initialised from round-1 depth (None: the trainer's 30k)
    odometry: OdometryErrors = field(default_factory=OdometryErrors)  # what the LIMO's odometry gets wrong

    def state_at(self, round_index: int, t_s: float) -> WorldState:
        """Objects, lights and illumination regions of the real world at round time ``t_s``."""
        return world_state(self.objects, self.lights, self.ambient, self.events, round_index, t_s)

    def change_times_s(self, scored_round: int = 1) -> list[float]:
        """Sorted times at which scored round ``scored_round``'s world changes (event starts and ends)."""
        return change_times_s(self.events, scored_round)


# ----------------------------------------------------------------------------------------------
# validation helpers


def _camera(value: Any, path: str) -> CameraSpec:
    m = _mapping(value or {}, path, {"width", "height", "hfov_deg", "rate_hz", "mount"})
    width = int(_num(m.get("width", 320), f"{path}.width", lo=8, hi=4096, integer=True))
    height = int(_num(m.get("height", 240), f"{path}.height", lo=8, hi=4096, integer=True))
    hfov = _num(m.get("hfov_deg", 70.0), f"{path}.hfov_deg", lo=10.0, hi=170.0)
    rate = _num(m.get("rate_hz", 10.0), f"{path}.rate_hz", positive=True, hi=1000.0)
    mm = _mapping(m.get("mount") or {}, f"{path}.mount",
                  {"height_m", "pitch_deg", "forward_m", "left_m", "roll_deg", "yaw_deg"})
    mount = CameraMount(
        height_m=_num(mm.get("height_m", 0.15), f"{path}.mount.height_m"),
        pitch_rad=math.radians(_num(mm.get("pitch_deg", 5.0), f"{path}.mount.pitch_deg", lo=-80, hi=80)),
        forward_m=_num(mm.get("forward_m", 0.1), f"{path}.mount.forward_m"),
        left_m=_num(mm.get("left_m", 0.0), f"{path}.mount.left_m"),
        roll_rad=math.radians(_num(mm.get("roll_deg", 0.0), f"{path}.mount.roll_deg", lo=-180, hi=180)),
        yaw_rad=math.radians(_num(mm.get("yaw_deg", 0.0), f"{path}.mount.yaw_deg", lo=-180, hi=180)),
    )
    return CameraSpec(Intrinsics.from_fov(width, height, math.radians(hfov)), mount, rate)


def _event(value: Any, path: str, objects: dict[str, Shape], lights: set[str]) -> Event:
    allowed = {"type", "from_s", "to_s", "from_round", "object", "light", "position", "yaw_deg", "shape",
               "intensity_scale", "color", "region_min", "region_max", "gain", "period_s", "round_shift_s"}
    m = _mapping(value, path, allowed, ("type", "from_s"))
    kind = _str(m["type"], f"{path}.type", EVENT_TYPES)
    from_s = _num(m["from_s"], f"{path}.from_s", lo=0.0)
    to_s = _num(m["to_s"], f"{path}.to_s") if "to_s" in m else math.inf
    if to_s <= from_s:
        raise _fail(f"{path}.to_s", "must be > from_s")
    from_round = int(_num(m["from_round"], f"{path}.from_round", lo=1, integer=True)) if "from_round" in m else 0
    if from_round and (math.isfinite(to_s) or kind in ("walker", "flicker")):
        raise _fail(f"{path}.from_round", "marks a persistent change: no to_s, and not a walker or a flicker")
    if kind in ("walker", "flicker") and not math.isfinite(to_s):
        raise _fail(f"{path}.to_s", f"is required for a {kind} event (it is transient)")
    ev = Event(type=kind, from_s=from_s, to_s=to_s, from_round=from_round)
    if "round_shift_s" in m:
        shifts = m["round_shift_s"]
        if from_round or not isinstance(shifts, list) or not shifts:
            raise _fail(f"{path}.round_shift_s", "a non-empty list of seconds, for an event of every round (no "
                        "from_round)")
        shifts = tuple(_num(v, f"{path}.round_shift_s[{i}]") for i, v in enumerate(shifts))
        if from_s + min(shifts) < 0:
            raise _fail(f"{path}.round_shift_s", f"shifts the event before the round starts (from_s {from_s:g})")
        ev = replace(ev, round_shift_s=shifts)
    per_type = {"move": {"object", "position", "yaw_deg"}, "add": {"shape"}, "remove": {"object"},
                "light": {"light", "intensity_scale", "color"},
                "region_light": {"region_min", "region_max", "gain"}, "walker": {"shape", "position"},
                "flicker": {"light", "intensity_scale", "period_s"}}
    for key in m:
        if key not in {"type", "from_s", "to_s", "from_round", "round_shift_s"} and key not in per_type[kind]:
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
    elif kind in ("add", "walker"):
        if "shape" not in m:
            raise _fail(f"{path}.shape", f"is required for an {kind} event" if kind == "add" else
                        "is required for a walker event (its position is where the walker starts)")
        ev = replace(ev, shape=_shape(m["shape"], f"{path}.shape", f"added{len(objects)}"))
        if kind == "walker":
            if "position" not in m:
                raise _fail(f"{path}.position", "is required for a walker event (where it ends)")
            ev = replace(ev, position=_vec(m["position"], f"{path}.position", 2))
    elif kind == "flicker":
        target = _str(m.get("light"), f"{path}.light")
        if target not in lights:
            raise _fail(f"{path}.light", f"no light with id {target!r}")
        ev = replace(ev, target=target,
                     intensity_scale=_num(m.get("intensity_scale", 0.2), f"{path}.intensity_scale", lo=0.0),
                     period_s=_num(m.get("period_s", 0.5), f"{path}.period_s", lo=0.05, hi=60.0))
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


ODOMETRY_KEY = "odometry"
_TOP_KEYS = {"name", "camera", "slot_s", "slots", "frames", "ambient", "background", "room", "lights",
             "objects", "mr_content", "route", "events", "server", "points", "model", ODOMETRY_KEY}


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
    mr_content = _str(m.get("mr_content", name), "mr_content")  # the server's virtual world in this scene
    if base_dir is not None and mr_content.endswith((".yaml", ".yml")) and not Path(mr_content).is_absolute():
        mr_content = str((base_dir / mr_content).resolve())

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
    model = _mapping(m.get("model") or {}, "model", {"train_iterations", "train_seconds", "train_width_px",
                                                     "budget", "init_points"})

    def model_int(key: str, lo: int) -> int | None:
        return int(_num(model[key], f"model.{key}", lo=lo, integer=True)) if key in model else None

    model_seconds = _num(model["train_seconds"], "model.train_seconds", positive=True) \
        if "train_seconds" in model else None
    odometry = OdometryErrors()
    if m.get(ODOMETRY_KEY) is not None:
        om = _mapping(m[ODOMETRY_KEY], ODOMETRY_KEY, {f.name for f in fields(OdometryErrors)})
        try:
            odometry = OdometryErrors(**{k: _num(v, f"{ODOMETRY_KEY}.{k}") for k, v in om.items()})
        except ValueError as err:
            raise _fail(ODOMETRY_KEY, str(err)) from err
    return Scene(name=name, camera=camera, route=route, slot_s=slot_s, slots=slots, frames=frames, odometry=odometry,
                 ambient=ambient, background=background, room=room, lights=lights,  # type: ignore[arg-type]
                 objects=objects, mr_content=mr_content, events=events,
                 server_position_m=server_pos, points=points, source=source,  # type: ignore[arg-type]
                 model_iterations=model_int("train_iterations", 1), model_train_seconds=model_seconds,
                 model_train_width_px=model_int("train_width_px", 8), model_budget=model_int("budget", 1),
                 model_init_points=model_int("init_points", 1))


# ----------------------------------------------------------------------------------------------
# finding and loading scene files


REPO_SCENES_DIR = REPO_CONFIG_DIR / "scenes"


def scene_dirs() -> list[Path]:
    """Where scene names are looked up (:func:`gsrmr_common.config_files.config_dirs` for ``scenes``)."""
    return config_dirs("scenes", REPO_SCENES_DIR)


def resolve_scene_path(name_or_path: str) -> Path:
    """A scene file path from a path or a bare name (``sandbox`` → ``…/config/scenes/sandbox.yaml``)."""
    return resolve_config(name_or_path, "scenes", "scene", REPO_SCENES_DIR)


def scene_cache_text(name_or_path: str) -> str:
    """The scene file's text without its top-level ``odometry`` section: what the caches of things made from the
    mapping round (headless laps, models, loss maps) are keyed by. The mapping round keeps true poses, so the
    robot's odometry errors change none of them."""
    out: list[str] = []
    skipping = False
    for line in resolve_scene_path(name_or_path).read_text().splitlines(keepends=True):
        top_level = bool(line.strip()) and not line[0].isspace() and not line.lstrip().startswith("#")
        if top_level:
            skipping = line.startswith(f"{ODOMETRY_KEY}:")
        if not skipping:
            out.append(line)
    return "".join(out)


def scene_digest(name_or_path: str) -> str:
    """The first 12 hex digits of the SHA-256 of :func:`scene_cache_text`: a cache of anything made from the scene
    (headless laps, models) keyed by it is never stale after an edit."""
    return hashlib.sha256(scene_cache_text(name_or_path).encode()).hexdigest()[:12]


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
