"""The ROS half of the known-writer checks (:mod:`gsrmr_common.writer_admission`): gated subscriptions of one node.

:class:`GatedInputs` subscribes a node's input topics raw, asks the node's
:class:`~gsrmr_common.writer_admission.WriterGate` about each writer GID and deserializes only what is admitted; it
refreshes the gate from the graph and pauses a flooded topic's subscription. :class:`ParameterAudit` lets live
parameters change only with ``live_parameter_changes``, logged and counted. How, how often and at what cost:
docs/security.md, "Known writers" and "Services, parameters, readers".
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterable, Sequence
import json
import time
from typing import Any, TypeVar

from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile
from rclpy.serialization import deserialize_message

from gsrmr_common.node_params import NodeParameters
from gsrmr_common.writer_admission import Endpoint, FloodBreaker, Verdict, WriterGate, join_node_name

#: How the shutdown line of :meth:`GatedInputs.log_summary` starts (a JSON object follows).
SUMMARY_PREFIX = "input checks: "
#: Re-read every gated topic's publishers this often [s].
REFRESH_S = 1.0
#: A message from an unknown GID refreshes its topic at most this often [s].
PROMPT_REFRESH_S = 0.02
#: While messages are held, re-check them this often [s].
HOLD_RECHECK_S = 0.05

Deliver = Callable[[Any, bytes], None]  # (message, writer GID)


P = TypeVar("P", bound=NodeParameters)


class GatedInputs:
    """A node's subscriptions whose messages are admitted by writer (see the module docstring)."""

    def __init__(self, node: Node, *, callback_group: Any = None, hold_s: float = 2.0, hold_max: int = 64) -> None:
        self.node = node
        self.gate = WriterGate(node.get_namespace(), hold_s=hold_s, hold_max=hold_max)
        self._group = callback_group
        self._subs: dict[str, tuple[Any, type, Deliver]] = {}  # gate key → (subscription or None, type, deliver)
        self._qos: dict[str, QoSProfile | int] = {}
        self._names: dict[str, str] = {}  # gate key → the resolved topic name
        self._refreshed_s: dict[str, float] = {}
        self.breaker = FloodBreaker()
        self._paused: dict[str, Any] = {}  # flooded topic → the timer that resubscribes it
        node.create_timer(REFRESH_S, self.refresh, callback_group=callback_group)
        self._hold_timer = node.create_timer(HOLD_RECHECK_S, self._recheck, callback_group=callback_group)
        self._hold_timer.cancel()

    def subscribe(self, kind: type, topic: str, deliver: Deliver, qos: QoSProfile | int, writers: Iterable[str], *,
                  rate_hz: float, burst: float) -> Any:
        """Subscribe ``topic`` (type ``kind``): ``deliver(msg, gid)`` gets each message a listed writer sent, within
        its rate limit (``rate_hz`` sustained per writer endpoint, ``burst`` at once)."""
        self.gate.add_topic(topic, writers, rate_hz=rate_hz, burst=burst)
        self._qos[topic] = qos
        sub = self._create(topic, kind)
        self._subs[topic] = (sub, kind, deliver)
        self._names[topic] = sub.topic_name
        self._refresh_topic(topic, time.monotonic())
        return sub

    def _create(self, topic: str, kind: type) -> Any:
        return self.node.create_subscription(kind, topic, lambda raw, info, key=topic: self._on_raw(key, raw, info),
                                             self._qos[topic], callback_group=self._group, raw=True)

    # ------------------------------------------------------------------ floods
    def _pause(self, topic: str, writer: str) -> None:
        """A flooded topic: drop its subscription (DDS then sends it nothing) and resubscribe after the pause."""
        sub, kind, deliver = self._subs[topic]
        if sub is None:
            return
        self.node.destroy_subscription(sub)
        self._subs[topic] = (None, kind, deliver)
        self._paused[topic] = self.node.create_timer(self.breaker.pause_s, lambda key=topic: self._resume(key),
                                                     callback_group=self._group)
        self.node.get_logger().warning(
            f"{topic} flooded ({self.breaker.refusals} refused messages within {self.breaker.window_s:g} s, the last "
            f"from {writer}): not reading it for {self.breaker.pause_s:g} s", throttle_duration_sec=5.0)

    def _resume(self, topic: str) -> None:
        timer = self._paused.pop(topic, None)
        if timer is not None:
            timer.cancel()
            self.node.destroy_timer(timer)
        _none, kind, deliver = self._subs[topic]
        self._subs[topic] = (self._create(topic, kind), kind, deliver)
        self._refresh_topic(topic, time.monotonic())

    # ------------------------------------------------------------------ graph
    def refresh(self) -> None:
        """Re-read every gated topic's publishers, then re-check the held messages."""
        now = time.monotonic()
        for topic in self._subs:
            self._refresh_topic(topic, now)
        self._recheck()

    def _refresh_topic(self, topic: str, now_s: float) -> None:
        infos = self.node.get_publishers_info_by_topic(self._names[topic])
        self.gate.update(topic, [Endpoint(bytes(i.endpoint_gid), join_node_name(i.node_namespace, i.node_name))
                                 for i in infos])
        self._refreshed_s[topic] = now_s

    def _recheck(self) -> None:
        now = time.monotonic()
        for topic, raw in self.gate.release(now):
            _sub, kind, deliver = self._subs[topic]
            gid, payload = raw
            deliver(deserialize_message(payload, kind), gid)
        if not self.gate.held:
            self._hold_timer.cancel()

    # ------------------------------------------------------------------ messages
    def _on_raw(self, topic: str, payload: bytes, info: dict) -> None:
        gid_info = info.get("publisher_gid") or {}
        gid = bytes(gid_info.get("data", b""))
        now = time.monotonic()
        if self.gate.holding(topic, gid):  # this writer's earlier messages wait for its name: none may overtake them
            if now - self._refreshed_s.get(topic, 0.0) >= PROMPT_REFRESH_S:
                self._refresh_topic(topic, now)
            self._recheck()
            if self.gate.holding(topic, gid):
                self.gate.hold(topic, gid, (gid, payload), now)
                return
        verdict = self.gate.check(topic, gid, now)
        if verdict is Verdict.HOLD and now - self._refreshed_s.get(topic, 0.0) >= PROMPT_REFRESH_S:
            self._refresh_topic(topic, now)  # a writer the graph may know by now
            verdict = self.gate.check(topic, gid, now)
        if verdict is Verdict.ADMIT:
            _sub, kind, deliver = self._subs[topic]
            deliver(deserialize_message(payload, kind), gid)
        elif verdict is Verdict.HOLD:
            self.gate.hold(topic, gid, (gid, payload), now)
            if self._hold_timer.is_canceled():
                self._hold_timer.reset()
        else:
            writer = self.writer_of(topic, gid)
            if self.breaker.refused(topic, writer, now):
                self._pause(topic, writer)

    # ------------------------------------------------------------------ reporting
    def diagnostic_values(self) -> dict[str, Any]:
        """The gate's counters (:meth:`WriterGate.diagnostic_values`) and the floods: ``{"<topic> by <writer>":
        pauses}``."""
        trips = sorted(list(self.breaker.trips.items()))
        return {**self.gate.diagnostic_values(), "floods": {f"{topic} by {writer}": n for (topic, writer), n in trips}}

    def problems(self) -> list[str]:
        """What ``/diagnostics`` warns about: the gate's problems and every flooded topic."""
        return self.gate.problems() + [
            f"{topic} flooded by {writer}: not read for {self.breaker.pause_s:g} s ({n} times)"
            for (topic, writer), n in sorted(list(self.breaker.trips.items()))]

    def log_summary(self, implausible: dict[str, int] | None = None, **extra: Any) -> None:
        """One INFO line at shutdown, ``input checks: {JSON}`` (:data:`SUMMARY_PREFIX`): the writers refused by
        name, the implausible inputs by reason, the writer alarms and ``extra`` counters (a run's log then shows that
        a clean run refused nothing; ``bench/acceptance/demo.py`` sums these lines)."""
        values = self.diagnostic_values()
        values.pop("writers_held", None)
        values["implausible"] = dict(sorted((implausible or {}).items()))
        self.node.get_logger().info(SUMMARY_PREFIX + json.dumps({**values, **extra}, sort_keys=True))

    def writer_of(self, topic: str, gid: bytes) -> str:
        """The node name the graph gives ``gid`` on ``topic`` (for logs), else a GID label."""
        return self.gate.writer_name(topic, gid) or f"gid:{gid[:6].hex()}…"


