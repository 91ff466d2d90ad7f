"""Which topics of a bag are the camera's colour images, its calibration and its aligned depth.

The rules (also in docs/dataset_tool.md):

* **image topics**: every ``sensor_msgs/Image`` or ``sensor_msgs/CompressedImage`` topic;
* **depth topic**: a name with a path component containing ``depth`` or ``disparity`` (``/camera/depth/
  image_raw``, ``/camera/aligned_depth_to_color/image_raw/compressedDepth``), or whose first message is depth
  (``16UC1``, ``mono16``, ``32FC1``, ``compressedDepth``: :func:`gsrmr_common.image_decode.is_depth_message`);
* **colour topic**: an image topic that is not depth and not infrared (a path component ``ir``, ``infra``,
  ``infra1``, ``infra2``, ``infrared``); the bag's only one is used when no topic is given — or, when the colour
  topics are one camera's transports (``…/image_raw`` and ``…/image_raw/compressed``), the uncompressed one;
* **calibration topic**: the image topic's sibling ``camera_info`` — the image topic without its transport
  suffix (``compressed``, ``compressedDepth``, ``theora``, ``zstd``, ``ffmpeg``, ``h264``), its last component
  replaced by ``camera_info`` (``/camera/color/image_raw/compressed`` → ``/camera/color/camera_info``);
* **aligned depth** (auto-detected): a depth topic whose first message is in the colour images' frame
  (``header.frame_id``, i.e. registered to the colour camera, as ``aligned_depth_to_color`` and
  ``depth_registered`` are) — of several, an uncompressed ``Image`` before a compressed one, then by name.
  Its size must match the colour camera's (checked by the dataset tool).
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
    """The ``camera_info`` topic next to an image topic (module docstring for the rule)."""
    base = strip_transport(image_topic)
    head, _, _last = base.rstrip("/").rpartition("/")
    return f"{head}/camera_info"


def describe_topics(topics: list[BagTopic]) -> str:
    """``/a (sensor_msgs/msg/Image, 40 msgs), …`` — or ``none`` — for messages."""
    return ", ".join(f"{t.name} ({t.msgtype}, {t.count} msgs)" for t in topics) or "none"
