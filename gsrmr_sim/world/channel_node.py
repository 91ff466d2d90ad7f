"""``gsrmr-sim-channel``: the simulated radio, publishing the true uplink gain of every slot ``lead_s`` before it.

On hardware the radio's driver publishes the same message from its own measurement. The gain:
:class:`~gsrmr_sim.world.true_channel.TrueChannel`; the node: docs/world.md, "Nodes"; parameters:
:class:`SimChannelParameters` and ``config/link.yaml``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from nav_msgs.msg import Odometry
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from std_msgs.msg import Float64MultiArray

from gsrmr_common.interrupts import console_main
from gsrmr_common.link_params import LinkParameters
from gsrmr_common.node_help import Endpoint, NodeInterface, ParameterGroup
from gsrmr_common.node_params import NodeParameters, ros_parameter
from gsrmr_common.pose2d import Pose2D, yaw_from_quaternion
from gsrmr_common.ros_node import aligned_timer, declare_link_budget, declare_parameters, run_node
from gsrmr_common.ros_wire import channel_sample_to_msg
from gsrmr_common.slot_clock import SlotClock
from gsrmr_common.wire import CHANNEL_TOPIC
from gsrmr_sim.limo.mock import GROUND_TRUTH_TOPIC
from gsrmr_sim.world.true_channel import TrueChannel


@dataclass(frozen=True)
class SimChannelParameters(NodeParameters):
    """The simulated radio's own parameters (the link's are config/link.yaml's)."""

    slot_s: float = ros_parameter(0.1, "Slot length τ [s]", min_value=1e-3, max_value=10.0, read_only=True)
    lead_s: float = ros_parameter(0.04, "Publish slot t's gain this long before t starts [s]", min_value=0.0,
                                  max_value=0.05, read_only=True)
    odom_topic: str = ros_parameter(GROUND_TRUTH_TOPIC, "True pose (nav_msgs/Odometry, map)", read_only=True)
    publish_log: str = ros_parameter("", "Also write every gain published here (CSV: slot, round_slot, slot_start_ns, "
                                     "published_ns; empty: nowhere)", read_only=True)


#: What ``gsrmr-sim-channel --help`` prints.
INTERFACE = NodeInterface(
    executable="gsrmr-sim-channel", node="gsrmr_sim_channel",
    summary="The simulated radio: publishes the true uplink gain of every slot, lead_s before it starts.",
    subscribes=(Endpoint(GROUND_TRUTH_TOPIC, "nav_msgs/msg/Odometry", "odom_topic: the true pose"),),
    publishes=(Endpoint(CHANNEL_TOPIC, "std_msgs/msg/Float64MultiArray", "[slot, round_slot, gain]"),),
    parameters=(ParameterGroup(SimChannelParameters), ParameterGroup(LinkParameters)))


class ChannelNode(Node):
    """Publishes one :class:`~gsrmr_common.wire.ChannelSample` per slot, ``lead_s`` ahead of it."""

    def __init__(self) -> None:
        super().__init__("gsrmr_sim_channel")
        self.link = declare_link_budget(self)
        p = declare_parameters(self, SimChannelParameters)
        slot_s, self.lead_ns, odom_topic = p.slot_s, int(1e9 * p.lead_s), p.odom_topic
        self.clock = SlotClock(slot_s)
        self.truth = TrueChannel(self.link)
        self.next_slot: int | None = None
        self.published = 0
        self.pub = self.create_publisher(Float64MultiArray, CHANNEL_TOPIC, 10)
        self._log = None  # how late each gain left (p.publish_log): gsrmr_sim.world_lateness
        if p.publish_log:
            Path(p.publish_log).parent.mkdir(parents=True, exist_ok=True)
            self._log = open(p.publish_log, "w", buffering=1 << 16)  # noqa: SIM115 (closed on exit)
            self._log.write("slot,round_slot,slot_start_ns,published_ns\n")
        self.create_subscription(Odometry, odom_topic, self._on_odom, qos_profile_sensor_data)
        # wake once per slot, 1 ms after slot t's lead point (polling at 200 Hz cost 11 % of a core)
        aligned_timer(self, self.clock, (1_000_000 - self.lead_ns) / 1e9, self._tick)
        self.get_logger().info(f"simulated radio: channel seed {self.link.channel_seed}, server at "
                               f"{self.link.server_position_m}, gains on {CHANNEL_TOPIC} {self.lead_ns / 1e6:.0f} ms "
                               "ahead of each slot")

    def _on_odom(self, msg: Odometry) -> None:
        p, q = msg.pose.pose, msg.pose.pose.orientation
        self.truth.observe_pose(Pose2D(p.position.x, p.position.y, yaw_from_quaternion(q.x, q.y, q.z, q.w)))

    def _tick(self) -> None:
        ahead_ns = self.get_clock().now().nanoseconds + self.lead_ns
        upcoming = self.clock.slot_at(ahead_ns)  # the slot that starts within lead_s (or already has)
        if self.next_slot is None:
            self.next_slot = upcoming + 1
            return
        while self.next_slot <= upcoming:
            started = self.truth.round_start_slot is not None
            sample = self.truth.sample(self.next_slot)
            if not started and self.truth.round_start_slot is not None:
                self.get_logger().info(f"robot moving: round clock of the channel starts at slot {sample.slot}")
            self.pub.publish(channel_sample_to_msg(sample))
            if self._log is not None:
                self._log.write(f"{sample.slot},{sample.round_slot},{self.clock.start_ns(sample.slot)},"
                                f"{self.get_clock().now().nanoseconds}\n")
            self.published += 1
            self.next_slot += 1

    def on_shutdown(self) -> None:
        """Close the publish log (called by run_node on exit)."""
        if self._log is not None:
            self._log.close()


@console_main
def main(args: list[str] | None = None) -> int:
    """Console script ``gsrmr-sim-channel``."""
    return run_node(ChannelNode, args, interface=INTERFACE)
