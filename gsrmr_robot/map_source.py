"""Where the robot's ``map → odom`` comes from (pure): its ``map_from_odom`` parameter, corrected by the server's
numbered corrections (:class:`~gsrmr_common.wire.MapCorrection`), each checked before it is applied. Design:
docs/nodes.md, "The server localizes the robot"."""

from __future__ import annotations

from dataclasses import dataclass
import math

from gsrmr_common.plausibility import Implausible
from gsrmr_common.pose2d import Pose2D
from gsrmr_common.wire import MapCorrection
from gsrmr_common.writer_admission import SeqTracker

#: Why a correction is refused (counted in ``implausible``).
CORRECTION_SEQ, CORRECTION_STEP, CORRECTION_TOTAL = "correction_seq", "correction_step", "correction_total"


@dataclass(frozen=True)
class CorrectionLimits:
    """How far one correction may move ``map → odom`` from the one in force, and the total from the parameter."""

    max_step_m: float = 0.5
    max_step_rad: float = math.radians(20.0)
    max_total_m: float = 3.0
    max_total_rad: float = math.radians(60.0)


class MapSource:
    """``map → odom`` = X ∘ M₀: M₀ the ``map_from_odom`` parameter, X the newest accepted correction (identity and
    seq 0 before the first)."""

    def __init__(self, map_from_odom: Pose2D, limits: CorrectionLimits, implausible: Implausible) -> None:
        self.parameter = Pose2D.of(map_from_odom)
        self.limits = limits
        self.implausible = implausible
        self.correction = Pose2D()
        self.seq = 0
        self.stamp_s = -math.inf  # of the newest fix in the correction in force
        self.variance = (math.inf, math.inf, math.inf)
        self._seq = SeqTracker()
        self.driven_since_correction_m = 0.0  # odometry distance since the correction in force was applied …
        self.driven_since_image_m = 0.0  # … and since the last image went (its fix may still come)

    def map_from_odom(self) -> Pose2D:
        """The pose of ``odom`` in ``map`` now."""
        return self.correction.compose(self.parameter)

    def set_parameter(self, map_from_odom: Pose2D) -> None:
        """A new ``map_from_odom`` parameter (the correction in force stays)."""
        self.parameter = Pose2D.of(map_from_odom)

    def offer(self, c: MapCorrection, writer_gid: bytes = b"") -> str | None:
        """A correction from an admitted writer. Returns why it is refused (counted), or None when it is applied:
        its seq must grow per writer endpoint (a repeat is ignored: None, nothing changes), the step from the
        correction in force and the total must be within :class:`CorrectionLimits`."""
        seq = self._seq.check(writer_gid, c.seq)
        if seq == "repeat":
            return None
        lim = self.limits
        x = Pose2D(c.a_m, c.b_m, c.theta_rad).wrapped()
        step = x.relative_to(self.correction)
        reason = None
        if seq == "older":
            reason = CORRECTION_SEQ
        elif step.distance_m((0.0, 0.0)) > lim.max_step_m or abs(step.theta_rad) > lim.max_step_rad:
            reason = CORRECTION_STEP
        elif x.distance_m((0.0, 0.0)) > lim.max_total_m or abs(x.theta_rad) > lim.max_total_rad:
            reason = CORRECTION_TOTAL
        if reason:
            self.implausible[reason] += 1
            return reason
        self.correction, self.seq, self.stamp_s = x, c.seq, c.stamp_s
        self.driven_since_correction_m = 0.0
        self.variance = (c.var_a_m2, c.var_b_m2, c.var_theta_rad2)
        return None

    def moved(self, distance_m: float) -> None:
        """The robot drove ``distance_m`` (odometry) since the last call."""
        if math.isfinite(distance_m) and distance_m > 0:
            self.driven_since_correction_m += distance_m
            self.driven_since_image_m += distance_m

    def image_sent(self) -> None:
        """An image went: the server may fix the robot from it."""
        self.driven_since_image_m = 0.0

    def stale(self, max_driven_m: float) -> bool:
        """Whether the keys' correction is stale: the robot drove more than ``max_driven_m`` since the correction in
        force (or since the start, before any) and more than half that since the last image (whose fix would have
        come by then). ``max_driven_m`` ≤ 0: never."""
        return (max_driven_m > 0 and self.driven_since_correction_m > max_driven_m
                and self.driven_since_image_m > 0.5 * max_driven_m)
