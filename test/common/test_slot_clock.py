"""The slot clock and its two cursors (pure, no ROS): floor vs nearest, phase, deadlines, skip-ahead."""

import pytest

from gsrmr_common.slot_clock import ComposeCursor, SlotClock, SlotTicker, slot_ns

TAU_NS = 100_000_000


def test_slot_length_and_validation():
    assert slot_ns(0.1) == TAU_NS and SlotClock(0.1).slot_len_ns == TAU_NS
    for bad in (0.0, -0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError):
            SlotClock(bad)


def test_floor_for_the_slot_we_are_in_nearest_for_the_slot_a_stamp_names():
    clock = SlotClock(0.1)
    for k in (0, 1, 17_000_000_000):  # 17e9 slots: 54 years of 0.1 s slots, still exact in int
        start = clock.start_ns(k)
        assert clock.slot_at(start) == clock.slot_named(start) == k
        assert clock.slot_at(start + TAU_NS - 1) == k  # the last ns of slot k is still in k
        assert clock.slot_named(start + TAU_NS // 2 - 1) == k  # a stamp a bit late still names k
        assert clock.slot_named(start - TAU_NS // 2) == k  # ... and a bit early (another host's clock)
        assert clock.slot_at(start - 1) == k - 1  # but the time just before k starts is in k − 1
    # the difference matters for a stamp 3 µs early (a float round trip of the slot start)
    assert clock.slot_named(clock.start_ns(42) - 3_000) == 42 and clock.slot_at(clock.start_ns(42) - 3_000) == 41


def test_phase_deadline_and_due_slot():
    clock = SlotClock(0.1)
    now = clock.start_ns(500) + 37_000_000
    assert clock.phase_ns(now) == 37_000_000
    assert clock.phase_ns(clock.start_ns(7)) == 0
    assert clock.deadline_ns(500, 0.03) == clock.start_ns(500) + 30_000_000
    assert clock.due_slot(now, 0.03) == 500  # 37 ms into 500: its 30 ms deadline has passed
    assert clock.due_slot(now, 0.04) == 499  # not yet with a 40 ms one
    assert clock.due_slot(clock.deadline_ns(500, 0.04), 0.04) == 500  # due exactly at the deadline


def test_ticker_runs_each_slot_once_in_order_and_counts_skips():
    clock = SlotClock(0.1)
    ticker = SlotTicker(clock)
    t = clock.start_ns(1000) + 50_000_000
    assert ticker.poll(t) is None  # the first poll only learns where it is: slot 1000 is half over
    assert ticker.poll(t + 10_000_000) is None  # still in 1000
    assert ticker.poll(clock.start_ns(1001) + 1_000_000) == (1001, 0)
    assert ticker.poll(clock.start_ns(1001) + 2_000_000) is None  # never twice
    assert ticker.poll(clock.start_ns(1004)) == (1004, 2)  # a late poll: 1002 and 1003 were skipped
    assert ticker.poll(clock.start_ns(1003)) is None  # a clock that steps back never re-runs a slot


def test_compose_cursor_waits_for_uploads_or_the_deadline_and_never_composes_early():
    clock = SlotClock(0.1)
    cursor = ComposeCursor(clock)
    complete: set[int] = set()
    pick = lambda now, delay=0.03: cursor.next_slot(  # noqa: E731
        now, delay_s=delay, max_backlog_slots=30, complete=complete.__contains__)
    start = clock.start_ns(200)
    assert pick(start + 5_000_000) is None  # the first call starts the cursor at the next slot (201)
    assert cursor.next == cursor.first == 200
    # slot 200 started before the cursor did, so it is only picked once it is due (no uploads known)
    assert pick(start + 20_000_000) is None
    assert pick(start + 30_000_000) == 200  # due at its 30 ms deadline
    assert pick(start + 31_000_000) is None
    # slot 201: complete uploads are composed at once, but not before the slot starts
    complete.add(201)
    assert pick(start + 90_000_000) is None  # 201 has not started yet
    assert pick(clock.start_ns(201) + 1_000_000) == 201
    assert cursor.round_time_s(201) == pytest.approx(0.1)
    # a 2 s stall: the 20 missed slots are composed one per call, in order, without skipping
    now = clock.start_ns(222) + 30_000_000
    got = [pick(now) for _ in range(21)]
    assert got == [*range(202, 223)] and cursor.skips == 0
    # 4.5 s behind (> 30 slots): one skip ahead to the due slot
    now = clock.start_ns(268) + 30_000_000
    assert pick(now) == 268 and cursor.skips == 1 and cursor.next == 269
    # the delay is read at each call: a longer one holds the next slot back
    assert pick(clock.start_ns(269) + 30_000_000, delay=0.05) is None
    assert pick(clock.start_ns(269) + 50_000_000, delay=0.05) == 269
