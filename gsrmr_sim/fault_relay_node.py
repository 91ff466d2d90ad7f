"""``gsrmr-uplink-relay``: the fault-injecting uplink relay as a ROS node (robot namespace → server namespace).

What it relays, the faults, their counts and its summary: :mod:`gsrmr_sim.fault_relay` and docs/reliability.md.
Parameters: :class:`RelayParameters` (read-only) and one ``<fault>_rate`` per fault (live).
"""

from __future__ import annotations

from dataclasses import dataclass, make_dataclass
import json
from pathlib import Path

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Vector3Stamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from sensor_msgs.msg import CompressedImage

from gsrmr_common.interrupts import console_main
from gsrmr_common.node_help import Endpoint, NodeInterface, ParameterGroup
from gsrmr_common.node_params import NodeParameters, ros_parameter
from gsrmr_common.ros_node import declare_parameters, diagnostics_msg, run_node
from gsrmr_common.ros_wire import IMAGE_UPLOAD_QOS, UPLINK_QOS, ns_to_stamp, stamp_to_ns
from gsrmr_sim.fault_relay import ALL_FAULTS, FaultInjector, FaultRates, Upload


@dataclass(frozen=True)
class RelayParameters(NodeParameters):
    """The relay's read-only parameters (the fault rates are :data:`FaultRateParameters`, live)."""

    input_prefix: str = ros_parameter("/robot", "Namespace the robot publishes its uplink in", read_only=True)
    slot_s: float = ros_parameter(0.1, "Slot length τ [s] (as robot and server)", min_value=0.01, max_value=10.0,
                                  read_only=True)
    seed: int = ros_parameter(0, "Fault RNG seed", min_value=0, max_value=2**31 - 1, read_only=True)
    delay_slots: float = ros_parameter(1.5, "Delay of a 'delay' fault [slots] (> 1)", min_value=1.01,
                                       max_value=100.0, read_only=True)
    stale_slots: int = ros_parameter(5, "Stamp shift of a 'stale' fault [slots]", min_value=1, max_value=1000,
                                     read_only=True)
    summary_path: str = ros_parameter("", "Write the JSON summary here on exit ('' = log only)", read_only=True)


#: One live ``<fault>_rate`` parameter per fault of :class:`FaultRates`, its default that class's.
FaultRateParameters = make_dataclass(
    "FaultRateParameters",
    [(f"{name}_rate", float, ros_parameter(float(getattr(FaultRates(), name)), f"P({name}) per message",
                                           min_value=0.0, max_value=1.0)) for name in ALL_FAULTS],
    bases=(NodeParameters,), frozen=True)

#: What ``gsrmr-uplink-relay --help`` prints.
INTERFACE = NodeInterface(
    executable="gsrmr-uplink-relay", node="gsrmr_uplink_relay",
    summary="Relays the robot's uplink (pose keys and images) from input_prefix into its own namespace, injecting "
            "faults (drop, duplicate, reorder, delay, stale, malformed …) at the given rates.",
    subscribes=(Endpoint("<input_prefix>/uplink/pose_key", "geometry_msgs/msg/Vector3Stamped"),
                Endpoint("<input_prefix>/uplink/image_raw/compressed", "sensor_msgs/msg/CompressedImage")),
    publishes=(Endpoint("uplink/pose_key", "geometry_msgs/msg/Vector3Stamped"),
               Endpoint("uplink/image_raw/compressed", "sensor_msgs/msg/CompressedImage"),
               Endpoint("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")),
    parameters=(ParameterGroup(RelayParameters), ParameterGroup(FaultRateParameters)))


