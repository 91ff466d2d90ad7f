"""Change events and the real world's state at a time (pure Python, no ROS).

The event kinds, how rounds are counted, transient events, ``round_shift_s`` and persistent changes
(``from_round``): docs/world.md, "Scene files"; their validation is :mod:`gsrmr_sim.world.scene`'s.
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
    from_round: int = 0  # ≥ 1: a persistent change from that scored round on (module docstring); 0: every round
    period_s: float = 1.0  # flicker: the light's on/off period
    round_shift_s: tuple[float, ...] = ()  # an every-round event's span shifted per scored round (module docstring)

    def span_s(self, scored_round: int = 1) -> tuple[float, float]:
        """(from_s, to_s) of the event in scored round ``scored_round`` (≥ 1): shifted by ``round_shift_s``."""
        if not self.round_shift_s or self.from_round:
            return self.from_s, self.to_s
        shift = self.round_shift_s[(scored_round - 1) % len(self.round_shift_s)]
        return self.from_s + shift, self.to_s + shift

    def active(self, t_s: float, scored_round: int = 1) -> bool:
        """True while the event applies in scored round ``scored_round`` (≥ 1) at round time ``t_s``."""
        if self.from_round and scored_round != self.from_round:
            return scored_round > self.from_round  # before its round: not yet; after it: there all along
        from_s, to_s = self.span_s(scored_round)
        return from_s <= t_s < to_s

    @property
    def persistent(self) -> bool:
        """A change that stays from its round on (``from_round`` set)."""
        return self.from_round > 0


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
            if not ev.active(t_s, round_index - 1):
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
            elif ev.type == "walker" and ev.shape is not None and ev.position is not None:
                from_s, to_s = ev.span_s(round_index - 1)
                done = (t_s - from_s) / (to_s - from_s)  # 0 → 1 over the span (walkers have a to_s)
                (x0, y0), (x1, y1) = ev.shape.position, ev.position
                objs[ev.shape.id] = replace(ev.shape, position=(x0 + done * (x1 - x0), y0 + done * (y1 - y0)))
            elif ev.type == "flicker" and ((t_s - ev.span_s(round_index - 1)[0]) % ev.period_s) < 0.5 * ev.period_s:
                lt = lts[ev.target]
                lts[ev.target] = replace(lt, intensity=lt.intensity * ev.intensity_scale)
    return WorldState(tuple(objs.values()), tuple(lts.values()), tuple(regions), ambient * global_gain)


def change_times_s(events: tuple[Event, ...], scored_round: int = 1) -> list[float]:
    """Sorted times at which scored round ``scored_round``'s world changes (event starts and finite ends; a walker
    moves and a flicker toggles in between)."""
    spans = [ev.span_s(scored_round) for ev in events]
    return sorted({a for a, _ in spans} | {b for _, b in spans if math.isfinite(b)})
