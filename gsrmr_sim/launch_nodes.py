"""Launch ``Node`` actions from the process list (:mod:`gsrmr_sim.sim_stack`): one mapping for every launch file.

``sim.launch.py`` and ``fleet.launch.py`` turn each :class:`~gsrmr_sim.sim_stack.ProcessSpec` into a
``launch_ros`` ``Node`` here; the demo and the tests run the same specs as plain processes
(:func:`gsrmr_sim.sim_stack.command_line`). Kept apart from :mod:`gsrmr_sim.sim_stack`, which non-launch code
imports, so only launch files load ``launch_ros``.
"""

from __future__ import annotations

from typing import Any

from launch_ros.actions import Node

from gsrmr_sim.sim_stack import ProcessSpec, nice_prefix

PACKAGE = "gsrmr"


def node_arguments(spec: ProcessSpec, namespace: str | None = None) -> dict[str, Any]:
    """The ``launch_ros.actions.Node`` keyword arguments of ``spec``: its executable, node name, arguments,
    parameter files then its overrides (last: they win, as in :func:`~gsrmr_sim.sim_stack.command_line`),
    remappings, niceness prefix, and ``namespace`` (default: the spec's own), output on the screen."""
    return {"package": PACKAGE, "executable": spec.executable, "name": spec.name,
            "namespace": spec.namespace if namespace is None else namespace, "output": "screen",
            "arguments": list(spec.arguments),
            "parameters": [*spec.param_files, spec.params] if spec.params else list(spec.param_files),
            "remappings": list(spec.remappings), "prefix": " ".join(nice_prefix(spec)) or None}


def launch_node(spec: ProcessSpec, namespace: str | None = None) -> Node:
    """``spec`` as a launch ``Node`` (:func:`node_arguments`)."""
    return Node(**node_arguments(spec, namespace))
