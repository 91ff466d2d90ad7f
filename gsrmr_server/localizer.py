"""The server's localizer (no ROS): received images registered against the model in a process of its own, off the
slot path, and their fixes filtered into ``map → odom`` corrections. Design: docs/nodes.md, "The server localizes
the robot"."""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
import math
import multiprocessing as mp
from multiprocessing.connection import Connection
import os
import time

import numba
import numpy as np

from gsrmr_common.camera import Camera, CameraMount, Intrinsics, camera_from_pose
from gsrmr_common.pose2d import Pose2D
from gsrmr_common.tf_tree import base_from_camera_optical_transform, transform_matrix
from gsrmr_common.wire import MapCorrection, PoseKey
from gsrmr_server.map_correction import Correction, CorrectionFilter, FilterConfig, Fix
from gsrmr_splat.localize import register
from gsrmr_splat.model import GaussianModel

#: Skipped registrations, by why (counted): the worker was busy, the last one was too recent, the server was late.
SKIP_BUSY, SKIP_INTERVAL, SKIP_LATE = "busy", "interval", "server_late"


@dataclass(frozen=True)
class LocalizerConfig:
    """When the server registers an image: at most one at a time, one per ``min_interval_s``, and none while the
    slot path runs late; the worker at a lower priority (``worker_nice``) than the slot path."""

    min_interval_s: float = 1.0
    worker_nice: int = 10
    worker_threads: int = 1  # the render threads of a registration


def _worker(conn: Connection, model_path: str, background: tuple[float, float, float], nice: int,
            threads: int) -> None:
    """The registration process: loads the model, then answers ``(job id, image u8, intrinsics, w2c)`` with
    ``(job id, accepted, refused, camera_to_world, inliers, seconds)`` until it reads None."""
    os.nice(nice)
    numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))
    model = GaussianModel.load_ply(model_path)
    conn.send(("ready", model.num_gaussians))
    while True:
        job = conn.recv()
        if job is None:
            return
        if job[0] == "model":
            model = GaussianModel.load_ply(job[1])
            continue
        job_id, image_u8, k, w2c = job
        guess = Camera(Intrinsics(*k), w2c)
        reg = register(model, image_u8.astype(np.float32) / 255.0, guess, background=background)
        conn.send((job_id, reg.accepted, reg.refused, reg.camera.camera_to_world, reg.inliers, reg.seconds))


@dataclass(frozen=True)
class _Pending:
    job_id: int
    stamp_s: float
    key: Pose2D
    key_correction: int
    travelled_m: float


