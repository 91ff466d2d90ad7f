"""What the server node takes from the graph, checked (the node's input callbacks hand their messages here).

:class:`ServerInputs` is the plausibility layer behind the admission by writer
(:class:`gsrmr_common.ros_admission.GatedInputs`); its rules: ``docs/security.md``, "Plausibility, even from the
right writer". Each method takes the arrival time ``now_ns`` (ROS time, ns), holds the node's lock while it touches
the books and returns the line to log, if any (the node logs it: rclpy wants one severity per call site).
"""

from __future__ import annotations

import math
import threading
from typing import Any

from geometry_msgs.msg import Vector3Stamped
from sensor_msgs.msg import CompressedImage
from std_msgs.msg import Float64MultiArray

from gsrmr_common.plausibility import Implausible, PoseTrack, ScheduleLimits, ledger_problem, schedule_problem
from gsrmr_common.ros_wire import ledger_from_msg, pose_key_from_msg, schedule_from_msg, stamp_to_ns
from gsrmr_common.slot_clock import SlotClock
from gsrmr_common.wire import MAX_COMPRESSED_BYTES, PoseKey, UplinkFault
from gsrmr_common.writer_admission import SeqTracker
from gsrmr_server.ledger_book import LedgerBook, SlotPlan
from gsrmr_server.uplink import SlotUploads, UplinkAssembler

# what a plausible schedule looks like to the server (the transmit power is the robot's radio's to bound)
_SCHEDULE_LIMITS = ScheduleLimits(max_power_w=float("inf"))


class ServerInputs:
    """The server's checked inputs: pose keys, images, ledger rows and schedules, per slot.

    What is taken lands in :attr:`uplink` (:class:`~gsrmr_server.uplink.UplinkAssembler`: keys, images) and
    :attr:`ledgers` (:class:`~gsrmr_server.ledger_book.LedgerBook`: ledger rows, the schedule), from which the slot
    being composed is taken (:meth:`take`). What is refused is counted: wire faults by
    :class:`~gsrmr_common.wire.UplinkFault` (in :attr:`uplink`), plausibility by reason (:attr:`implausible`).
    """

    def __init__(self, clock: SlotClock, max_speed_mps: float, lock: threading.Lock) -> None:
        self.clock = clock
        self.lock = lock
        self.uplink = UplinkAssembler()
        self.ledgers = LedgerBook()
        self.implausible = Implausible()
        self.poses = PoseTrack(max_speed_mps, clock.slot_s)
        self._schedule_seq = SeqTracker()
        self.composed_slot: int | None = None  # the newest slot taken for composition

    def on_key(self, msg: Vector3Stamped, now_ns: int) -> str | None:
        """A pose key: refused when malformed (wrong frame, invalid stamp) or when it jumps faster than the robot
        drives (``pose_jump``; the warning says what jumped, for a false alarm's diagnosis)."""
        with self.lock:
            try:
                key = pose_key_from_msg(msg, self.clock)
            except ValueError:
                self.uplink.count(UplinkFault.MALFORMED_KEY)
                return None
            last = self.poses.last
            if key.is_valid() and not self.poses.offer(key.slot, key.a_m, key.b_m):
                self.implausible["pose_jump"] += 1  # no relocalisation (yet)
                if last is None:
                    return None
                return (f"pose key refused (pose_jump): slot {key.slot} at ({key.a_m:.3f}, {key.b_m:.3f}) m, "
                        f"{math.hypot(key.a_m - last[1], key.b_m - last[2]):.3f} m from the track's slot {last[0]} "
                        f"({key.slot - last[0]} slots; reach {self.poses.reach_m(key.slot - last[0]):.3f} m)")
            self.uplink.on_key(key, self.clock.slot_at(now_ns), now_ns)
        return None

    def on_image(self, msg: CompressedImage, now_ns: int) -> None:
        """An uploaded JPEG for the slot its stamp names; oversized or unstamped ones are counted, not kept."""
        data = bytes(msg.data)
        with self.lock:
            if len(data) > MAX_COMPRESSED_BYTES:
                self.uplink.count(UplinkFault.OVERSIZED_IMAGE)
                return
            try:
                image_slot = self.clock.slot_named(stamp_to_ns(msg.header.stamp))
            except ValueError:
                self.uplink.count(UplinkFault.MALFORMED_IMAGE)
                return
            self.uplink.on_image(image_slot, data, self.clock.slot_at(now_ns), now_ns)

    def on_schedule(self, msg: Float64MultiArray, gid: bytes, now_ns: int) -> str | None:
        """A schedule from writer endpoint ``gid``: taken when it parses, is plausible (T, slots near now) and is
        newer (seq) than the last one of that endpoint; else counted (the error line is returned when it does not
        parse)."""
        try:
            sched = schedule_from_msg(msg)
        except ValueError as err:
            with self.lock:
                self.implausible["schedule_malformed"] += 1
            return f"schedule refused: {err}"
        reason = schedule_problem(sched, self.clock.slot_at(now_ns), _SCHEDULE_LIMITS)
        if reason is None:
            seq = self._schedule_seq.check(gid, sched.seq)
            if seq == "repeat":  # the same schedule delivered again (latched): nothing new
                return None
            reason = "schedule_seq" if seq == "older" else None
        with self.lock:
            if reason:
                self.implausible[reason] += 1
            else:
                self.ledgers.schedule = sched
        return None

    def on_ledger(self, msg: Float64MultiArray, now_ns: int) -> None:
        """The robot's ledger row: taken once per slot, for a slot near the one being composed (the clock's before
        the first: a replay driving the node faster than real time, ``bench/perf/soak.py --node``, stays near it
        too)."""
        with self.lock:
            try:
                row = ledger_from_msg(msg)
            except ValueError:  # wrong length, or a NaN/inf slot, x or bit count
                self.uplink.count(UplinkFault.MALFORMED_LEDGER)
                return
            near = self.composed_slot if self.composed_slot is not None else self.clock.slot_at(now_ns)
            reason = ledger_problem(row, near)
            if reason is None and self.ledgers.image_sent(row.slot) is not None:
                reason = "ledger_repeat"  # one row per slot: the first stands
            if reason:
                self.implausible[reason] += 1
                return
            self.ledgers.add(row)

    def complete(self, slot: int) -> bool:
        """Its key and its image arrived, or its key and the robot's ledger row saying no image follows."""
        with self.lock:
            return self.uplink.complete(slot, self.ledgers.image_sent(slot))

    def take(self, slot: int) -> tuple[SlotPlan, SlotUploads, PoseKey | None]:
        """Slot ``slot`` for composition (once; the caller holds the lock): the robot's plan for it, its uploads
        and the best pose estimate for it."""
        self.composed_slot = slot if self.composed_slot is None else max(slot, self.composed_slot)
        plan = self.ledgers.take(slot)
        return plan, self.uplink.take(slot, image_expected=plan.image_expected), self.uplink.best_pose(slot)

    def diagnostic_values(self) -> dict[str, Any]:
        """The plausibility refusals by reason and the relocalisations (JSON-able)."""
        return {"implausible": self.implausible.values_for_diagnostics(),
                "relocalisations": self.poses.relocalisations}

    def problems(self) -> list[str]:
        """What ``/diagnostics`` warns about: implausible inputs refused, if any."""
        if not self.implausible:
            return []
        return ["implausible inputs refused: " + ", ".join(f"{k} {n}" for k, n in sorted(self.implausible.items()))]
