"""Which topics of a bag are the camera's colour images, its calibration and its aligned depth, by the rules of
docs/dataset_tool.md, "What it reads" (*Which topic is what*).
"""

from __future__ import annotations

from collections.abc import Mapping
import re

from gsrmr_common.image_decode import COMPRESSED_TYPE, IMAGE_TYPE
from gsrmr_offline.bag_reader import BagTopic

TRANSPORT_SUFFIXES = ("compressed", "compressedDepth", "theora", "zstd", "ffmpeg", "h264")
_DEPTH_NAME = re.compile(r"depth|disparity", re.IGNORECASE)
_INFRARED_COMPONENT = re.compile(r"^(ir|infra\d*|infrared)$", re.IGNORECASE)


def image_topics(topics: Mapping[str, BagTopic]) -> list[BagTopic]:
    """The ``Image`` and ``CompressedImage`` topics, by name."""
    return [t for name, t in sorted(topics.items()) if t.msgtype in (IMAGE_TYPE, COMPRESSED_TYPE)]


def has_depth_name(topic: str) -> bool:
    """Whether a path component of ``topic`` names depth or disparity."""
    return any(_DEPTH_NAME.search(part) for part in topic.split("/") if part)


def has_infrared_name(topic: str) -> bool:
    """Whether a path component of ``topic`` is an infrared camera's (``ir``, ``infra1`` …)."""
    return any(_INFRARED_COMPONENT.match(part) for part in topic.split("/") if part)


def strip_transport(topic: str) -> str:
    """``topic`` without a trailing image_transport suffix (``/cam/image_raw/compressed`` → ``/cam/image_raw``)."""
    head, _, last = topic.rstrip("/").rpartition("/")
    return head if last in TRANSPORT_SUFFIXES and head else topic


def sibling_camera_info(image_topic: str) -> str:
    """The ``camera_info`` topic next to an image topic: the topic without its transport suffix, its last
    component replaced by ``camera_info`` (``/camera/color/image_raw/compressed`` → ``/camera/color/camera_info``)."""
    base = strip_transport(image_topic)
    head, _, _last = base.rstrip("/").rpartition("/")
    return f"{head}/camera_info"


def describe_topics(topics: list[BagTopic]) -> str:
    """``/a (sensor_msgs/msg/Image, 40 msgs), …`` — or ``none`` — for messages."""
    return ", ".join(f"{t.name} ({t.msgtype}, {t.count} msgs)" for t in topics) or "none"
