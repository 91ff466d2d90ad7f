"""Known writers (pure, no ROS): which publisher endpoints a node takes an input topic's messages from.

:class:`WriterGate` joins the graph's publisher endpoints (node name and GID per topic) with each message's writer GID:
admitted, refused, held while discovery trails, alarmed on two endpoints under one listed name, rate-limited per
endpoint. :class:`SeqTracker` keeps the schedule's ``seq`` monotonic per writer endpoint; :class:`FloodBreaker` tells
when a topic is flooded. The rules, the writer lists and their defaults: docs/security.md, "Known writers". Times are
seconds of any monotonic clock; GIDs are the bytes of ``rmw_gid_t`` (16 with Fast DDS).
"""

from __future__ import annotations

from collections import Counter, deque
from collections.abc import Iterable
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

#: The writer-list entry that admits any writer (the topic is open).
ANY_WRITER = "*"
#: Fast DDS reports this name for an endpoint whose node it has not discovered yet.
UNKNOWN_NODE_NAMES = frozenset({"", "_NODE_NAME_UNKNOWN_"})
#: Why a message was refused (the counters' last key).
REFUSAL_REASONS = ("unlisted", "unknown", "rate", "held_over")
#: A topic is flooded when this many of its messages were refused within FLOOD_WINDOW_S (legitimate topics carry
#: 10–20 messages/s; a listed writer is refused only beyond its rate limit, 40/s for the per-slot topics) …
FLOOD_REFUSALS = 200
FLOOD_WINDOW_S = 1.0
#: … and then the node stops reading it for this long [s] (what legitimate writers send meanwhile is lost too): a
#: refused message still costs the node's executor its dispatch, tens of µs, so a 10 kHz flood would take a core;
#: with the reader gone the writer has no one to send to.
FLOOD_PAUSE_S = 1.0


def join_node_name(namespace: str, name: str) -> str:
    """``(namespace, name)`` as the graph reports them → the fully qualified name (``/robot1/gsrmr_robot``)."""
    ns = namespace.rstrip("/")
    return f"{ns}/{name}" if ns.startswith("/") else f"/{ns}/{name}" if ns else f"/{name}"


def resolve_writer_name(entry: str, namespace: str) -> str:
    """A writer-list entry → a fully qualified node name: absolute entries stay, relative ones are resolved in
    ``namespace`` (the reading node's), ``*`` stays ``*``. ValueError for an empty entry or a trailing slash."""
    entry = entry.strip()
    if entry == ANY_WRITER:
        return entry
    if not entry or entry.endswith("/") or "//" in entry:
        raise ValueError(f"writer {entry!r} is no node name (a name, a relative ns/name, an absolute /ns/name or *)")
    if entry.startswith("/"):
        return entry
    ns = namespace.rstrip("/")
    return f"{ns}/{entry}" if ns else f"/{entry}"


def writer_list_problem(name: str, entries: Iterable[str]) -> str | None:
    """Why ``entries`` is no usable writer list of parameter ``name`` (empty, or an entry no node name), or None."""
    entries = list(entries)
    if not entries:
        return f"{name} must name at least one writer node (or * for any)"
    for entry in entries:
        try:
            resolve_writer_name(entry, "/")
        except ValueError as err:
            return f"{name}: {err}"
    return None


class Verdict(Enum):
    """What to do with one received message."""

    ADMIT = "admit"
    REFUSE = "refuse"
    HOLD = "hold"  # the writer's GID is not in the graph yet


@dataclass(frozen=True)
class Endpoint:
    """A publisher endpoint as the graph reports it: its GID and its node's fully qualified name."""

    gid: bytes
    node: str


@dataclass
class RateLimit:
    """A token bucket: ``rate_hz`` sustained, ``burst`` at once (``rate_hz`` ≤ 0: unlimited)."""

    rate_hz: float
    burst: float
    tokens: float = field(init=False)
    stamp_s: float | None = field(default=None, init=False)

    def __post_init__(self) -> None:
        if self.burst < 1:
            raise ValueError("rate limit: burst must be ≥ 1")
        self.tokens = float(self.burst)

    def take(self, now_s: float) -> bool:
        """One message at ``now_s``: True when within the limit (a token taken), False when over it."""
        if self.rate_hz <= 0:
            return True
        if self.stamp_s is not None:
            self.tokens = min(self.burst, self.tokens + (now_s - self.stamp_s) * self.rate_hz)
        self.stamp_s = now_s
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False


@dataclass
class _Topic:
    legit: frozenset[str]  # fully qualified names, or {"*"}
    rate_hz: float
    burst: float
    gids: dict[bytes, str] = field(default_factory=dict)  # gid → node, as the graph last reported
    buckets: dict[bytes, RateLimit] = field(default_factory=dict)

    @property
    def open(self) -> bool:
        return ANY_WRITER in self.legit


@dataclass
class _Held:
    topic: str
    gid: bytes
    item: Any
    since_s: float


