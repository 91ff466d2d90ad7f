"""Small rclpy helpers every gsrmr node uses: :func:`run_node` (the main() wrapper), parameter declaration, diagnostics.

Imports rclpy; keep pure logic elsewhere.
"""

from __future__ import annotations

import array
from collections.abc import Callable, Sequence
import sys
import time
from typing import Any, TypeVar

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
import rclpy
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter

from gsrmr_common.camera import CameraMount
from gsrmr_common.interrupts import CLEANUP, POLICY, RUNNING, START, arm_exit_deadline
from gsrmr_common.link_model import LinkBudget
from gsrmr_common.link_params import LinkParameters
from gsrmr_common.mount_params import MOUNT_PREFIX, CameraMountParameters
from gsrmr_common.node_help import NodeInterface, format_help, wants_help
from gsrmr_common.node_params import NodeParameters
from gsrmr_common.slot_clock import SlotClock

P = TypeVar("P", bound=NodeParameters)


#: Seconds the DDS teardown (destroying the node, shutting rclpy down, interpreter exit) may take before the
#: process ends anyway with code 0 (:func:`gsrmr_common.interrupts.arm_exit_deadline`). It takes milliseconds
#: idle; 4 s is inside ``launch``'s 5 s before SIGTERM.
DDS_TEARDOWN_DEADLINE_S = 4.0


def run_node(factory: Callable[[], Node], args: Sequence[str] | None = None, *, interface: NodeInterface,
             threads: int = 1) -> int:
    """Init rclpy, build the node, spin until SIGINT/SIGTERM or shutdown, clean up; return an exit code.

    With ``-h`` or ``--help`` among the program's own arguments it prints ``interface``
    (:func:`~gsrmr_common.node_help.format_help`) and returns 0 without starting anything.

    The pattern of ``ros2/examples``, hardened for a terminal's Ctrl-C under ``ros2 launch`` (see
    :mod:`gsrmr_common.interrupts`): an interrupt while the node is being built ends start-up at once,
    one while spinning ends the spin through rclpy's handler, and the signals that follow (``launch``
    forwards its own SIGINT) do not cut the clean-up short. Every such stop exits with code 0.
    ``threads`` > 1 spins a MultiThreadedExecutor, so callbacks in different callback groups run
    concurrently (a node whose slot work takes tens of milliseconds still receives messages meanwhile).
    """
    argv = list(sys.argv if args is None else args)
    if wants_help(argv):
        print(format_help(interface), end="")
        return 0
    node: Node | None = None
    POLICY.install()
    POLICY.enter(START)
    try:
        rclpy.init(args=argv)
        node = factory()
        executor = MultiThreadedExecutor(num_threads=threads) if threads > 1 else SingleThreadedExecutor()
        executor.add_node(node)
        POLICY.enter(RUNNING)
        # rclpy.spin, in 0.1 s steps: a signal sets POLICY.stop_requested (nothing is raised inside the
        # executor), and the loop ends within a step even if rclpy's own handler did not wake it.
        while rclpy.ok() and not POLICY.stop_requested:
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RuntimeError:
        # SIGINT shuts the context down while the executor may be taking a message, or while the factory
        # still creates entities; rclpy then raises a RuntimeError instead of ExternalShutdownException.
        # Without a signal it is a real error — also one raised before any context exists (rcl refusing to
        # initialise, e.g. SROS2 enforced without the node's enclave: it must exit non-zero and say why).
        if POLICY.received == 0:
            raise
    finally:
        POLICY.enter(CLEANUP)
        if node is not None:
            on_shutdown = getattr(node, "on_shutdown", None)
            if callable(on_shutdown):
                on_shutdown()
        # the node's own clean-up is done; the DDS teardown can livelock inside Fast DDS (interrupts module)
        arm_exit_deadline(DDS_TEARDOWN_DEADLINE_S)
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


def _is_float_default(default: Any) -> bool:
    """A DOUBLE or DOUBLE_ARRAY parameter's default (a float, or a non-empty list/tuple of floats)."""
    if isinstance(default, float):
        return True
    return isinstance(default, (list, tuple)) and bool(default) and all(isinstance(v, float) for v in default)


def _whole_numbers_as_float(value: Any) -> Any:
    """An INTEGER (or INTEGER_ARRAY) value as the DOUBLE (DOUBLE_ARRAY) it stands for; any other value as is."""
    if isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if isinstance(value, (list, tuple, array.array)) and len(value) and all(
            isinstance(v, int) and not isinstance(v, bool) for v in value):
        return [float(v) for v in value]
    return value


def _coerce_whole_numbers_on_set(node: Node) -> None:
    """Once per node: a later ``ros2 param set /node x 1`` (the CLI types ``1`` as INTEGER) of a DOUBLE
    parameter sets 1.0 instead of being refused as the wrong type (an rclpy pre-set callback)."""
    if getattr(node, "_gsrmr_coerces_whole_numbers", False):
        return

    kind = Parameter.Type
    widen = {kind.INTEGER: kind.DOUBLE, kind.INTEGER_ARRAY: kind.DOUBLE_ARRAY}

    def coerce(parameters: list[Parameter]) -> list[Parameter]:
        out = []
        for p in parameters:
            if (p.type_ in widen and node.has_parameter(p.name)
                    and node.get_parameter(p.name).type_ == widen[p.type_]):
                p = Parameter(p.name, value=_whole_numbers_as_float(p.value))
            out.append(p)
        return out

    node.add_pre_set_parameters_callback(coerce)
    node._gsrmr_coerces_whole_numbers = True  # type: ignore[attr-defined]


