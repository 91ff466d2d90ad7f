"""How late the simulated world ran, per part (camera, mock base, radio), from a run's report folder."""

from __future__ import annotations

import math
import time

import pytest

from gsrmr_sim.limo.mock import MockLimo
from gsrmr_sim.world_lateness import (
    base_late_p95_ms,
    channel_gain_p95_ms,
    frame_age_p95_ms,
    no_gain_slots,
    read_rows,
    scored,
    world_lateness,
)

SLOTS_HEADER = "slot,stamp_s,frame_stamp_s,round_slot,scored\n"


def slots_csv(n: int = 20, *, first: int = 100) -> str:
    """``n`` slots of 0.1 s from slot ``first``: two unscored ones first, frames 30 ms old (slot 110's 130 ms),
    slot 105 booked without a measured gain."""
    lines = [SLOTS_HEADER]
    for k in range(first, first + n):
        age = 0.13 if k == 110 else 0.03
        lines.append(f"{k},{k / 10},{k / 10 - age},{-1 if k == 105 else k - first},{int(k >= first + 2)}\n")
    return "".join(lines)


def test_camera_age_and_the_slots_without_a_measured_gain(tmp_path):
    (tmp_path / "slots.csv").write_text(slots_csv())
    rows = scored(read_rows(tmp_path / "slots.csv"))
    assert len(rows) == 18
    assert frame_age_p95_ms(rows) == pytest.approx(30 + 0.15 * 100, abs=1e-6)  # 1 of 18 at 130 ms: p95 interpolates
    assert no_gain_slots(rows) == 1
    assert math.isnan(frame_age_p95_ms([]))


def test_base_lateness_is_its_ticks_within_the_scored_slots_only():
    rows = [{"stamp_s": "10.0"}, {"stamp_s": "11.0"}]
    truth = [{"stamp_ns": str(int(t * 1e9)), "tick_late_ms": late}
             for t, late in [(9.0, "500.0"), (10.0, "1.0"), (10.5, "nan"), (10.6, "3.0"), (11.0, "2.0"),
                             (11.5, "900.0")]]
    assert base_late_p95_ms(truth, rows) == pytest.approx(2.9)  # 1, 3, 2: before and after the round left out
    assert math.isnan(base_late_p95_ms([{"stamp_ns": "10000000000"}], rows))  # a log without the column
    assert math.isnan(base_late_p95_ms(truth, []))


def test_channel_gain_is_publish_time_minus_slot_start_of_the_scored_slots():
    rows = [{"slot": "101"}, {"slot": "102"}]
    published = [{"slot": "100", "slot_start_ns": "0", "published_ns": "500000000"},  # not scored
                 {"slot": "101", "slot_start_ns": "100000000", "published_ns": "61000000"},  # 39 ms ahead
                 {"slot": "102", "slot_start_ns": "200000000", "published_ns": "210000000"}]  # 10 ms late
    assert channel_gain_p95_ms(published, rows) == pytest.approx(-39 + 0.95 * 49)
    assert math.isnan(channel_gain_p95_ms([], rows))


def test_a_report_folder_gives_every_figure_and_names_what_it_lacks(tmp_path):
    (tmp_path / "slots.csv").write_text(slots_csv())
    figures, problems = world_lateness(tmp_path)
    assert figures["world_age_p95_ms"] == pytest.approx(45.0) and figures["channel_no_gain_slots"] == 1
    assert "base_late_p95_ms" not in figures and len(problems) == 2  # no truth log, no publish log
    rec = tmp_path / "recording"
    rec.mkdir()
    (rec / "truth_poses.csv").write_text("stamp_ns,x_m,y_m,yaw_rad,tick_late_ms\n"
                                         + "".join(f"{k * 10**8},0,0,0,0.5\n" for k in range(100, 120))
                                         + "11900000000,0,0")  # torn by a kill: dropped
    (rec / "channel_publish.csv").write_text("slot,round_slot,slot_start_ns,published_ns\n"
                                             + "".join(f"{k},{k - 100},{k * 10**8},{k * 10**8 - 39_000_000}\n"
                                                       for k in range(100, 120)))
    figures, problems = world_lateness(tmp_path)
    assert problems == []
    assert figures["base_late_p95_ms"] == pytest.approx(0.5)
    assert figures["channel_gain_p95_ms"] == pytest.approx(-39.0)
    figures, problems = world_lateness(tmp_path / "nowhere")
    assert figures == {} and len(problems) == 1 and problems[0].startswith("slots.csv: ")


def test_the_mock_base_reports_how_late_its_ticks_ran(tmp_path):
    with MockLimo(str(tmp_path / "limo"), rate_hz=50.0) as mock:
        time.sleep(0.2)
        late = mock.take_tick_lateness_s()
    assert late is not None and 0.0 <= late < 0.5
