"""The robot's wheel odometry calibrated by the server's fixes (pure): each odometry step's translation scaled by
``gain − slip·|ω|``, the two learned from how far the robot really went between fixes. Design: docs/nodes.md, "The
server localizes the robot".

Frames: ``raw`` poses are the base driver's ``odom → base_link`` (m, rad); the calibrated poses live in a frame that
starts at the first raw pose and keeps its heading (a wheel odometry's heading comes from its IMU; only distances
are scaled). Keys are made from the calibrated poses; ``map → odom`` then names that frame's pose in ``map``.
"""

from __future__ import annotations

from collections import OrderedDict, deque
from dataclasses import dataclass
import math

from gsrmr_common.pose2d import Pose2D


@dataclass(frozen=True)
class CalibrationConfig:
    """How the calibration learns (SI units; the gain and slip are dimensionless, the slip per rad/s)."""

    prior_sigma: float = 0.05  # σ of the prior on gain (around 1) and slip (around 0)
    fix_sigma_m: float = 0.007  # noise of one displacement between two fixes, per axis
    forget: float = 0.9  # weight left to the older pairs at each new one (a memory of about ten pairs)
    min_travel_m: float = 0.1  # a pair of fixes closer than this (by odometry) teaches nothing
    max_gap_s: float = 5.0  # … nor one further apart in time than this
    max_mismatch_m: float = 0.03  # a pair whose displacement misses the prediction by more than this …
    max_mismatch_per_m: float = 0.1  # … plus this per metre driven is a bad fix or an odometry reset: skipped
    gain_range: tuple[float, float] = (0.8, 1.25)
    max_slip_per_radps: float = 0.5
    max_raw_step_m: float = 0.5  # a raw odometry step longer than this is a reset: the history starts again


@dataclass(frozen=True)
class _Sample:
    stamp_ns: int
    pose: Pose2D  # calibrated
    sum_a: tuple[float, float]  # Σ raw displacement (odom axes, m) since the start
    sum_w: tuple[float, float]  # Σ raw displacement × |ω| (m·rad/s)
    raw_theta_rad: float  # the raw heading there (the calibrated one differs by a constant between resets)
    epoch: int  # raw odometry resets so far