def declare(node: Node, name: str, default: Any, description: str, *, min_value: float | None = None,
            max_value: float | None = None, read_only: bool = False, constraints: str = "") -> Any:
    """Declare a parameter with a descriptor (description, range) and return its current value.

    Ranges are enforced by rclpy both for launch-time overrides and for later ``set_parameters``
    calls (the request is refused with a reason naming the range).

    A DOUBLE parameter given a whole number (``-p loss_margin:=0``, ``loss_margin: 0`` in a YAML, ``ros2 param
    set … 0``) takes it as that float; rclpy alone refuses it as the wrong type, which at start-up ends the node.
    Any other type mismatch (a string for a number, a float for an INTEGER) is still refused.
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
    if _is_float_default(default):
        _coerce_whole_numbers_on_set(node)
        # rclpy applies a start-up override before any callback could convert it: read it (rclpy keeps the
        # overrides in ``_parameter_overrides``; no public accessor) and declare its float instead.
        override = getattr(node, "_parameter_overrides", {}).get(name)
        if override is not None:
            as_float = _whole_numbers_as_float(override.value)
            if as_float is not override.value:
                return node.declare_parameter(name, as_float, descriptor, ignore_override=True).value
    return node.declare_parameter(name, default, descriptor).value


def declare_parameters(node: Node, params_cls: type[P], prefix: str = "") -> P:
    """Declare every ROS parameter of the dataclass ``params_cls`` (its :func:`~gsrmr_common.node_params.ros_parameter`
    fields, in order: ``prefix`` + name, default and descriptor) and return an instance of the values it starts with.

    Raises ValueError (``"parameter <why>"``) for a start-up value the class's rules refuse. Fields that are
    no ROS parameter (a nested LinkBudget …) keep their defaults: declare them with their own class."""
    values = {}
    for f, spec in params_cls.specs():
        default = list(f.default) if isinstance(f.default, tuple) else f.default
        values[f.name] = declare(node, prefix + f.name, default, spec.description, min_value=spec.min_value,
                                 max_value=spec.max_value, read_only=spec.read_only, constraints=spec.constraints)
    return params_cls().with_values(values)


def diagnostics_msg(node: Node, *, name: str, hardware_id: str, values: dict[str, object],
                    problems: Sequence[str] = (), level: bytes | None = None, message: str | None = None
                    ) -> DiagnosticArray:
    """One ``/diagnostics`` status of ``node``, stamped now: level WARN when there are ``problems`` (else OK)
    unless ``level`` is given, message the problems joined by "; " (or "ok") unless ``message`` is given,
    every value as a string."""
    if level is None:
        level = DiagnosticStatus.WARN if problems else DiagnosticStatus.OK
    status = DiagnosticStatus(level=level, name=name, hardware_id=hardware_id,
                              message=message if message is not None else ("; ".join(problems) or "ok"),
                              values=[KeyValue(key=str(k), value=str(v)) for k, v in values.items()])
    arr = DiagnosticArray(status=[status])
    arr.header.stamp = node.get_clock().now().to_msg()
    return arr


def declare_camera_mount(node: Node) -> CameraMount:
    """Declare the ``camera_mount.*`` parameters (``config/camera_mount.yaml``, loaded into the robot and the
    server: :class:`~gsrmr_common.mount_params.CameraMountParameters`) and return the mount: the pose of
    ``camera_optical_frame`` in ``base_link``."""
    return declare_parameters(node, CameraMountParameters, MOUNT_PREFIX).mount()


def declare_link_budget(node: Node) -> LinkBudget:
    """Declare the uplink parameters (``config/link.yaml``: :class:`~gsrmr_common.link_params.LinkParameters`,
    read-only, with descriptors and ranges) on ``node`` and return the
    :class:`~gsrmr_common.link_model.LinkBudget` they describe (SI units)."""
    return declare_parameters(node, LinkParameters).budget()


def aligned_timer(node: Node, clock: SlotClock, phase_s: float, callback: Callable[[], None]) -> None:
    """Call ``callback`` once per slot of ``clock`` at ``phase_s`` into the slot (e.g. 1 ms after every slot
    start) — instead of polling a clock at 200 Hz (each rclpy wake-up costs ~0.5 ms of CPU).

    Blocks the caller (a node's constructor) until the next such instant (< one slot), then starts one
    periodic timer: rcl timers fire at ``start + k·period`` and never early, so every call is at or just
    after its instant (late by the executor's wake-up). The callback should still work out *which* slot
    is due from the clock, as a late call must do the right thing anyway."""
    period_ns = clock.slot_len_ns
    wait_ns = (round(phase_s * 1e9) - clock.phase_ns(node.get_clock().now().nanoseconds)) % period_ns
    time.sleep(wait_ns / 1e9)
    node.create_timer(clock.slot_s, callback)
