"""Small rclpy helpers every gsrmr node uses: a main() wrapper and parameter declaration.

Imports rclpy; keep pure logic elsewhere.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
import sys
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
import rclpy
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.node import Node

from gsrmr_common.interrupts import CLEANUP, POLICY, RUNNING, START


def run_node(factory: Callable[[], Node], args: Sequence[str] | None = None, *, threads: int = 1) -> int:
    """Init rclpy, build the node, spin until SIGINT/SIGTERM or shutdown, clean up; return an exit code.

    The pattern of ``ros2/examples``, hardened for a terminal's Ctrl-C under ``ros2 launch`` (see
    :mod:`gsrmr_common.interrupts`): an interrupt while the node is being built ends start-up at once,
    one while spinning ends the spin through rclpy's handler, and the signals that follow (``launch``
    forwards its own SIGINT) do not cut the clean-up short. Every such stop exits with code 0.
    ``threads`` > 1 spins a MultiThreadedExecutor, so callbacks in different callback groups run
    concurrently (a node whose slot work takes tens of milliseconds still receives messages meanwhile).
    """
    argv = list(sys.argv if args is None else args)
    node: Node | None = None
    POLICY.install()
    POLICY.enter(START)
    try:
        rclpy.init(args=argv)
        node = factory()
        executor = MultiThreadedExecutor(num_threads=threads) if threads > 1 else None
        POLICY.enter(RUNNING)
        rclpy.spin(node, executor=executor)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RuntimeError:
        # SIGINT shuts the context down while the executor may be taking a message, or while the factory
        # still creates entities; rclpy then raises a RuntimeError instead of ExternalShutdownException.
        # Only a real error (the context still up) re-raises.
        if rclpy.ok():
            raise
    finally:
        POLICY.enter(CLEANUP)
        if node is not None:
            on_shutdown = getattr(node, "on_shutdown", None)
            if callable(on_shutdown):
                on_shutdown()
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


def declare(node: Node, name: str, default: Any, description: str, *, min_value: float | None = None,
            max_value: float | None = None, read_only: bool = False, constraints: str = "") -> Any:
    """Declare a parameter with a descriptor (description, range) and return its current value.

    Ranges are enforced by rclpy both for launch-time overrides and for later ``set_parameters``
    calls (the request is refused with a reason naming the range).
    """
    descriptor = ParameterDescriptor(description=description, read_only=read_only,
                                     additional_constraints=constraints)
    if min_value is not None or max_value is not None:
        if isinstance(default, bool):
            raise TypeError(f"parameter {name}: a bool takes no range")
        if isinstance(default, int):
            lo = int(min_value) if min_value is not None else -(2**62)
            hi = int(max_value) if max_value is not None else 2**62
            descriptor.integer_range = [IntegerRange(from_value=lo, to_value=hi, step=0)]
        else:
            lo_f = float(min_value) if min_value is not None else -sys.float_info.max
            hi_f = float(max_value) if max_value is not None else sys.float_info.max
            descriptor.floating_point_range = [FloatingPointRange(from_value=lo_f, to_value=hi_f, step=0.0)]
    return node.declare_parameter(name, default, descriptor).value
