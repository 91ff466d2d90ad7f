"""The model swap (gsrmr_server/model_swap.py): loaded off the composing thread, handed over once, the newest
request wins, a failed load keeps the model in use."""

from __future__ import annotations

import threading

from gsrmr_server.model_swap import ModelSwap


def test_a_loaded_model_is_taken_once_at_the_next_boundary():
    gate = threading.Event()

    def load(path: str) -> str:
        gate.wait(5.0)
        return f"model of {path}"

    swap = ModelSwap(load)
    swap.in_use = "a.ply"
    thread = swap.request("b.ply")
    assert swap.take() is None and swap.loading == "b.ply"  # still loading: the slot keeps its model
    gate.set()
    thread.join(5.0)
    got = swap.take()
    assert got is not None and (got.model, got.path) == ("model of b.ply", "b.ply") and got.load_s >= 0.0
    assert swap.take() is None and swap.in_use == "b.ply" and swap.swaps == 1 and swap.loading == ""


def test_the_newest_request_wins_and_a_failed_load_keeps_the_model_in_use():
    release = {"old.ply": threading.Event(), "new.ply": threading.Event()}

    def load(path: str) -> str:
        release[path].wait(5.0)
        return path

    swap = ModelSwap(load)
    old, new = swap.request("old.ply"), swap.request("new.ply")
    release["new.ply"].set()
    new.join(5.0)
    release["old.ply"].set()  # the superseded load finishes last: dropped
    old.join(5.0)
    assert swap.take().path == "new.ply" and swap.take() is None

    def broken(path: str) -> str:
        raise ValueError("not a 3DGS .ply")

    failing = ModelSwap(broken)
    failing.in_use = "a.ply"
    failing.request("bad.ply").join(5.0)
    assert failing.take() is None and failing.in_use == "a.ply" and failing.swaps == 0
    assert failing.error == "bad.ply: ValueError: not a 3DGS .ply" and failing.loading == ""
