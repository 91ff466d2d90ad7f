"""The robot's image writer and its acknowledgements: the uplink hold-back waits for them only while every matched
reader of the image topic is one of ``image_readers`` (else the throughput model of
:class:`~gsrmr_robot.uplink_backlog.UplinkBacklog` times the images). ROS side of the backlog."""

from __future__ import annotations

from collections.abc import Iterable
import threading

from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.publisher import Publisher

from gsrmr_common.writer_admission import join_node_name, resolve_writer_name
from gsrmr_robot.uplink_backlog import UplinkBacklog

#: While an image is unacknowledged, the writer's acknowledgements are polled this often [s].
ACK_POLL_S = 0.005


class ImageAcks:
    """Books each image's acknowledgement in ``backlog``; checks the image topic's readers once a second."""

    def __init__(self, node: Node, publisher: Publisher, image_readers: Iterable[str], backlog: UplinkBacklog,
                 lock: threading.Lock) -> None:
        self.node, self.publisher, self.backlog, self._lock = node, publisher, backlog, lock
        self.known = frozenset(resolve_writer_name(r, node.get_namespace()) for r in image_readers)
        self.stranger_readers: tuple[str, ...] = ()  # readers of the image topic that are not image_readers
        node.create_timer(1.0, self._check_readers)
        self._timer = node.create_timer(ACK_POLL_S, self._poll)
        self._timer.cancel()

    def sent(self, bits: int) -> None:
        """An image of ``bits`` was published now: its acknowledgement is awaited."""
        self.backlog.sent(bits, self.node.get_clock().now().nanoseconds / 1e9)
        if self._timer.is_canceled():
            self._timer.reset()

    def _poll(self) -> None:
        """Every image published so far acknowledged by every matched reader: book the delay, stop polling."""
        if not self.backlog.waiting or not self.backlog.acks_trusted:  # untrusted: the throughput model times it
            self._timer.cancel()
            return
        if self.publisher.wait_for_all_acked(Duration(seconds=0)):
            self.backlog.acked(self.node.get_clock().now().nanoseconds / 1e9)
            self._timer.cancel()

    def _check_readers(self) -> None:
        """Trust the acknowledgements only while every matched reader is one of ``image_readers``."""
        readers = {join_node_name(i.node_namespace, i.node_name)
                   for i in self.node.get_subscriptions_info_by_topic(self.publisher.topic_name)}
        strangers = tuple(sorted(readers - self.known))
        if strangers != self.stranger_readers:
            self.node.get_logger().warning(
                f"image readers not in image_readers: {', '.join(strangers)} — their acknowledgements are not waited "
                "for: the hold-back times images by the measured throughput" if strangers else
                "every image reader is a known one again: the hold-back follows the acknowledgements")
        self.stranger_readers = strangers
        with self._lock:
            self.backlog.acks_trusted = not strangers
        if not strangers and self.backlog.waiting and self._timer.is_canceled():
            self._timer.reset()