class ServerLocalizer:
    """Registers some of the received images and keeps the correction filter.

    Args:
        model_path: The server's model (the worker loads its own copy).
        mount: The camera's pose on the robot (``camera_mount.*``).
        background: The model's background, RGB in [0, 1].
        config: When to register (:class:`LocalizerConfig`).
        filter_config: The correction filter's noise model (:class:`~gsrmr_server.map_correction.FilterConfig`).
    """

    def __init__(self, model_path: str, mount: CameraMount, background: tuple[float, float, float],
                 config: LocalizerConfig | None = None, filter_config: FilterConfig | None = None) -> None:
        self.config = config or LocalizerConfig()
        self.mount = mount
        self.base_from_camera = transform_matrix(base_from_camera_optical_transform(mount))
        self.filter = CorrectionFilter(filter_config)
        self.skipped: dict[str, int] = {}
        self.registrations = 0
        self.registration_s: list[float] = []
        self.results: dict[str, int] = {}
        ctx = mp.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_worker, args=(child, model_path, tuple(background), self.config.worker_nice,
                                                       self.config.worker_threads), daemon=True,
                                 name="gsrmr-localizer")
        self._proc.start()
        self.ready = False  # the worker has loaded its model
        self._pending: _Pending | None = None
        self._next_id = 0
        self._last_submit_s = -math.inf
        self._last_key: Pose2D | None = None
        self._travelled_m = 0.0

    def note_key(self, key: PoseKey) -> None:
        """Every slot's key: how far the robot drove between fixes (the filter's drift allowance)."""
        pose = Pose2D(key.a_m, key.b_m, key.theta_rad)
        if self._last_key is not None:
            self._travelled_m += pose.distance_m(self._last_key)
        self._last_key = pose

    def offer(self, image_u8: np.ndarray, key: PoseKey, key_correction: int, intrinsics: Intrinsics,
              stamp_s: float, now_s: float, late: bool) -> bool:
        """An image slot's decoded image (H×W×3 uint8 RGB at ``intrinsics``) and its key: registered unless the
        worker is busy, the last registration is under ``min_interval_s`` old or the slot path runs ``late``.
        Returns whether it was submitted."""
        reason = (SKIP_BUSY if self._pending is not None or not self.ready else
                  SKIP_INTERVAL if now_s - self._last_submit_s < self.config.min_interval_s else
                  SKIP_LATE if late else None)
        if reason:
            self.skipped[reason] = self.skipped.get(reason, 0) + 1
            return False
        pose = Pose2D(key.a_m, key.b_m, key.theta_rad)
        guess = camera_from_pose(pose.x_m, pose.y_m, pose.theta_rad, self.mount, intrinsics)
        k = (intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy, intrinsics.width, intrinsics.height)
        self._next_id += 1
        self._conn.send((self._next_id, np.ascontiguousarray(image_u8), k, guess.world_to_camera))
        self._pending = _Pending(self._next_id, stamp_s, pose, int(key_correction), self._travelled_m)
        self._last_submit_s = now_s
        return True

    def poll(self, now_s: float) -> Correction | None:
        """Take the worker's answer, if any: a fix the filter accepts gives the next correction to send."""
        if not self.ready and self._conn.poll():
            tag, _n = self._conn.recv()
            self.ready = tag == "ready"
        if self._pending is None or not self._conn.poll():
            self.filter.update_state(now_s)
            return None
        job_id, accepted, refused, c2w, _inliers, seconds = self._conn.recv()
        pending, self._pending = self._pending, None
        self.registrations += 1
        self.registration_s = [*self.registration_s[-99:], float(seconds)]
        if job_id != pending.job_id or not accepted:
            self.results[refused or "stale"] = self.results.get(refused or "stale", 0) + 1
            return None
        map_from_base = np.asarray(c2w) @ np.linalg.inv(self.base_from_camera)
        base = Pose2D(float(map_from_base[0, 3]), float(map_from_base[1, 3]),
                      math.atan2(map_from_base[1, 0], map_from_base[0, 0]))
        verdict = self.filter.offer(Fix(pending.stamp_s, base, pending.key, pending.key_correction),
                                    travelled_m=pending.travelled_m)
        self.results[verdict or "accepted"] = self.results.get(verdict or "accepted", 0) + 1
        if verdict is not None:
            return None
        self._travelled_m -= pending.travelled_m
        return self.filter.next_correction()

    def swap_model(self, model_path: str) -> None:
        """Register against another model from the next job on."""
        self._conn.send(("model", model_path))

    def close(self) -> None:
        """Stop the worker."""
        with contextlib.suppress(BrokenPipeError, OSError):  # the worker is gone already
            self._conn.send(None)
        self._proc.join(timeout=2.0)
        if self._proc.is_alive():
            self._proc.terminate()

    def diagnostic_values(self, now_s: float) -> dict[str, object]:
        """The localization's state, its counts and the registration time."""
        f = self.filter
        times = sorted(self.registration_s)
        return {"localization": f.update_state(now_s), "correction_seq": f.seq,
                "fix_age_s": round(now_s - f.stamp_s, 2) if math.isfinite(f.stamp_s) else -1,
                "fixes": dict(self.results), "registrations_skipped": dict(self.skipped),
                "registration_ms_p50": round(1e3 * times[len(times) // 2], 1) if times else -1}


def correction_record(c: Correction) -> MapCorrection:
    """The wire record of a correction."""
    return MapCorrection(c.seq, c.stamp_s, c.x.x_m, c.x.y_m, c.x.theta_rad, *c.variance)


def wait_until_ready(localizer: ServerLocalizer, timeout_s: float = 60.0) -> bool:
    """Block until the worker has loaded its model (tests, benches)."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        localizer.poll(0.0)
        if localizer.ready:
            return True
        time.sleep(0.05)
    return False
