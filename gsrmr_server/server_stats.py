"""The server node's running figures (pure, no ROS): slots composed and on time, where r̂ came from, latency
and composition stage times, computed once (:meth:`ServerStats.summary`) for ``/diagnostics``
(:func:`diagnostic_report`) and for ``server_summary.json`` on shutdown.
"""

from __future__ import annotations

from collections import Counter, deque
from collections.abc import Mapping
import json
from typing import Any

import numpy as np

from gsrmr_server.render_intrinsics import RenderIntrinsics


class ServerStats:
    """Counts over the whole run; latency and stage times over the last ``history`` slots."""

    def __init__(self, slot_s: float, history: int = 1000) -> None:
        self.slot_s = float(slot_s)
        self.history = int(history)
        self.slots = self.slots_on_time = 0
        self.sources: Counter[str] = Counter()
        self.latencies_ms: deque[float] = deque(maxlen=self.history)  # slot start → m̂ published
        self.stage_ms: dict[str, deque[float]] = {}  # composition stage → its times (MRComposer timings)

    def record(self, latency_ms: float, source: str, timings_ms: Mapping[str, float]) -> None:
        """One composed slot: published ``latency_ms`` after its start, r̂ from ``source``, its stage times."""
        self.slots += 1
        self.slots_on_time += int(latency_ms <= 1e3 * self.slot_s)
        self.sources[str(source)] += 1
        self.latencies_ms.append(float(latency_ms))
        for stage, ms in timings_ms.items():
            self.stage_ms.setdefault(stage, deque(maxlen=self.history)).append(float(ms))

    def summary(self, faults: Mapping[str, int]) -> dict[str, Any]:
        """The figures as JSON-ready values: ``slots``, ``slots_on_time``, ``sources``, ``faults`` (the uplink's
        counters), ``compose_ms_p50`` (median per stage, ms), ``latency_ms_p50`` and ``latency_ms_p99``."""
        lat = np.asarray(self.latencies_ms) if self.latencies_ms else np.zeros(1)
        return {"slots": self.slots, "slots_on_time": self.slots_on_time, "sources": dict(self.sources),
                "faults": {str(k): int(v) for k, v in faults.items()},
                "compose_ms_p50": {k: round(float(np.median(v)), 2) for k, v in self.stage_ms.items() if v},
                "latency_ms_p50": float(np.percentile(lat, 50)), "latency_ms_p99": float(np.percentile(lat, 99))}


def diagnostic_report(summary: Mapping[str, Any], camera: RenderIntrinsics) -> tuple[dict[str, Any], list[str]]:
    """The server's ``/diagnostics`` status from a :meth:`ServerStats.summary` (floats to 0.01, mappings as
    JSON) and the render intrinsics' state: (values, problems — any uplink fault, no or refused camera_info)."""
    values = {k: json.dumps(v) if isinstance(v, Mapping) else round(v, 2) if isinstance(v, float) else v
              for k, v in summary.items()}
    values["camera_info"] = camera.status
    return values, (["uplink faults counted"] if summary["faults"] else []) + camera.problems()
