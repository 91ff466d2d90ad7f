"""Launch ``Node`` actions from the process list (:mod:`gsrmr_sim.sim_stack`): one mapping for every launch file.

Kept apart from :mod:`gsrmr_sim.sim_stack`, which non-launch code imports, so that only launch files load
``launch_ros`` (docs/architecture.md, "One pipeline each"). SROS2 with ``keystore:=``: docs/security.md.
"""

from __future__ import annotations

import os
from typing import Any

from launch_ros.actions import Node

from gsrmr_sim.sim_stack import ProcessSpec, nice_prefix

PACKAGE = "gsrmr"


def enclave(node_name: str) -> str:
    """The SROS2 enclave of a node: ``/gsrmr/<name without gsrmr_>`` (``gsrmr_robot`` → ``/gsrmr/robot``), the
    paths config/security/policy.xml grants (robot.launch.py and server.launch.py follow the same rule)."""
    return "/gsrmr/" + node_name.removeprefix("gsrmr_")


def security_arguments(node_name: str, keystore: str) -> dict[str, Any]:
    """The ``Node`` keyword arguments that run ``node_name`` enforced in its enclave of ``keystore``: ``--enclave``
    and ROS_SECURITY_KEYSTORE / ROS_SECURITY_ENABLE=true / ROS_SECURITY_STRATEGY=Enforce (a node whose enclave
    is missing or refused does not start); none without a keystore."""
    if not keystore:
        return {}
    return {"ros_arguments": ["--enclave", enclave(node_name)],
            "additional_env": {"ROS_SECURITY_KEYSTORE": os.path.abspath(os.path.expanduser(keystore)),
                               "ROS_SECURITY_ENABLE": "true", "ROS_SECURITY_STRATEGY": "Enforce"}}


def node_arguments(spec: ProcessSpec, namespace: str | None = None, keystore: str = "") -> dict[str, Any]:
    """The ``launch_ros.actions.Node`` keyword arguments of ``spec``: its executable, node name, arguments,
    parameter files then its overrides (last: they win, as in :func:`~gsrmr_sim.sim_stack.command_line`),
    remappings, niceness prefix, and ``namespace`` (default: the spec's own), output on the screen; with a
    ``keystore``, its enclave (:func:`security_arguments`)."""
    return {"package": PACKAGE, "executable": spec.executable, "name": spec.name,
            "namespace": spec.namespace if namespace is None else namespace, "output": "screen",
            "arguments": list(spec.arguments),
            "parameters": [*spec.param_files, spec.params] if spec.params else list(spec.param_files),
            "remappings": list(spec.remappings), "prefix": " ".join(nice_prefix(spec)) or None,
            **security_arguments(spec.name, keystore)}


def launch_node(spec: ProcessSpec, namespace: str | None = None, keystore: str = "") -> Node:
    """``spec`` as a launch ``Node`` (:func:`node_arguments`)."""
    return Node(**node_arguments(spec, namespace, keystore))
