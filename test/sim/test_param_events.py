"""gsrmr-demo --swap-model (gsrmr_sim/param_events.py): the event, the command it runs, the swaps it reports."""

from __future__ import annotations

import pytest

from gsrmr_sim.param_events import reseeds, swap_loss_map_event, swap_model_event, swap_slots, swap_summary


def test_a_swap_event_sets_the_server_model_path_at_its_round_slot(tmp_path):
    model = tmp_path / "model_v2.ply"
    model.write_bytes(b"ply\n")
    ev = swap_model_event(f"{model}@144")
    assert (ev.at_slot, ev.node, ev.name, ev.value) == (144, "gsrmr_server", "model_path", str(model))
    assert ev.argv()[1:] == ["param", "set", "--no-daemon", "--spin-time", "5", "/gsrmr_server", "model_path",
                             str(model)]
    for bad in (f"{model}", f"{model}@x", "@3", f"{tmp_path / 'missing.ply'}@3"):
        with pytest.raises(ValueError):
            swap_model_event(bad)


def test_the_report_places_each_logged_swap_in_the_round_and_counts_the_slots_on_time_around_it():
    log = ("[INFO] [gsrmr_server]: model swapped in at slot 1005: /m/model_v2.ply (9 Gaussians, loaded in 0.10 s)\n"
           "[INFO] [gsrmr_server]: model swapped in at slot 77: /m/model_v3.ply (9 Gaussians, loaded in 0.10 s)\n")
    assert swap_slots(log) == [{"slot": 1005, "path": "/m/model_v2.ply"}, {"slot": 77, "path": "/m/model_v3.ply"}]
    rows = [{"slot": 1000 + i, "latency_ms": 150.0 if i == 7 else 20.0} for i in range(20)]
    out = swap_summary([{"at_slot": 4}], log, rows, 0.1, around=3)
    assert out["param_events"] == [{"at_slot": 4}]
    assert out["model_swaps"][0] == {"slot": 1005, "path": "/m/model_v2.ply", "round_slot": 5,
                                     "on_time_around": "6/7"}  # slot 1007 late
    assert out["model_swaps"][1]["round_slot"] is None and out["model_swaps"][1]["on_time_around"] == "0/0"


def test_a_loss_map_swap_sets_the_scheduler_loss_map_file_and_the_report_lists_what_it_took(tmp_path):
    loss_map = tmp_path / "loss_map_v2.json"
    loss_map.write_text("{}")
    ev = swap_loss_map_event(f"{loss_map}@150")
    assert (ev.at_slot, ev.node, ev.name, ev.value) == (150, "gsrmr_scheduler", "loss_map_file", str(loss_map))
    for bad in (f"{loss_map}", f"{loss_map}@", f"{tmp_path / 'missing.json'}@3"):
        with pytest.raises(ValueError, match="--swap-loss-map"):
            swap_loss_map_event(bad)
    log = "[INFO] [gsrmr_scheduler]: loss map re-seeded from /m/loss_map_v2.json (31 cells)\n"
    assert reseeds(log) == [{"path": "/m/loss_map_v2.json", "cells": 31}]
    assert swap_summary([], "", [], 0.1, scheduler_log=log)["loss_map_reseeds"] == reseeds(log)
    assert swap_summary([], "", [], 0.1)["loss_map_reseeds"] == []


def test_the_operator_command_runs_below_the_round_nodes_priority(tmp_path, monkeypatch):
    """On the 2 cores the round shares, the CLI must not take the slot path's CPU: it runs at OPERATOR_NICE."""
    import os
    import sys

    from gsrmr_sim.param_events import OPERATOR_NICE, ParamEvent

    monkeypatch.setattr(ParamEvent, "argv", lambda self: [sys.executable, "-c", "import os; print(os.nice(0))"])
    log = tmp_path / "param_set_0.log"
    proc = ParamEvent(1, "gsrmr_server", "model_path", "x.ply").start(dict(os.environ), log)
    assert proc.wait(timeout=30) == 0
    assert int(log.read_text().split()[-1]) == min(19, os.nice(0) + OPERATOR_NICE)  # the kernel caps niceness at 19