def gid_label(gid: bytes) -> str:
    """A GID as a short label for counters when no node name is known (``gid:<first 6 bytes hex>…``)."""
    return f"gid:{bytes(gid)[:6].hex()}…"


class WriterGate:
    """Admission of messages by writer endpoint on a node's input topics (see the module docstring)."""

    def __init__(self, namespace: str = "/", *, hold_s: float = 1.0, hold_max: int = 32) -> None:
        if not hold_s > 0 or hold_max < 1:
            raise ValueError("writer gate: hold_s must be > 0 and hold_max ≥ 1")
        self.namespace = namespace or "/"
        self.hold_s, self.hold_max = float(hold_s), int(hold_max)
        self._topics: dict[str, _Topic] = {}
        self._held: deque[_Held] = deque()
        self.refused: Counter[tuple[str, str, str]] = Counter()  # (topic, writer, reason) → messages
        self.admitted: Counter[str] = Counter()  # topic → messages
        self.alarms: Counter[tuple[str, str]] = Counter()  # (topic, name) → refreshes that saw > 1 endpoint
        self.alarm_gids: dict[tuple[str, str], tuple[str, ...]] = {}  # (topic, name) → the live GIDs (labels)

    # ------------------------------------------------------------------ configuration
    def add_topic(self, topic: str, writers: Iterable[str], *, rate_hz: float = 0.0, burst: float = 10.0) -> None:
        """Gate ``topic``: its legitimate ``writers`` (list entries, resolved in this gate's namespace) and the
        rate limit each writer endpoint gets (``rate_hz`` ≤ 0: none)."""
        legit = frozenset(resolve_writer_name(w, self.namespace) for w in writers)
        if not legit:
            raise ValueError(f"writer gate: {topic} needs at least one writer (or {ANY_WRITER})")
        self._topics[topic] = _Topic(legit, float(rate_hz), float(burst))

    @property
    def topics(self) -> tuple[str, ...]:
        """The gated topics."""
        return tuple(self._topics)

    def legit(self, topic: str) -> frozenset[str]:
        """The fully qualified names of ``topic``'s legitimate writers (``{"*"}``: any)."""
        return self._topics[topic].legit

    # ------------------------------------------------------------------ the graph
    def update(self, topic: str, endpoints: Iterable[Endpoint]) -> None:
        """The publisher endpoints the graph reports for ``topic`` now (replacing the last report): GIDs gone from
        it lose their rate buckets; a listed name with more than one endpoint raises (and counts) an alarm."""
        t = self._topics[topic]
        t.gids = {bytes(e.gid): e.node for e in endpoints}
        for gone in set(t.buckets) - set(t.gids):
            del t.buckets[gone]
        by_name: dict[str, list[bytes]] = {}
        for gid, node in t.gids.items():
            if node in t.legit:
                by_name.setdefault(node, []).append(gid)
        for name in {n for (tp, n) in self.alarm_gids if tp == topic} - set(by_name):
            self.alarm_gids.pop((topic, name), None)
        for name, gids in by_name.items():
            if len(gids) > 1:
                self.alarms[(topic, name)] += 1
                self.alarm_gids[(topic, name)] = tuple(sorted(gid_label(g) for g in gids))
            else:
                self.alarm_gids.pop((topic, name), None)

    def writer_name(self, topic: str, gid: bytes) -> str | None:
        """The node the graph names for ``gid`` on ``topic`` (None: not in the graph, or its name unknown yet)."""
        node = self._topics[topic].gids.get(bytes(gid))
        return None if node is None or node.rsplit("/", 1)[-1] in UNKNOWN_NODE_NAMES else node

    # ------------------------------------------------------------------ messages
    def check(self, topic: str, gid: bytes | None, now_s: float) -> Verdict:
        """The verdict on one message of ``topic`` from ``gid`` at ``now_s`` (a refusal is counted here; a HOLD is
        the caller's to :meth:`hold`). An open topic admits every writer (rate limit still applies)."""
        t = self._topics[topic]
        gid = bytes(gid) if gid is not None else b""
        name = self.writer_name(topic, gid)
        if not t.open:
            if name is None:
                return Verdict.HOLD
            if name not in t.legit:
                self.refused[(topic, name, "unlisted")] += 1
                return Verdict.REFUSE
        bucket = t.buckets.get(gid)
        if bucket is None:
            bucket = t.buckets[gid] = RateLimit(t.rate_hz, t.burst)
        if not bucket.take(now_s):
            self.refused[(topic, name or gid_label(gid), "rate")] += 1
            return Verdict.REFUSE
        self.admitted[topic] += 1
        return Verdict.ADMIT

    def hold(self, topic: str, gid: bytes | None, item: Any, now_s: float) -> None:
        """Keep a message whose writer is not in the graph yet; past ``hold_max`` the oldest is refused
        (``held_over``)."""
        self._held.append(_Held(topic, bytes(gid or b""), item, now_s))
        while len(self._held) > self.hold_max:
            old = self._held.popleft()
            self.refused[(old.topic, gid_label(old.gid), "held_over")] += 1

    def holding(self, topic: str, gid: bytes | None) -> bool:
        """Whether a message of ``topic`` from ``gid`` is held (a later one must not overtake it)."""
        key = bytes(gid or b"")
        return any(h.topic == topic and h.gid == key for h in self._held)

    @property
    def held(self) -> int:
        """Messages waiting for their writer to appear in the graph."""
        return len(self._held)

    def release(self, now_s: float) -> list[tuple[str, Any]]:
        """Re-check the held messages (after a graph refresh, or on a timer): ``(topic, item)`` of those now
        admitted, in arrival order; those refused are counted, those still unknown after ``hold_s`` are refused
        as ``unknown``, the rest stay held."""
        out: list[tuple[str, Any]] = []
        keep: deque[_Held] = deque()
        for h in self._held:
            verdict = self.check(h.topic, h.gid, now_s)
            if verdict is Verdict.ADMIT:
                out.append((h.topic, h.item))
            elif verdict is Verdict.HOLD:
                if now_s - h.since_s >= self.hold_s:
                    self.refused[(h.topic, gid_label(h.gid), "unknown")] += 1
                else:
                    keep.append(h)
        self._held = keep
        return out

    # ------------------------------------------------------------------ reporting
    def refused_by_writer(self) -> dict[str, dict[str, int]]:
        """``{writer: {"<topic> <reason>": messages}}`` of every refusal so far."""
        out: dict[str, dict[str, int]] = {}
        for (topic, writer, reason), n in sorted(list(self.refused.items())):  # a snapshot: callbacks may count on
            out.setdefault(writer, {})[f"{topic} {reason}"] = n
        return out

    def problems(self) -> list[str]:
        """What ``/diagnostics`` warns about: each refused writer by name, each name with two live endpoints."""
        per_writer: Counter[tuple[str, str]] = Counter()
        for (topic, writer, _reason), n in list(self.refused.items()):
            per_writer[(writer, topic)] += n
        out = [f"ignored writer {w} on {t} ({n} messages)" for (w, t), n in sorted(per_writer.items())]
        out += [f"two live endpoints under {name} on {topic}: {', '.join(gids)} (impostor or restart)"
                for (topic, name), gids in sorted(list(self.alarm_gids.items()))]
        return out

    def diagnostic_values(self) -> dict[str, Any]:
        """Counters for ``/diagnostics`` (JSON-able): refused per writer, alarms per name, held now."""
        return {"writers_refused": self.refused_by_writer(),
                "writer_alarms": {f"{name} on {topic}": n for (topic, name), n in sorted(list(self.alarms.items()))},
                "writers_held": self.held}


