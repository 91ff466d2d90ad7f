"""Round-2 change events and the real world's state at a time.

Events are what makes the operating round differ from the mapping round (the paper's GS
discrepancies): an object moved, added or removed; a light's intensity/colour changed (or the
ambient level, target ``ambient``); surfaces inside an axis-aligned region brightened or tinted.
Each is active for ``from_s ≤ t < to_s`` (round seconds; ``to_s`` = inf: until the end). Round 1
never applies events. Validation of event entries lives with the rest of the scene schema in
:mod:`gsrmr_sim.world.scene`. Pure Python, no ROS.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
import math
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from gsrmr_shapes.spec import Light, Shape


@dataclass(frozen=True)
class Event:
    """A round-2 change. ``from_s``/``to_s``: active span (to_s = inf: until the end of the round).

    * move: ``target`` object goes to ``position`` (and ``yaw_rad`` if given).
    * add: ``shape`` appears. * remove: ``target`` disappears.
    * light: ``target`` light gets ``intensity_scale`` and ``color`` (if given).
    * region_light: surfaces inside the axis-aligned box ``region_min``..``region_max`` get ``gain``.
    """

    type: str
    from_s: float
    to_s: float = math.inf
    target: str = ""
    position: tuple[float, float] | None = None
    yaw_rad: float | None = None
    shape: Shape | None = None
    intensity_scale: float = 1.0
    color: tuple[float, float, float] | None = None
    region_min: tuple[float, float, float] = (0.0, 0.0, 0.0)
    region_max: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gain: tuple[float, float, float] = (1.0, 1.0, 1.0)

    def active(self, t_s: float) -> bool:
        """True while the event applies (from_s ≤ t < to_s)."""
        return self.from_s <= t_s < self.to_s


@dataclass(frozen=True)
class WorldState:
    """What the real camera sees at one time: solids, lights, illumination regions, ambient level."""

    objects: tuple[Shape, ...]
    lights: tuple[Light, ...]
    regions: tuple[tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, ...]], ...]
    ambient: float


def world_state(objects: tuple[Shape, ...], lights: tuple[Light, ...], ambient: float,
                events: tuple[Event, ...], round_index: int, t_s: float) -> WorldState:
    """The real world at round time ``t_s``: the static scene with every active event applied in order."""
    objs = {o.id: o for o in objects}
    lts = {lt.id: lt for lt in lights}
    regions: list[tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, ...]]] = []
    global_gain = 1.0
    if round_index >= 2:
        for ev in events:
            if not ev.active(t_s):
                continue
            if ev.type == "move":
                if ev.target not in objs:  # removed by an earlier event
                    continue
                obj = objs[ev.target]
                yaw = obj.yaw_rad if ev.yaw_rad is None else ev.yaw_rad
                objs[ev.target] = replace(obj, position=ev.position or obj.position, yaw_rad=yaw)
            elif ev.type == "add" and ev.shape is not None:
                objs[ev.shape.id] = ev.shape
            elif ev.type == "remove":
                objs.pop(ev.target, None)
            elif ev.type == "light":
                if ev.target == "ambient":
                    global_gain *= ev.intensity_scale
                    continue
                lt = lts[ev.target]
                lts[ev.target] = replace(lt, intensity=lt.intensity * ev.intensity_scale, color=ev.color or lt.color)
            elif ev.type == "region_light":
                regions.append((ev.region_min, ev.region_max, ev.gain))
    return WorldState(tuple(objs.values()), tuple(lts.values()), tuple(regions), ambient * global_gain)


def change_times_s(events: tuple[Event, ...]) -> list[float]:
    """Sorted times at which the round-2 world changes (event starts and finite ends)."""
    times = {ev.from_s for ev in events} | {ev.to_s for ev in events if math.isfinite(ev.to_s)}
    return sorted(times)