class ParameterAudit:
    """Live parameter changes of a node: allowed only with ``live_parameter_changes``, logged and counted."""

    def __init__(self, node: Node, allowed: bool) -> None:
        self.node = node
        self.allowed = bool(allowed)
        self.changes: Counter[str] = Counter()
        self.refused: Counter[str] = Counter()

    def refusal(self, names: Iterable[str]) -> str | None:
        """Why a change of ``names`` is refused because live changes are off (None: they are on). rclpy refuses a
        read-only parameter before the on-set callback runs, so ``names`` are live ones."""
        live = list(names)
        if self.allowed or not live:
            return None
        for name in live:
            self.refused[name] += 1
        return (f"parameter changes are off while {self.node.get_name()} runs (live_parameter_changes is false at "
                f"start-up; docs/security.md): {', '.join(live)} not changed")

    def problem(self, params_cls: type[NodeParameters], params: Sequence[Parameter]) -> str | None:
        """Why the on-set callback refuses ``params``: a value ``params_cls`` refuses (type, range, read-only, its
        rules), or live changes are off. None: accepted."""
        for param in params:
            reason = params_cls.change_problem(param.name, param.value)
            if reason:
                return reason
        return self.refusal(param.name for param in params)

    def applied(self, current: P, params: Sequence[Parameter]) -> P:
        """``current`` with the accepted ``params`` (the post-set callback's new values), each change recorded."""
        new = current.with_values({param.name: param.value for param in params})
        self.record({param.name: (getattr(current, param.name, None), getattr(new, param.name, param.value))
                     for param in params})
        return new

    def record(self, changes: dict[str, tuple[Any, Any]]) -> None:
        """Log (WARN) and count accepted changes ``{name: (old, new)}`` — the caller is not known to rclpy's
        on-set callback."""
        for name, (old, new) in changes.items():
            self.changes[name] += 1
            self.node.get_logger().warning(f"parameter {name} changed at run time: {old!r} → {new!r} (caller not "
                                           "known: rclpy's parameter service does not pass it on)")

    def diagnostic_values(self) -> dict[str, Any]:
        """``parameter_changes`` and ``parameter_changes_refused`` by name."""
        return {"parameter_changes": dict(sorted(self.changes.items())),
                "parameter_changes_refused": dict(sorted(self.refused.items()))}
