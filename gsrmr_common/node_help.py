"""What a node's ``--help`` prints without starting it: what the node is, its topics, services and parameters.

Each node module holds a :class:`NodeInterface`, which :func:`gsrmr_common.ros_node.run_node` prints for ``-h`` or
``--help``; its parameters come from the dataclasses the node declares, so ``--help`` and ``ros2 param describe``
say the same. Pure, no ROS.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
import textwrap

from gsrmr_common.node_params import NodeParameters

HELP_FLAGS = ("-h", "--help")


@dataclass(frozen=True)
class Endpoint:
    """A topic or service: its name (relative names follow the node's namespace), its type, a short note."""

    name: str
    type: str
    note: str = ""


@dataclass(frozen=True)
class ParameterGroup:
    """The parameters of one :class:`NodeParameters` dataclass, declared under ``prefix`` (e.g. ``camera_mount.``)."""

    params: type[NodeParameters]
    prefix: str = ""

    def names(self) -> list[str]:
        """The declared parameter names, in declaration order."""
        return [self.prefix + f.name for f, _ in self.params.specs()]


@dataclass(frozen=True)
class NodeInterface:
    """A node as its user sees it: executable, default node name, one-line summary, endpoints and parameters."""

    executable: str
    node: str
    summary: str
    subscribes: tuple[Endpoint, ...] = ()
    publishes: tuple[Endpoint, ...] = ()
    services: tuple[Endpoint, ...] = ()
    parameters: tuple[ParameterGroup, ...] = ()
    arguments: str = ""  # command-line arguments of its own, before --ros-args (e.g. the mock LIMO's)

    def parameter_names(self) -> list[str]:
        """Every parameter the node declares (beyond rclpy's own ``use_sim_time`` …)."""
        return [name for group in self.parameters for name in group.names()]


def wants_help(argv: Sequence[str]) -> bool:
    """``-h`` or ``--help`` among the program's own arguments (``argv[1:]`` up to ``--ros-args``)."""
    own = list(argv[1:])
    if "--ros-args" in own:
        own = own[:own.index("--ros-args")]
    return any(a in HELP_FLAGS for a in own)


def _range(spec_min: float | None, spec_max: float | None) -> str:
    if spec_min is None and spec_max is None:
        return ""
    lo = "-inf" if spec_min is None else f"{spec_min:g}"
    hi = "inf" if spec_max is None else f"{spec_max:g}"
    return f" [{lo}, {hi}]"


def _default(value: object) -> str:
    if isinstance(value, tuple):
        return "[" + ", ".join(repr(v) if isinstance(v, str) else f"{v:g}" for v in value) + "]"
    if isinstance(value, float):
        return f"{value:g}"
    return repr(value) if isinstance(value, str) else str(value).lower() if isinstance(value, bool) else str(value)


def _endpoints(title: str, endpoints: Sequence[Endpoint]) -> list[str]:
    if not endpoints:
        return []
    lines = [f"{title}:"]
    for e in endpoints:
        lines.append(f"  {e.name}  ({e.type})" + (f": {e.note}" if e.note else ""))
    return lines


def format_help(interface: NodeInterface, width: int = 100) -> str:
    """The ``--help`` text of ``interface``: usage, summary, topics, services, then every parameter with its type,
    default, range (inclusive), read-only flag and description."""
    usage = f"usage: {interface.executable}"
    usage += f" {interface.arguments}" if interface.arguments else ""
    usage += " [--ros-args [-p NAME:=VALUE]... [--params-file FILE] [-r FROM:=TO]...]"
    lines = [usage, "", *textwrap.wrap(f"{interface.summary} (node name {interface.node!r})", width), ""]
    for title, endpoints in (("Subscribes", interface.subscribes), ("Publishes", interface.publishes),
                             ("Services", interface.services)):
        block = _endpoints(title, endpoints)
        lines += [*block, ""] if block else []
    if interface.parameters:
        lines.append("Parameters (ros2 param describe gives the same; read-only ones are set at start-up):")
        for group in interface.parameters:
            for f, spec in group.params.specs():
                kind = type(f.default).__name__ if not isinstance(f.default, tuple) else "list"
                head = (f"  {group.prefix}{f.name} ({kind}, default {_default(f.default)}"
                        f"{_range(spec.min_value, spec.max_value)}{', read-only' if spec.read_only else ''})")
                lines.append(head)
                lines += textwrap.wrap(spec.description, width, initial_indent="      ", subsequent_indent="      ")
    return "\n".join(lines).rstrip() + "\n"