class CalibratedOdometry:
    """Raw odometry in, calibrated poses out; fixes teach the gain and the slip.

    Args:
        config: How it learns.
        history: How many odometry samples are kept for :meth:`key_made` (≥ the samples of ``max_pose_age_s``).
    """

    def __init__(self, config: CalibrationConfig | None = None, history: int = 400) -> None:
        self.config = config or CalibrationConfig()
        self.gain, self.slip = 1.0, 0.0
        self.pairs_used = 0
        self.pairs_skipped = 0
        self._raw: Pose2D | None = None
        self._raw_stamp_ns = 0
        self._pose = Pose2D()
        self._sum_a = (0.0, 0.0)
        self._sum_w = (0.0, 0.0)
        self._epoch = 0
        self._samples: deque[_Sample] = deque(maxlen=history)
        self._by_stamp: dict[int, _Sample] = {}
        self._keys: OrderedDict[int, _Sample] = OrderedDict()  # slot → the sample its key was made from
        self._last_fix: tuple[_Sample, Pose2D] | None = None  # (key sample, true pose in map) of the last fix
        self._info = [0.0, 0.0, 0.0]  # forgotten normal equations: [[i00, i01], [i01, i11]] …
        self._rhs = [0.0, 0.0]  # … and their right side, in (gain − 1, slip)

    def add(self, stamp_ns: int, raw: Pose2D, omega_radps: float | None = None) -> Pose2D:
        """One raw odometry pose (and the base's turn rate, else from the headings); returns the calibrated pose (a
        non-finite ``raw`` is returned as it is, and changes nothing)."""
        raw = Pose2D.of(raw)
        if not all(math.isfinite(v) for v in raw):
            return raw
        if self._raw is not None:
            dx, dy = raw.x_m - self._raw.x_m, raw.y_m - self._raw.y_m
            if math.hypot(dx, dy) > self.config.max_raw_step_m or stamp_ns < self._raw_stamp_ns:
                self._epoch += 1  # the driver restarted its odometry: pairs across this teach nothing
            else:
                step = raw.relative_to(self._raw)
                dt_s = (stamp_ns - self._raw_stamp_ns) / 1e9
                if omega_radps is None or not math.isfinite(omega_radps):
                    omega_radps = step.theta_rad / dt_s if dt_s > 0 else 0.0
                w = abs(omega_radps)
                scale = max(0.0, self.gain - self.slip * w)
                self._pose = self._pose.compose(Pose2D(step.x_m * scale, step.y_m * scale, step.theta_rad))
                self._sum_a = (self._sum_a[0] + dx, self._sum_a[1] + dy)
                self._sum_w = (self._sum_w[0] + dx * w, self._sum_w[1] + dy * w)
        else:
            self._pose = raw
        self._raw, self._raw_stamp_ns = raw, int(stamp_ns)
        sample = _Sample(int(stamp_ns), self._pose, self._sum_a, self._sum_w, raw.theta_rad, self._epoch)
        if len(self._samples) == self._samples.maxlen:
            self._by_stamp.pop(self._samples[0].stamp_ns, None)
        self._samples.append(sample)
        self._by_stamp[sample.stamp_ns] = sample
        return self._pose

    def raw_frame(self) -> Pose2D:
        """The base driver's ``odom`` frame in the calibrated one, at the newest pose (what turns a ``map →``
        calibrated-frame pose into the ``map → odom`` TF consumers expect)."""
        return Pose2D() if self._raw is None else self._pose.compose(self._raw.inverse())

    def key_made(self, slot: int, stamp_ns: int) -> None:
        """The key of ``slot`` was made from the calibrated pose stamped ``stamp_ns`` (one :meth:`add` returned)."""
        sample = self._by_stamp.get(int(stamp_ns))
        if sample is None:
            return
        self._keys[int(slot)] = sample
        while len(self._keys) > 200:
            self._keys.popitem(last=False)

    def learn(self, slot: int, map_from_odom: Pose2D) -> bool:
        """A correction from a fix of ``slot``'s key is in force, ``map_from_odom`` with it: the true pose then was
        ``map_from_odom ∘ key pose``. With the fix before, the displacement teaches gain and slip. Returns whether
        the pair was used."""
        sample = self._keys.get(int(slot))
        if sample is None:
            return False
        frame = Pose2D.of(map_from_odom)
        true = frame.compose(sample.pose)
        last, self._last_fix = self._last_fix, (sample, true)
        if last is None or last[0].stamp_ns >= sample.stamp_ns:
            return False
        cfg = self.config
        prev, prev_true = last
        ax, ay = sample.sum_a[0] - prev.sum_a[0], sample.sum_a[1] - prev.sum_a[1]
        wx, wy = sample.sum_w[0] - prev.sum_w[0], sample.sum_w[1] - prev.sum_w[1]
        travel_m = math.hypot(ax, ay)
        if (prev.epoch != sample.epoch or travel_m < cfg.min_travel_m
                or (sample.stamp_ns - prev.stamp_ns) / 1e9 > cfg.max_gap_s):
            return False
        to_raw = frame.theta_rad + sample.pose.theta_rad - sample.raw_theta_rad  # raw odom axes in map
        c, s = math.cos(-to_raw), math.sin(-to_raw)
        mx, my = true.x_m - prev_true.x_m, true.y_m - prev_true.y_m
        dx, dy = c * mx - s * my, s * mx + c * my
        # model: D = gain·A − slip·W, in (u = gain − 1, slip): D − A = u·A − slip·W
        miss = math.hypot(dx - (self.gain * ax - self.slip * wx), dy - (self.gain * ay - self.slip * wy))
        if miss > cfg.max_mismatch_m + cfg.max_mismatch_per_m * travel_m:
            self.pairs_skipped += 1
            return False
        weight = 1.0 / cfg.fix_sigma_m ** 2
        info = [v * cfg.forget for v in self._info]
        rhs = [v * cfg.forget for v in self._rhs]
        for a, w, d in ((ax, wx, dx - ax), (ay, wy, dy - ay)):
            info[0] += weight * a * a
            info[1] -= weight * a * w
            info[2] += weight * w * w
            rhs[0] += weight * a * d
            rhs[1] -= weight * w * d
        self._info, self._rhs = info, rhs
        prior = 1.0 / cfg.prior_sigma ** 2
        i00, i01, i11 = info[0] + prior, info[1], info[2] + prior
        det = i00 * i11 - i01 * i01
        u = (i11 * rhs[0] - i01 * rhs[1]) / det
        slip = (i00 * rhs[1] - i01 * rhs[0]) / det
        self.gain = min(max(1.0 + u, cfg.gain_range[0]), cfg.gain_range[1])
        self.slip = min(max(slip, -cfg.max_slip_per_radps), cfg.max_slip_per_radps)
        self.pairs_used += 1
        return True
