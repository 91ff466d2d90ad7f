"""The hindsight pose errors: each scored key slot's key against the true pose at the key's stamp."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gsrmr_sim.pose_errors import key_pose_errors, read_truth, truth_at


def test_keys_are_compared_at_their_frames_stamps_and_fallbacks_are_left_out(tmp_path):
    log = tmp_path / "truth.csv"
    stamps = np.arange(0, 2_000_000_001, 20_000_000)  # 50 Hz for 2 s
    x = 0.3 * stamps / 1e9  # driving along x at 0.3 m/s
    np.savetxt(log, np.c_[stamps, x, np.zeros_like(x), np.full_like(x, 0.1)], delimiter=",",
               header="stamp_ns,x_m,y_m,yaw_rad", comments="")
    truth = read_truth(log)
    assert truth_at(truth, 1.01) == pytest.approx((0.303, 0.0, 0.1)) and truth_at(truth, 3.0) is None
    rows = [{"source": "image", "pose_a_m": 0.3 + 0.01, "pose_b_m": 0.0, "pose_theta_rad": 0.1 + math.radians(0.5),
             "frame_stamp_s": 1.0, "stamp_s": 1.05},
            {"source": "render", "pose_a_m": 0.315, "pose_b_m": 0.0, "pose_theta_rad": 0.1, "frame_stamp_s": None,
             "stamp_s": 1.05},  # no frame: the slot's start
            {"source": "fallback", "pose_a_m": 9.0, "pose_b_m": 9.0, "pose_theta_rad": 0.0, "stamp_s": 1.0}]
    e = key_pose_errors(rows, truth)
    assert e["pose_error_slots"] == 2 and e["pose_error_m_median"] == pytest.approx(0.005, abs=1e-9)
    assert e["pose_error_deg_p95"] == pytest.approx(0.5 * 0.95, abs=1e-6)
    assert key_pose_errors(rows, None)["pose_error_slots"] == 0


def test_the_truth_log_reads_with_its_tick_lateness_column(tmp_path):
    log = tmp_path / "truth.csv"
    log.write_text("stamp_ns,x_m,y_m,yaw_rad,tick_late_ms\n20000000,0.5,0.0,0.1,0.25\n0,0.0,0.0,0.1,nan\n")
    assert read_truth(log).tolist() == [[0.0, 0.0, 0.0, 0.1], [0.02, 0.5, 0.0, 0.1]]
