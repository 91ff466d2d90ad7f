"""Solids, materials and lights of the simulated world (:mod:`gsrmr_sim.world.scene`) and the server's virtual content
(:mod:`gsrmr_server.mr.content`): their dataclasses and the validation of their YAML entries (:class:`SpecError` names
the key path); :mod:`gsrmr_shapes.raycast` draws them. Frames and units: ``map``, metres; angles in degrees in YAML
(keys ``*_deg``), radians in the dataclasses (``*_rad``); colours linear RGB in [0, 1]. Pure Python, no ROS.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
from typing import Any, Protocol

TEXTURES = ("flat", "checker", "noise", "stripes")
LIGHT_TYPES = ("directional", "point")
SHAPES = ("box", "cylinder")


class SpecError(ValueError):
    """An invalid YAML entry; the message starts with the key path."""


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



# ----------------------------------------------------------------------------------------------
# validation helpers (public: the scene and the MR content parsers share them)


def fail(path: str, msg: str) -> SpecError:
    """A :class:`SpecError` for the entry at ``path``."""
    return SpecError(f"{path}: {msg}")


def mapping(value: Any, path: str, allowed: set[str], required: tuple[str, ...] = ()) -> dict:
    """``value`` as a mapping with only ``allowed`` keys and every ``required`` one."""
    if not isinstance(value, dict):
        raise fail(path, "must be a mapping")
    for key in value:
        if key not in allowed:
            raise fail(f"{path}.{key}" if path else str(key),
                        f"unknown key (allowed: {', '.join(sorted(allowed))})")
    for key in required:
        if key not in value:
            raise fail(f"{path}.{key}" if path else key, "is required")
    return value


def number(value: Any, path: str, *, lo: float | None = None, hi: float | None = None,
         positive: bool = False, integer: bool = False) -> float:
    """``value`` as a finite float within the given bounds."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise fail(path, "must be a finite number")
    if integer and int(value) != value:
        raise fail(path, "must be an integer")
    if positive and value <= 0:
        raise fail(path, "must be > 0")
    if lo is not None and value < lo:
        raise fail(path, f"must be ≥ {lo}")
    if hi is not None and value > hi:
        raise fail(path, f"must be ≤ {hi}")
    return float(value)


def vector(value: Any, path: str, n: int, *, positive: bool = False, unit: bool = False) -> tuple[float, ...]:
    """``value`` as ``n`` finite floats (all > 0 if ``positive``, in [0, 1] if ``unit``)."""
    what = f"{n} {'positive ' if positive else ''}numbers{' in [0, 1]' if unit else ''}"
    if not isinstance(value, list | tuple) or len(value) != n:
        raise fail(path, f"must be {what}")
    out = []
    for v in value:
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise fail(path, f"must be {what}")
        if (positive and v <= 0) or (unit and not 0.0 <= v <= 1.0):
            raise fail(path, f"must be {what}")
        out.append(float(v))
    return tuple(out)


def string(value: Any, path: str, choices: tuple[str, ...] | None = None) -> str:
    """``value`` as a non-empty string (one of ``choices`` if given)."""
    if not isinstance(value, str) or not value:
        raise fail(path, "must be a non-empty string")
    if choices is not None and value not in choices:
        raise fail(path, f"must be one of {', '.join(choices)}")
    return value


def listing(value: Any, path: str) -> list:
    """``value`` as a list."""
    if not isinstance(value, list):
        raise fail(path, "must be a list")
    return value


def parse_material(value: Any, path: str, default: Material) -> Material:
    """A :class:`Material` entry (``default`` where absent); ``color2`` defaults to 0.6 × ``color``."""
    if value is None:
        return default
    m = mapping(value, path, {"texture", "color", "color2", "scale_m"})
    color = vector(m["color"], f"{path}.color", 3, unit=True) if "color" in m else default.color
    color2 = vector(m["color2"], f"{path}.color2", 3, unit=True) if "color2" in m else \
        tuple(0.6 * c for c in color)
    return Material(
        texture=string(m.get("texture", default.texture), f"{path}.texture", TEXTURES),
        color=color,  # type: ignore[arg-type]
        color2=color2,  # type: ignore[arg-type]
        scale_m=number(m.get("scale_m", default.scale_m), f"{path}.scale_m", positive=True),
    )


SHAPE_KEYS = {"id", "shape", "position", "size", "yaw_deg", "base_z_m", "radius_m", "height_m", "material"}


