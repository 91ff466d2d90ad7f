"""The online planner's configuration (pure): :class:`PlannerConfig`, every knob of the
:class:`~gsrmr_scheduler.planner.OnlinePlanner`, frozen and validated; its defaults are the plain receding-horizon
planner, every refinement of the live loop off. The node sets each field from its parameters
(:meth:`gsrmr_scheduler.scheduler_params.SchedulerParameters.planner_config`; the values and why: docs/scheduling.md,
"The live loop"); a running planner takes a change of the :data:`LIVE_FIELDS` only.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields
import math
from types import MappingProxyType
from typing import Any

from gsrmr_common.link_model import IMAGE_BITS, KEY_BITS, SLOT_S
from gsrmr_scheduler.solve import METHODS

# Fields a running planner may change (OnlinePlanner.reconfigure): they enter the next plan only.
LIVE_FIELDS = frozenset({"loss_threshold", "horizon_slots", "method", "solver_options", "image_bits", "pose_bits",
                         "drift_threshold", "drift_window_samples", "loss_margin"})


@dataclass(frozen=True)
class PlannerConfig:
    """The planner's knobs: losses are MR losses, the scale of ``loss_threshold``; τ = ``slot_s`` in seconds, the
    payloads in bits, ``round_start_m`` in metres."""

    loss_threshold: float  # L_th: the mean MR loss per slot the plan must meet
    horizon_slots: int  # H: slots per plan
    slot_s: float = SLOT_S  # τ
    image_bits: float = IMAGE_BITS  # I, the image the plan assumes
    pose_bits: float = KEY_BITS  # S, the pose key
    method: str = "exact"  # gsrmr_scheduler.solve method
    solver_options: Mapping[str, Any] = field(default_factory=dict)  # keyword arguments of the solver
    drift_threshold: float = 0.02  # replan when the mean |measured − predicted| L exceeds this …
    drift_window_samples: int = 5  # … over this many measured slots
    loss_margin: float = 0.0  # plan for L_th·(1 − loss_margin): a fixed back-off
    oracle_channel: bool = False  # g_t from the simulator's future fading (simulation only: an upper bound)
    trust_loss_map: bool = False  # L_t from the loss map as it stands: no burst model, no learned margin
    in_slot_decision: bool = False  # per-slot gain thresholds (the robot decides at the gain it measures)
    explore_image_fraction: float = 0.0  # in-slot rule: an image at least in this best fraction of fades
    startup_explore_samples: int = 0  # in-slot rule: images in the better half of fades until this many L_t
    probe_gap_slots: int = 0  # in-slot rule: this long without an image → any fade ≥ the median one (0 = off)
    stale_fix_m: float = 0.0  # in-slot rule: the robot's pose fix is stale after this far [m] (FixAge; 0 = off)
    image_slot_loss: float = 0.0  # J: the MR loss an image slot leaves (its JPEG)
    loss_sample_offset: float = 0.0  # subtracted from every loss sample: its JPEG's bias (LossMap.sample_offset)
    burst_time_constant_slots: float = 25.0  # burst model: how fast a measured burst fades into the average
    margin_quantile: float = 0.75  # burst model: learned margin = this quantile of measured / predicted (0 = off)
    margin_window_samples: int = 30  # burst model: … over this many recent measurements
    refine_slots: int = 300  # booked slots whose loss estimate still follows new measurements
    round_slots: int = 0  # T of an operating round whose mean must meet L_th (0 = a running mean)
    round_start_m: float = 0.05  # a round starts when the reported pose first moves this far from where it stood
    half_level_extra_loss: float = 0.0  # extra MR loss of a key slot the server composed at its half level …
    quarter_level_extra_loss: float = 0.0  # … and at its quarter level (bench/perf/compose_levels.py)

    def __post_init__(self) -> None:
        object.__setattr__(self, "solver_options", MappingProxyType(dict(self.solver_options)))
        reason = self._problem()
        if reason:
            raise ValueError(f"planner config: {reason}")
        for f in fields(self):
            if f.type == "float":  # an integer given for a float knob is stored as the float it means
                object.__setattr__(self, f.name, float(getattr(self, f.name)))

    @property
    def loss_target(self) -> float:
        """L_th·(1 − ``loss_margin``): the mean loss the plan aims at."""
        return self.loss_threshold * (1.0 - self.loss_margin)

    def live_change_problem(self, new: PlannerConfig) -> str | None:
        """Why a running planner cannot move from this configuration to ``new`` (a field outside
        :data:`LIVE_FIELDS` differs), or None."""
        fixed = [f.name for f in fields(self)
                 if f.name not in LIVE_FIELDS and getattr(self, f.name) != getattr(new, f.name)]
        return f"{', '.join(fixed)} cannot change in a running planner (set at start-up)" if fixed else None

    def _problem(self) -> str | None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.type in ("int", "bool") and not _is(value, f.type):
                return f"{f.name} must be {'an integer' if f.type == 'int' else 'a bool'}, got {value!r}"
            if f.type == "float" and not (_is(value, "float") and math.isfinite(value)):
                return f"{f.name} must be a finite number, got {value!r}"
        checks = (
            (self.slot_s > 0, "slot_s must be > 0"),
            (self.pose_bits > 0, "pose_bits must be > 0"),
            (self.image_bits > self.pose_bits, "image_bits must exceed pose_bits (an image is larger than a key)"),
            (self.loss_threshold >= 0, "loss_threshold must be >= 0"),
            (self.horizon_slots >= 1, "horizon_slots must be >= 1"),
            (self.method in METHODS, f"method must be one of {list(METHODS)}, got {self.method!r}"),
            (self.drift_threshold >= 0, "drift_threshold must be >= 0"),
            (self.drift_window_samples >= 1, "drift_window_samples must be >= 1"),
            (0 <= self.loss_margin < 1, "loss_margin must be in [0, 1)"),
            (0 <= self.explore_image_fraction <= 1, "explore_image_fraction must be in [0, 1]"),
            (self.startup_explore_samples >= 0, "startup_explore_samples must be >= 0"),
            (self.probe_gap_slots >= 0, "probe_gap_slots must be >= 0"),
            (self.stale_fix_m >= 0, "stale_fix_m must be >= 0"),
            (self.image_slot_loss >= 0, "image_slot_loss must be a loss >= 0"),
            (abs(self.loss_sample_offset) <= 1, "loss_sample_offset must be in [-1, 1]"),
            (self.burst_time_constant_slots > 0, "burst_time_constant_slots must be > 0"),
            (0 <= self.margin_quantile <= 1, "margin_quantile must be in [0, 1]"),
            (self.margin_window_samples >= 1, "margin_window_samples must be >= 1"),
            (self.refine_slots >= 0, "refine_slots must be >= 0"),
            (self.round_slots >= 0, "round_slots must be >= 0"),
            (self.round_start_m >= 0, "round_start_m must be >= 0"),
            (0 <= self.half_level_extra_loss <= 1 and 0 <= self.quarter_level_extra_loss <= 1,
             "half_level_extra_loss and quarter_level_extra_loss must be losses in [0, 1]"),
        )
        return next((why for ok, why in checks if not ok), None)


def _is(value: Any, kind: str) -> bool:
    """``value`` is of the field type ``kind`` (an int is a float; a bool is no number)."""
    if kind == "bool":
        return isinstance(value, bool)
    if isinstance(value, bool):
        return False
    return isinstance(value, int) if kind == "int" else isinstance(value, (int, float))
