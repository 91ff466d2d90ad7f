"""How far the robot's pose keys were from the truth, in hindsight (pure): each scored slot's key against the mock
base's true pose at the key's stamp (the capture stamp of the frame the key stands for, else the slot's start)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from gsrmr_common.pose2d import wrap_angle

#: The slot sources whose MR image was composed at the robot's key (not the server's fallback estimate).
KEY_SOURCES = ("image", "render")


def read_truth(path: str | Path) -> np.ndarray:
    """The mock base's truth log (``stamp_ns,x_m,y_m,yaw_rad``, further columns ignored) as N×4 float64, sorted by
    stamp (stamps in s)."""
    data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2, usecols=(0, 1, 2, 3))
    if data.size == 0:
        return np.zeros((0, 4))
    data[:, 0] *= 1e-9
    return data[np.argsort(data[:, 0], kind="stable")]


def truth_at(truth: np.ndarray, stamp_s: float) -> tuple[float, float, float] | None:
    """The true pose at ``stamp_s`` (linear between the two samples around it; None outside the log)."""
    if truth.shape[0] < 2 or not truth[0, 0] <= stamp_s <= truth[-1, 0]:
        return None
    i = int(np.searchsorted(truth[:, 0], stamp_s, side="right")) - 1
    i = min(i, truth.shape[0] - 2)
    t0, t1 = truth[i, 0], truth[i + 1, 0]
    f = 0.0 if t1 <= t0 else (stamp_s - t0) / (t1 - t0)
    x = truth[i, 1] + f * (truth[i + 1, 1] - truth[i, 1])
    y = truth[i, 2] + f * (truth[i + 1, 2] - truth[i, 2])
    yaw = truth[i, 3] + f * wrap_angle(truth[i + 1, 3] - truth[i, 3])
    return x, y, yaw


def key_pose_errors(rows: list[dict], truth: np.ndarray | None) -> dict[str, float | int | None]:
    """``pose_error_m_median``, ``pose_error_m_p95``, ``pose_error_deg_median``, ``pose_error_deg_p95`` over the
    scored rows composed at a key, and ``pose_error_slots`` (None for each when there is none)."""
    d_m, d_deg = [], []
    for r in rows:
        if r.get("source") not in KEY_SOURCES or r.get("pose_a_m") is None:
            continue
        stamp = r.get("frame_stamp_s") if r.get("frame_stamp_s") is not None else r.get("stamp_s")
        true = None if stamp is None or truth is None else truth_at(truth, float(stamp))
        if true is None:
            continue
        d_m.append(math.hypot(r["pose_a_m"] - true[0], r["pose_b_m"] - true[1]))
        d_deg.append(abs(math.degrees(wrap_angle(r["pose_theta_rad"] - true[2]))))
    if not d_m:
        return {"pose_error_slots": 0, "pose_error_m_median": None, "pose_error_m_p95": None,
                "pose_error_deg_median": None, "pose_error_deg_p95": None}
    return {"pose_error_slots": len(d_m), "pose_error_m_median": float(np.median(d_m)),
            "pose_error_m_p95": float(np.percentile(d_m, 95)), "pose_error_deg_median": float(np.median(d_deg)),
            "pose_error_deg_p95": float(np.percentile(d_deg, 95))}
