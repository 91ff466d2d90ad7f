"""Online planning over a receding horizon (pure): predict poses, losses and gains, then solve P_GS.

:class:`OnlinePlanner` (``online.py``) composes one plan from small objects, each owning one concept:

* :class:`PlannerConfig` (``config.py``) — every knob, frozen and validated; the scheduler's parameters map
  onto it in :meth:`gsrmr_scheduler.scheduler_params.SchedulerParameters.planner_config`;
* :class:`RoutePredictor` (``route.py``) — future poses along the route;
* :class:`LossForecast` (``forecast.py``) — L_t predicted, estimated for booked slots, learned from samples;
* :class:`LossBudget` (``budget.py``) — booked slots, rounds, the Σ loss each block of a plan may leave;
* :class:`LinkCap` (``link_cap.py``) — the image fraction the uplink carries;
* :class:`InSlotPricing` (``pricing.py``) — the in-slot rule's gain thresholds, exploration and probing;
* :class:`DriftMonitor` (``drift.py``) — when measured losses call for a replan;
* :class:`SampleAlignedCadence` (``cadence.py``) — when the periodic replan runs: right after the next loss sample.
"""

from gsrmr_scheduler.planner.budget import LossBudget
from gsrmr_scheduler.planner.cadence import SampleAlignedCadence
from gsrmr_scheduler.planner.config import LIVE_FIELDS, PlannerConfig
from gsrmr_scheduler.planner.drift import DriftMonitor
from gsrmr_scheduler.planner.forecast import LossForecast, SlotLossModel
from gsrmr_scheduler.planner.link_cap import LinkCap
from gsrmr_scheduler.planner.online import OnlinePlanner, PlanResult
from gsrmr_scheduler.planner.pricing import InSlotPricing
from gsrmr_scheduler.planner.route import RoutePredictor

__all__ = ["LIVE_FIELDS", "DriftMonitor", "InSlotPricing", "LinkCap", "LossBudget", "LossForecast", "OnlinePlanner",
           "PlanResult", "PlannerConfig", "RoutePredictor", "SampleAlignedCadence", "SlotLossModel"]
