"""Online planning over a receding horizon (pure): predict poses, losses and gains, then solve P_GS.

:class:`OnlinePlanner` composes one plan from small objects, each owning one concept (all exported here); which owns
what: docs/scheduling.md, "The planner's code".
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
