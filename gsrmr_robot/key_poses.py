"""Where each slot's pose key comes from (pure): the odometry poses by stamp, calibrated by the server's fixes, put in
``map`` by the ``map → odom`` in force. Design: docs/nodes.md, "The server localizes the robot"."""

from __future__ import annotations

from gsrmr_common.pose2d import Pose2D
from gsrmr_robot.map_source import MapSource
from gsrmr_robot.odometry_calibration import CalibratedOdometry
from gsrmr_robot.uplink_core import PoseHistory


class KeyPoses:
    """The robot's poses for its keys.

    Args:
        maps: ``map → odom`` (the parameter and the server's corrections).
        calibrate: Calibrate the odometry by the fixes (:class:`CalibratedOdometry`); else raw odometry.
    """

    def __init__(self, maps: MapSource, calibrate: bool) -> None:
        self.maps = maps
        self.history = PoseHistory()  # odometry poses (calibrated when calibrating) by stamp
        self.odometry = CalibratedOdometry() if calibrate else None

    def odom(self, stamp_ns: int, raw: Pose2D, omega_radps: float | None, arrival_ns: int) -> None:
        """One odometry pose of the base driver (``odom → base_link``) and its turn rate [rad/s]."""
        pose = raw if self.odometry is None else self.odometry.add(stamp_ns, raw, omega_radps)
        self.history.add(stamp_ns, pose, arrival_ns)

    def key(self, slot: int, stamp_ns: int | None, now_ns: int, max_age_ns: int) -> tuple[Pose2D | None, Pose2D]:
        """``slot``'s key: the pose in ``map`` at ``stamp_ns`` (the frame's; None: the newest), None when the odometry
        is older than ``max_age_ns`` (:meth:`PoseHistory.at`); and the ``map → odom`` to publish on TF (it joins
        the base driver's own ``odom`` frame)."""
        sample = self.history.sample_at(stamp_ns, now_ns, max_age_ns)
        map_from_odom = self.maps.map_from_odom()
        tf_map_from_odom = map_from_odom
        if self.odometry is not None:
            tf_map_from_odom = map_from_odom.compose(self.odometry.raw_frame())
            if sample is not None:
                self.odometry.key_made(slot, sample[0])
        if sample is None:
            return None, tf_map_from_odom
        return map_from_odom.compose(sample[1]), tf_map_from_odom

    def odom_at(self, stamp_ns: int, tolerance_ns: int) -> Pose2D | None:
        """The odometry pose (``odom → base_link``) nearest ``stamp_ns``, None when none is within ``tolerance_ns``
        (a localizer's estimate older than the history, or from before the odometry started)."""
        sample = self.history.sample_at(int(stamp_ns))
        return sample[1] if sample is not None and abs(sample[0] - stamp_ns) <= tolerance_ns else None

    def correction_applied(self, fix_slot: int) -> None:
        """The correction from a fix of ``fix_slot``'s key is in force: it teaches the calibration."""
        if self.odometry is not None:
            self.odometry.learn(fix_slot, self.maps.map_from_odom())

    def position(self) -> tuple[float, float] | None:
        """The robot's newest (x, y) in ``map`` [m]."""
        latest = self.history.latest
        return None if latest is None else self.maps.map_from_odom().compose(latest)[:2]

    def calibration(self) -> dict | None:
        """The calibration's state for ``/diagnostics`` (None: not calibrating)."""
        o = self.odometry
        return None if o is None else {"gain": round(o.gain, 4), "slip_per_radps": round(o.slip, 4),
                                       "pairs_used": o.pairs_used, "pairs_skipped": o.pairs_skipped}
