"""Parameter changes during a round, made as an operator makes them: ``ros2 param set`` (``gsrmr-demo --swap-model``).

A :class:`ParamEvent` runs ``ros2 param set /NODE NAME VALUE`` in the stack's ROS domain once the round has composed
``at_slot`` slots, without waiting for it; the hot swap of a model and of a seed loss map it makes:
docs/model_update.md, "In the simulation".
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
import re
import subprocess
import sys

from gsrmr_sim.supervisor import OWN_PROCESS_GROUP

#: The niceness an operator's ``ros2 param set`` runs at beside the round (:meth:`ParamEvent.start`); on hardware
#: run it the same way on the server's machine (``nice -n 10 ros2 param set …``), or from another one.
OPERATOR_NICE = 10
#: Seconds the CLI spins to discover the node before it sets the parameter (``--spin-time``; :meth:`ParamEvent.argv`).
DISCOVERY_SPIN_S = 5.0

#: The server's log line of a swap (gsrmr_server.server_node): "model swapped in at slot N: PATH (…)".
SWAP_LINE = re.compile(r"model swapped in at slot (\d+): (\S+)")
#: The scheduler's log line of a new seed map (gsrmr_scheduler.scheduler_node):
#: "loss map re-seeded from PATH (N cells)".
RESEED_LINE = re.compile(r"loss map re-seeded from (\S+) \((\d+) cells\)")


def ros2_cli() -> str:
    """The ``ros2`` command of this environment (beside the interpreter), else as found on PATH."""
    beside = Path(sys.executable).parent / "ros2"
    return str(beside) if beside.exists() else "ros2"


@dataclass(frozen=True)
class ParamEvent:
    """``ros2 param set /node name value`` once the round has composed ``at_slot`` slots."""

    at_slot: int
    node: str
    name: str
    value: str

    def argv(self) -> list[str]:
        """The command line: no daemon (nothing outlives the round), so the CLI discovers the graph itself, for
        :data:`DISCOVERY_SPIN_S` (ros2cli's default, 0.5 s, missed the node in 3 of 10 sets at nice 10 beside a
        round: "Node not found")."""
        return [ros2_cli(), "param", "set", "--no-daemon", "--spin-time", f"{DISCOVERY_SPIN_S:g}",
                f"/{self.node.lstrip('/')}", self.name, self.value]

    def start(self, env: dict[str, str], log_path: Path) -> subprocess.Popen:
        """Start the command in ``env`` (the stack's: its ROS domain), its output to ``log_path``, at
        :data:`OPERATOR_NICE`: on the 2 cores the round's nodes share, an operator's CLI (a Python process that
        imports rclpy and discovers the graph for ~3 s) must not take the CPU the slot path needs (one run made a
        slot 133 ms late while two CLIs started at normal priority, docs/results.md)."""
        log_path.parent.mkdir(parents=True, exist_ok=True)
        with open(log_path, "w") as out:
            return subprocess.Popen(["nice", "-n", str(OPERATOR_NICE), *self.argv()], env=env, stdout=out,
                                    stderr=subprocess.STDOUT, **OWN_PROCESS_GROUP)

    def describe(self) -> str:
        """``ros2 param set /gsrmr_server model_path v1.ply`` (the runner's log)."""
        return f"ros2 param set /{self.node.lstrip('/')} {self.name} {self.value}"

    def as_dict(self) -> dict:
        """The event as the report's ``param_events`` list has it."""
        return {"at_slot": self.at_slot, "node": self.node, "name": self.name, "value": self.value}


def _file_at_slot(text: str, option: str, what: str) -> tuple[Path, int]:
    """``"FILE@SLOT"`` → (FILE absolute, SLOT); ValueError for anything else, or a file that does not exist."""
    path, sep, at = text.rpartition("@")
    if not (sep and path and at.isdigit()):
        raise ValueError(f"{option} {text!r}: expected {what}@SLOT")
    file = Path(path).expanduser().resolve()
    if not file.is_file():
        raise ValueError(f"{option} {text!r}: {file} is no file")
    return file, int(at)


def swap_model_event(text: str) -> ParamEvent:
    """``"MODEL.ply@SLOT"`` → the server's ``model_path`` set to MODEL.ply (absolute) at round slot SLOT.
    ValueError for anything else, or a file that does not exist."""
    model, at = _file_at_slot(text, "--swap-model", "MODEL.ply")
    return ParamEvent(at, "gsrmr_server", "model_path", str(model))


def swap_loss_map_event(text: str) -> ParamEvent:
    """``"MAP.json@SLOT"`` → the scheduler's ``loss_map_file`` set to MAP.json (absolute) at round slot SLOT (the
    scheduler reads and checks the file itself, and refuses one that is no loss map). ValueError as
    :func:`swap_model_event`."""
    loss_map, at = _file_at_slot(text, "--swap-loss-map", "MAP.json")
    return ParamEvent(at, "gsrmr_scheduler", "loss_map_file", str(loss_map))


def swap_slots(server_log: str) -> list[dict]:
    """The swaps a server log reports: ``[{"slot": N, "path": PATH}, …]`` (N the server's slot index)."""
    return [{"slot": int(m.group(1)), "path": m.group(2).rstrip(":")} for m in SWAP_LINE.finditer(server_log)]


def reseeds(scheduler_log: str) -> list[dict]:
    """The seed maps a scheduler log reports taking: ``[{"path": PATH, "cells": N}, …]``."""
    return [{"path": m.group(1), "cells": int(m.group(2))} for m in RESEED_LINE.finditer(scheduler_log)]


def swap_summary(param_log: list[dict], server_log: str, rows: list[dict], slot_s: float, around: int = 5,
                 scheduler_log: str = "") -> dict:
    """The report's figures of the swaps in a round: ``param_events`` (each ``ros2 param set``: its round slot, exit
    code, answer), ``model_swaps`` (each swap the server logged: its slot, the round slot it is (None: outside the
    scored rows), the model, and how many of the ``2·around + 1`` scored slots around it were on time:
    ``latency_ms`` ≤ ``slot_s``) and ``loss_map_reseeds`` (each seed map the scheduler logged taking)."""
    index = {int(r["slot"]): i for i, r in enumerate(rows)}
    swaps = []
    for swap in swap_slots(server_log):
        i = index.get(swap["slot"])
        near = rows[max(0, i - around):i + around + 1] if i is not None else []
        on_time = sum(1 for r in near if float(r["latency_ms"]) <= 1e3 * slot_s)
        swaps.append({**swap, "round_slot": i, "on_time_around": f"{on_time}/{len(near)}"})
    return {"param_events": list(param_log), "model_swaps": swaps, "loss_map_reseeds": reseeds(scheduler_log)}
