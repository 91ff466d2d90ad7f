"""Where the robot's ``map → odom`` comes from (pure): its ``map_from_odom`` parameter, corrected by the server's
numbered corrections (:class:`~gsrmr_common.wire.MapCorrection`), each checked before it is applied, or replaced by
another localizer's (AMCL, slam_toolbox). Design: docs/nodes.md, "The server localizes the robot"."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
import math
from typing import Any

from gsrmr_common.plausibility import Implausible
from gsrmr_common.pose2d import Pose2D, yaw_from_quaternion
from gsrmr_common.tf_tree import MAP_FRAME
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
        self.variance = (c.var_a_m2, c.var_b_m2, c.var_theta_rad2)
        return None

    def set_external(self, map_from_odom: Pose2D, stamp_s: float,
                     variance: tuple[float, float, float] = (math.nan,) * 3) -> str | None:
        """``map → odom`` from another localizer (its own filter and its own jumps: no step or total limit), put in
        force as the next numbered correction. Returns why it is refused (counted ``correction_malformed``: a
        non-finite pose or stamp), or None."""
        pose = Pose2D.of(map_from_odom)
        if not (all(math.isfinite(v) for v in pose) and math.isfinite(stamp_s)):
            self.implausible["correction_malformed"] += 1
            return "correction_malformed"
        self.correction = pose.wrapped().compose(self.parameter.inverse())
        self.seq, self.stamp_s, self.variance = self.seq + 1, float(stamp_s), tuple(float(v) for v in variance)
        return None


def map_from_odom_of(map_from_base: Pose2D, odom_from_base: Pose2D) -> Pose2D:
    """``map → odom`` from the base's pose in ``map`` (a localizer's estimate) and in ``odom`` (the odometry at the
    same stamp): ``map_from_base ∘ odom_from_base⁻¹`` (m, rad)."""
    return Pose2D.of(map_from_base).compose(Pose2D.of(odom_from_base).inverse())


def planar_pose(position: Any, orientation: Any) -> Pose2D:
    """(x, y, yaw) of a ROS position/translation and quaternion (m, rad; z, roll and pitch dropped)."""
    return Pose2D(float(position.x), float(position.y),
                  yaw_from_quaternion(orientation.x, orientation.y, orientation.z, orientation.w))


def map_to_odom_edges(transforms: Iterable[Any], odom_frame: str) -> list[tuple[int, Pose2D]]:
    """The ``map → odom_frame`` edges of a ``TFMessage``'s transforms, as (stamp ns, planar pose of odom in map);
    frame names compared without a leading ``/`` (ROS 1 writers)."""
    out = []
    for t in transforms:
        if t.header.frame_id.lstrip("/") == MAP_FRAME and t.child_frame_id.lstrip("/") == odom_frame.lstrip("/"):
            stamp_ns = t.header.stamp.sec * 1_000_000_000 + t.header.stamp.nanosec
            out.append((stamp_ns, planar_pose(t.transform.translation, t.transform.rotation)))
    return out