def parse_shape(value: Any, path: str, default_id: str) -> Shape:
    """A box or cylinder entry (keys :data:`SHAPE_KEYS`; ``yaw_deg`` in degrees)."""
    m = mapping(value, path, SHAPE_KEYS, ("position",))
    kind = string(m.get("shape", "box"), f"{path}.shape", SHAPES)
    if kind == "box":
        if "radius_m" in m or "height_m" in m:
            raise fail(f"{path}.radius_m" if "radius_m" in m else f"{path}.height_m",
                        "not allowed for a box (use size)")
        size = vector(m.get("size", [0.3, 0.3, 0.3]), f"{path}.size", 3, positive=True)
        radius = 0.0
    else:
        if "size" in m:
            raise fail(f"{path}.size", "not allowed for a cylinder (use radius_m and height_m)")
        radius = number(m.get("radius_m", 0.1), f"{path}.radius_m", positive=True)
        height = number(m.get("height_m", 0.5), f"{path}.height_m", positive=True)
        size = (2 * radius, 2 * radius, height)
    return Shape(
        id=string(m.get("id", default_id), f"{path}.id"),
        shape=kind,
        position=vector(m["position"], f"{path}.position", 2),  # type: ignore[arg-type]
        size=size,  # type: ignore[arg-type]
        yaw_rad=math.radians(number(m.get("yaw_deg", 0.0), f"{path}.yaw_deg")),
        base_z_m=number(m.get("base_z_m", 0.0), f"{path}.base_z_m"),
        radius_m=radius,
        material=parse_material(m.get("material"), f"{path}.material", Material("checker", (0.7, 0.3, 0.2),
                                                                           (0.5, 0.2, 0.15), 0.08)),
    )


def parse_waypoints(value: Any, path: str, min_n: int) -> tuple[tuple[float, float], ...]:
    """At least ``min_n`` (x, y) points in metres."""
    pts = listing(value, path)
    if len(pts) < min_n:
        raise fail(path, f"needs at least {min_n} waypoints")
    return tuple(vector(p, f"{path}[{i}]", 2) for i, p in enumerate(pts))  # type: ignore[misc]


def parse_light(value: Any, path: str, index: int) -> Light:
    """A directional (``direction``, normalised) or point (``position``) light."""
    m = mapping(value, path, {"id", "type", "direction", "position", "color", "intensity", "range_m",
                               "shadows"}, ("type",))
    kind = string(m["type"], f"{path}.type", LIGHT_TYPES)
    key = "direction" if kind == "directional" else "position"
    if key not in m:
        raise fail(f"{path}.{key}", f"is required for a {kind} light")
    other = "position" if kind == "directional" else "direction"
    if other in m:
        raise fail(f"{path}.{other}", f"not allowed for a {kind} light")
    vec = vector(m[key], f"{path}.{key}", 3)
    if kind == "directional":
        norm = math.sqrt(sum(v * v for v in vec))
        if norm == 0:
            raise fail(f"{path}.direction", "must be a non-zero vector")
        vec = tuple(v / norm for v in vec)
    shadows = m.get("shadows", False)
    if not isinstance(shadows, bool):
        raise fail(f"{path}.shadows", "must be true or false")
    return Light(
        id=string(m.get("id", f"light{index}"), f"{path}.id"), type=kind, vector=vec,  # type: ignore[arg-type]
        color=vector(m.get("color", [1, 1, 1]), f"{path}.color", 3, unit=True),  # type: ignore[arg-type]
        intensity=number(m.get("intensity", 0.6), f"{path}.intensity", lo=0.0),
        range_m=number(m.get("range_m", 2.0), f"{path}.range_m", positive=True),
        shadows=shadows,
    )


def unique(ids: list[str], path: str) -> None:
    """Refuse a repeated id (the message names the second occurrence)."""
    seen: set[str] = set()
    for i, ident in enumerate(ids):
        if ident in seen:
            raise fail(f"{path}[{i}].id", f"duplicate id {ident!r}")
        seen.add(ident)


class Lighting(Protocol):
    """What lights a ray-cast render: lights, illumination regions (min xyz, max xyz, rgb gain) and the
    ambient level. The simulator's ``WorldState`` and the MR content's lighting both provide it."""

    @property
    def lights(self) -> tuple[Light, ...]: ...

    @property
    def regions(self) -> tuple[tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, ...]], ...]:
        ...

    @property
    def ambient(self) -> float: ...


@dataclass(frozen=True)
class StaticLighting:
    """Fixed lighting (no illumination regions): the virtual world's."""

    lights: tuple[Light, ...] = ()
    ambient: float = 0.4
    regions: tuple = ()