class FaultRelayNode(Node):
    """Relays the robot's uplink into this node's namespace, injecting faults (:mod:`gsrmr_sim.fault_relay`), with
    the robot's and the server's QoS profiles of the two topics."""

    def __init__(self, **node_kwargs) -> None:
        super().__init__("gsrmr_uplink_relay", **node_kwargs)
        p = declare_parameters(self, RelayParameters)
        prefix, slot_s, seed, delay_slots, stale_slots = (p.input_prefix.rstrip("/"), p.slot_s, p.seed, p.delay_slots,
                                                          p.stale_slots)
        self.summary_path = p.summary_path
        rate_values = declare_parameters(self, FaultRateParameters)
        rates = {name: getattr(rate_values, f"{name}_rate") for name in ALL_FAULTS}
        self.injector = FaultInjector(FaultRates(**rates), seed=seed, slot_s=slot_s, delay_slots=delay_slots,
                                      stale_slots=stale_slots)
        self.add_on_set_parameters_callback(self._validate)
        self._pub = {"key": self.create_publisher(Vector3Stamped, "uplink/pose_key", UPLINK_QOS),
                     "image": self.create_publisher(CompressedImage, "uplink/image_raw/compressed", IMAGE_UPLOAD_QOS)}
        self._pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_subscription(Vector3Stamped, f"{prefix}/uplink/pose_key", self._on_key, UPLINK_QOS)
        self.create_subscription(CompressedImage, f"{prefix}/uplink/image_raw/compressed", self._on_image,
                                 IMAGE_UPLOAD_QOS)
        self.create_timer(0.002, self._release)
        self.create_timer(1.0, self._publish_diagnostics)
        self.get_logger().info(f"uplink relay {prefix}/uplink → {self.get_namespace()}: seed {seed}, "
                               f"rates {self.injector.summary()['rates']}")

    def _validate(self, params) -> SetParametersResult:
        """On-set: a new set of rates takes effect at once; rates FaultRates refuses are refused."""
        current = {n: getattr(self.injector.rates, n) for n in ALL_FAULTS}
        for p in params:
            if p.name.endswith("_rate") and p.name[:-5] in current:
                current[p.name[:-5]] = float(p.value)
        try:
            rates = FaultRates(**current)
        except ValueError as err:
            return SetParametersResult(successful=False, reason=str(err))
        self.injector.set_rates(rates)
        return SetParametersResult(successful=True)

    def _now(self) -> int:
        return self.get_clock().now().nanoseconds

    def _stamp(self, msg, kind: str) -> int | None:
        if self._pub[kind].get_subscription_count() == 0:  # nobody to deliver to: no draw, no count
            self.injector.errors[f"{kind}.no_subscriber"] += 1
            return None
        try:
            return stamp_to_ns(msg.header.stamp)
        except ValueError:
            self.injector.errors[f"{kind}.malformed_stamp"] += 1
            return None

    def _on_key(self, msg) -> None:
        stamp = self._stamp(msg, "key")
        if stamp is not None:
            v = msg.vector
            up = Upload("key", stamp, (v.x, v.y, v.z), msg.header.frame_id)
            self._send(self.injector.push(up, self._now()))

    def _on_image(self, msg) -> None:
        stamp = self._stamp(msg, "image")
        if stamp is not None:
            self._fmt = msg.format
            self._send(self.injector.push(Upload("image", stamp, bytes(msg.data), msg.header.frame_id),
                                          self._now()))

    def _release(self) -> None:
        self._send(self.injector.due(self._now()))

    def _send(self, uploads: list[Upload]) -> None:
        for up in uploads:
            if up.kind == "key":
                msg = Vector3Stamped()
                msg.vector.x, msg.vector.y, msg.vector.z = up.data  # type: ignore[misc]
            else:
                msg = CompressedImage(format=getattr(self, "_fmt", "jpeg"), data=up.data)
            msg.header.stamp = ns_to_stamp(up.stamp_ns)
            msg.header.frame_id = up.frame_id
            self._pub[up.kind].publish(msg)

    def _publish_diagnostics(self) -> None:
        s = self.injector.summary()
        values = {**s["injected"], "held": s["held"], "mutation_errors": json.dumps(s["mutation_errors"])}
        self._pub_diag.publish(diagnostics_msg(self, name=f"{self.get_name()}: uplink fault relay",
                                               hardware_id="gsrmr_uplink_relay", values=values,
                                               message="injecting faults"))

    def on_shutdown(self) -> None:
        """Log and write the JSON summary (called by run_node on exit)."""
        text = json.dumps(self.injector.summary(), indent=1, sort_keys=True)
        self.get_logger().info(f"relay summary: {text}")
        if self.summary_path:
            Path(self.summary_path).write_text(text)


@console_main
def main(args: list[str] | None = None) -> int:
    """Console script ``gsrmr-uplink-relay``."""
    return run_node(FaultRelayNode, args, interface=INTERFACE)