class SeqTracker:
    """Sequence numbers that must grow per writer endpoint (a restarted writer — a new GID — starts afresh)."""

    def __init__(self, keep: int = 64) -> None:
        self._last: dict[bytes, int] = {}
        self.keep = int(keep)

    def accept(self, gid: bytes | None, seq: int) -> bool:
        """True (and remembered) when ``seq`` is above the last one accepted from ``gid``; False for a repeat or an
        older one (a replay)."""
        return self.check(gid, seq) == "new"

    def check(self, gid: bytes | None, seq: int) -> str:
        """``"new"`` (remembered) when ``seq`` is above the last one accepted from ``gid``; ``"repeat"`` for the
        same ``seq`` again from the same endpoint (a latched sample DDS delivers once more: nothing new, no lie);
        ``"older"`` for one below it (a replay)."""
        key = bytes(gid or b"")
        last = self._last.get(key)
        if last is not None and seq <= last:
            return "repeat" if seq == last else "older"
        self._last.pop(key, None)
        self._last[key] = int(seq)
        while len(self._last) > self.keep:  # forget the writers not heard from longest
            del self._last[next(iter(self._last))]
        return "new"


class FloodBreaker:
    """When a topic's refusals say it is flooded (:data:`FLOOD_REFUSALS` within :data:`FLOOD_WINDOW_S`); counts the
    trips by topic and the writer whose refusal tripped it."""

    def __init__(self, refusals: int = FLOOD_REFUSALS, window_s: float = FLOOD_WINDOW_S,
                 pause_s: float = FLOOD_PAUSE_S) -> None:
        if refusals < 1 or not window_s > 0 or not pause_s > 0:
            raise ValueError("flood breaker: refusals >= 1, window_s and pause_s > 0")
        self.refusals, self.window_s, self.pause_s = int(refusals), float(window_s), float(pause_s)
        self._times: dict[str, deque[float]] = {}
        self.trips: Counter[tuple[str, str]] = Counter()  # (topic, writer) → times the topic was paused

    def refused(self, topic: str, writer: str, now_s: float) -> bool:
        """One refused message of ``topic`` (from ``writer``) at ``now_s``: True when the topic is flooded now (the
        caller pauses it; the window starts afresh)."""
        times = self._times.setdefault(topic, deque())
        times.append(now_s)
        while times and now_s - times[0] > self.window_s:
            times.popleft()
        if len(times) < self.refusals:
            return False
        times.clear()
        self.trips[(topic, writer)] += 1
        return True
