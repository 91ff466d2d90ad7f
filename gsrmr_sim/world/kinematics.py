"""Unicycle kinematics s_{t+1} = s_t + F(s_t, u_t)·τ (paper Sec. II) and headless route driving.

State (a_m, b_m, theta_rad) in the map frame, control (v_mps, omega_rps). Integration is exact for
a constant control over the step (arc of a circle). Pure numpy, no ROS.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

from gsrmr_common.pose2d import Pose2D, wrap_angle
from gsrmr_common.route import LoopPath, PurePursuit
from gsrmr_sim.world.scene import Route


def unicycle_step(pose: Pose2D, v_mps: float, omega_rps: float, dt_s: float) -> Pose2D:
    """Pose after driving (v, ω) for ``dt_s`` seconds from ``pose`` (exact arc integration)."""
    a, b, th = pose
    if abs(omega_rps) < 1e-9:
        a += v_mps * dt_s * math.cos(th)
        b += v_mps * dt_s * math.sin(th)
    else:
        r = v_mps / omega_rps
        a += r * (math.sin(th + omega_rps * dt_s) - math.sin(th))
        b -= r * (math.cos(th + omega_rps * dt_s) - math.cos(th))
    return Pose2D(a, b, wrap_angle(th + omega_rps * dt_s))


@dataclass
class Drive:
    """A headless drive: per-slot times (s), poses (N×3: a_m, b_m, theta_rad), controls (N×2: the first
    of each slot), progress, and every controller step's control (N×substeps×2: v_mps, omega_rps)."""

    times_s: np.ndarray
    poses: np.ndarray
    controls: np.ndarray
    progress_m: np.ndarray
    loop_length_m: float
    step_controls: np.ndarray


def has_moved(pose: Pose2D, rest: Pose2D, *, min_move_m: float = 0.01,
              min_turn_rad: float = 0.01) -> bool:
    """Whether ``pose`` (a_m, b_m, theta_rad) left ``rest`` by more than ``min_move_m`` or turned by more
    than ``min_turn_rad`` (the round of the simulated world starts then)."""
    return (math.hypot(pose[0] - rest[0], pose[1] - rest[1]) > min_move_m
            or abs(wrap_angle(pose[2] - rest[2])) > min_turn_rad)


def start_pose(route: Route, jitter_m: float = 0.0, seed: int = 0) -> Pose2D:
    """The route's start (first waypoint, facing the second), displaced by up to ``jitter_m`` (seeded)."""
    path = LoopPath(route.waypoints)
    x, y = path.point_at(0.0)
    th = path.heading_at(0.0)
    if jitter_m > 0:
        rng = np.random.default_rng(seed)
        dx, dy = rng.uniform(-jitter_m, jitter_m, 2)
        x, y = x + float(dx), y + float(dy)
        th += float(rng.uniform(-1, 1)) * jitter_m
    return Pose2D(x, y, th)


def drive_route(route: Route, slots: int, slot_s: float, *, pose0: Pose2D | None = None,
                substeps: int = 10) -> Drive:
    """Drive the route closed-loop (pure pursuit + unicycle) and sample it at every slot start.

    The controller runs at ``substeps`` per slot (10 → 100 Hz for τ = 0.1 s).
    """
    path = LoopPath(route.waypoints)
    ctrl = PurePursuit(route.speed_mps, route.lookahead_m, route.max_omega_rps)
    pose = pose0 if pose0 is not None else start_pose(route)
    s = 0.0
    dt = slot_s / substeps
    times, poses, controls, progress, fine = [], [], [], [], []
    v = w = 0.0
    for k in range(slots):
        times.append(k * slot_s)
        poses.append(pose)
        progress.append(s)
        for j in range(substeps):
            v, w, s = ctrl.command(path, pose, s)
            if j == 0:
                controls.append((v, w))
            fine.append((v, w))
            pose = unicycle_step(pose, v, w, dt)
    return Drive(np.asarray(times), np.asarray(poses, dtype=np.float64).reshape(-1, 3),
                 np.asarray(controls, dtype=np.float64).reshape(-1, 2), np.asarray(progress), path.length_m,
                 np.asarray(fine, dtype=np.float64).reshape(slots, substeps, 2))


def lap_time_s(route: Route, dt_s: float = 0.01, max_s: float = 600.0) -> float:
    """Seconds for one closed-loop lap of the route at its nominal speed (pure pursuit, from the start)."""
    path = LoopPath(route.waypoints)
    ctrl = PurePursuit(route.speed_mps, route.lookahead_m, route.max_omega_rps)
    pose = start_pose(route)
    s, t = 0.0, 0.0
    while t < max_s:
        v, w, s_new = ctrl.command(path, pose, s)
        if s_new >= path.length_m:
            # interpolate the crossing within the last step
            return t - dt_s * (s_new - path.length_m) / max(s_new - s, 1e-12)
        s = s_new
        pose = unicycle_step(pose, v, w, dt_s)
        t += dt_s
    raise RuntimeError("route: no lap completed within max_s")
