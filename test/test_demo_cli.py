"""``gsrmr-demo``'s two-host options (pure: nothing is started)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from gsrmr_sim import demo
from gsrmr_sim.link_events import parse_link_events
import gsrmr_sim.netns as netns
from gsrmr_sim.report import link_summary, write_report
from gsrmr_sim.round_start import first_round_row
from gsrmr_sim.truth_frames import TruthFrameReader, TruthFrameWriter


def test_link_events_parse_and_refuse_nonsense():
    events = parse_link_events("down@100, up@120,rate=1.5@150")
    assert [(e.at_slot, e.action, e.mbit) for e in events] == [(100, "down", 0.0), (120, "up", 0.0), (150, "rate", 1.5)]
    assert events[2].as_dict() == {"at_slot": 150, "action": "rate", "mbit": 1.5}
    for bad in ("down", "down@x", "rate@10", "up=3@10", "reboot@5"):
        with pytest.raises(ValueError):
            parse_link_events(bad)


def test_params_parse_as_yaml_values():
    got = demo.parse_params(["gsrmr_robot:hold_images_while_queued=false", "gsrmr_robot:jpeg_quality=70",
                             "gsrmr_server:mr_content=garden"])
    assert got == {"gsrmr_robot": {"hold_images_while_queued": False, "jpeg_quality": 70},
                   "gsrmr_server": {"mr_content": "garden"}}
    for bad in ("gsrmr_robot", "gsrmr_robot:jpeg_quality", ":x=1"):
        with pytest.raises(ValueError):
            demo.parse_params([bad])


def test_two_hosts_without_root_exits_2_with_one_line(monkeypatch, capsys):
    monkeypatch.setattr(netns, "unavailable_reason", lambda: "needs root (network namespaces and veth pairs)")
    assert demo.main(["--hosts", "2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["gsrmr-demo --hosts 2: needs root (network namespaces and veth pairs)"]


def test_two_hosts_refuses_the_oracle_and_link_events_need_two_hosts(monkeypatch):
    monkeypatch.setattr(netns, "unavailable_reason", lambda: None)
    with pytest.raises(SystemExit):
        demo.main(["--hosts", "2", "--oracle"])
    with pytest.raises(SystemExit):
        demo.main(["--link-events", "down@10"])


def test_a_report_folder_holding_a_run_is_refused(tmp_path):
    (tmp_path / "recording").mkdir()
    with pytest.raises(SystemExit):
        demo.main(["--out", str(tmp_path)])


def test_link_summary_counts_what_crossed_between_start_and_end():
    log = {"start": {"uplink": 1000, "downlink": 500, "uplink_dropped": 3, "wall_s": 10.0},
           "end": {"uplink": 1_251_000, "downlink": 20_500, "uplink_dropped": 7, "wall_s": 30.0},
           "events": [{"at_slot": 100, "action": "down"}]}
    rows = [{"bytes_sent": 24}, {"bytes_sent": 8000}, {"bytes_sent": None}]
    got = link_summary(log, rows, 5.0)
    assert got["link_uplink_bytes"] == 1_250_000 and got["link_downlink_bytes"] == 20_000
    assert got["link_uplink_mbit_mean"] == pytest.approx(0.5) and got["link_seconds"] == 20.0
    assert got["ledger_bytes_sent"] == 8024 and got["link_uplink_dropped_packets"] == 4
    assert got["link_events"] == log["events"]


def test_report_folder_has_the_profile_plot_and_the_summary(tmp_path):
    rows = [{"slot": 500 + k, "x": k % 2, "power_w": 0.2 if k % 2 else None, "stamp_s": 50.0 + 0.1 * k,
             "source": "image" if k % 2 else "render"} for k in range(12)]
    summary = {"slots": 12, "energy_ratio_vs_upload_all": 2.5}
    write_report(tmp_path / "report", rows, summary)
    assert (tmp_path / "report" / "profile_x_p.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert json.loads((tmp_path / "report" / "summary.json").read_text()) == summary
    assert not (tmp_path / "report" / "mr_strip.png").exists()  # no run.mcap, no strip


def test_round_starts_where_the_radio_round_slot_is_zero_else_where_the_key_moved():
    def row(round_slot, a_m=-1.0):
        return {"round_slot": round_slot, "pose_a_m": a_m, "pose_b_m": -1.1, "pose_theta_rad": 0.0,
                "source": "image"}

    # the ledger's round slots reached the server from round slot 2 on (row 7): the round starts at row 5
    assert first_round_row([row(None)] * 5 + [row(-1)] * 2 + [row(2), row(3)]) == 5
    assert first_round_row([row(None)] * 3 + [row(None, -0.9)]) == 3  # no round slots: the first moved key
    assert first_round_row([row(None)] * 4) is None


def test_truth_frames_round_trip_by_capture_stamp_and_prune(tmp_path):
    writer = TruthFrameWriter(tmp_path, keep=3)
    stamps = [1_795_000_000_123_456_789 + k * 100_000_000 for k in range(5)]
    for k, stamp in enumerate(stamps):
        writer.put(stamp, np.full((4, 6, 3), k, np.uint8))
    assert len(list(tmp_path.glob("*.npy"))) == 3 and not list(tmp_path.glob("*.tmp"))
    reader = TruthFrameReader(tmp_path)
    # the robot's ledger carries the stamp as float seconds: matched to the microsecond
    got = reader.frame(stamps[4] / 1e9, 0)
    assert got is not None and got.shape == (4, 6, 3) and int(got[0, 0, 0]) == 4
    assert reader.frame(stamps[0] / 1e9, 0) is None  # pruned
    assert reader.frame(stamps[3] / 1e9 + 0.01, 0) is None  # no frame at that stamp
    # without a stamp: the newest frame captured by 5 ms after the slot start
    assert int(reader.frame(None, stamps[3] + 1_000_000)[0, 0, 0]) == 3
    assert reader.frame(None, stamps[0]) is None
    assert TruthFrameReader(tmp_path / "missing").frame(None, stamps[4]) is None
