"""The MCAP side of a recording: topics, segments of a running recording, their merge and the salvage of
a crashed one (the layout and the crash-safety rules: ``docs/nodes.md``, "The server's recording").
"""

from __future__ import annotations

from collections.abc import Iterator
import hashlib
import os
from pathlib import Path
import re
from typing import Any

from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from mcap_ros2.decoder import DecoderFactory
import numpy as np

TOPIC_MR_IMAGE = "/gsrmr/mr/image/compressed"
TOPIC_CMD_VEL = "/gsrmr/cmd_vel"
TOPIC_SLOT_LOG = "/gsrmr/slot_log"
# Written by the server through write_message when the robot's calibration arrives (not per slot).
TOPIC_CAMERA_INFO = "/gsrmr/camera_info"
# Written by the server in each slot composed with the robot's image: that image as it arrived (the robot's JPEG, the
# header's stamp the slot start) and the slot's pose key as a geometry_msgs/PoseStamped of base_link in map (x = a_m,
# y = b_m, z = 0, yaw θ) at the same stamp — training data for an update of the model, which
# gsrmr-dataset reads as a bag (--pose-topic, with the camera mount).
TOPIC_RECEIVED_IMAGE = "/gsrmr/received/image/compressed"
TOPIC_RECEIVED_POSE = "/gsrmr/received/pose"
TOPIC_TYPES = {
    TOPIC_MR_IMAGE: "sensor_msgs/msg/CompressedImage",
    TOPIC_CMD_VEL: "geometry_msgs/msg/TwistStamped",
    TOPIC_SLOT_LOG: "std_msgs/msg/String",
}
MCAP_NAME = "run.mcap"
_SEGMENT_RE = re.compile(r"^run-(\d{4,})\.mcap(\.part)?$")


def _encodable(value: Any) -> Any:
    """A generated ROS message as nested dicts for mcap-ros2-support's encoder, which refuses numpy arrays.

    rclpy holds fixed-size numeric arrays (``CameraInfo.k``, ``Odometry`` covariances) as numpy arrays;
    they become lists. ``bytes`` and ``array.array`` (``uint8[]`` data, sequences) pass unchanged.
    """
    fields = getattr(value, "get_fields_and_field_types", None)
    if callable(fields):
        return {name: _encodable(getattr(value, name)) for name in fields()}
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, list):  # sequences of nested messages
        return [_encodable(item) for item in value]
    return value


def _segment_paths(out_dir: Path) -> tuple[list[Path], list[Path]]:
    """(finished segments, unfinished .part segments), each sorted by segment number."""
    done, parts = [], []
    for path in out_dir.iterdir():
        match = _SEGMENT_RE.match(path.name)
        if match:
            (parts if match.group(2) else done).append((int(match.group(1)), path))
    return [p for _, p in sorted(done)], [p for _, p in sorted(parts)]


def _salvage_records(path: Path) -> Iterator[Schema | Channel | Message]:
    """Schemas, channels and messages of a possibly truncated MCAP, up to the first damaged record."""
    with path.open("rb") as f:
        try:
            for record in StreamReader(f, validate_crcs=True).records:
                if isinstance(record, (Schema, Channel, Message)):
                    yield record
        except (McapError, EOFError, ValueError, OSError, RuntimeError, KeyError, IndexError):
            return  # torn or damaged tail: keep what was read so far


def _records(path: Path, salvage: bool) -> Iterator[tuple[Schema | None, Channel, Message]]:
    if not salvage:
        with path.open("rb") as f:
            yield from make_reader(f).iter_messages(log_time_order=False)
        return
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    for record in _salvage_records(path):
        if isinstance(record, Schema):
            schemas[record.id] = record
        elif isinstance(record, Channel):
            channels[record.id] = record
        elif record.channel_id in channels:
            channel = channels[record.channel_id]
            yield schemas.get(channel.schema_id), channel, record


def merge_segments(out_dir: str | os.PathLike[str], *, salvage_parts: bool = False,
                   delete: bool = True) -> Path | None:
    """Merge ``run-NNNN.mcap`` segments (and, if ``salvage_parts``, what is readable of ``.part``
    segments) into ``out_dir/run.mcap`` (written as ``run.mcap.part`` then renamed).

    Returns the path, or None if there was nothing to merge. ``delete`` removes the merged segments.
    If ``run.mcap`` already exists (a crash between its rename and the deletion of the segments), its
    messages come first and segment messages identical to one of them are skipped, so merging twice
    never loses or duplicates a message.
    """
    out = Path(out_dir)
    done, parts = _segment_paths(out)
    sources = [(p, False) for p in done] + ([(p, True) for p in parts] if salvage_parts else [])
    sources.sort(key=lambda item: int(_SEGMENT_RE.match(item[0].name).group(1)))  # type: ignore[union-attr]
    if not sources:
        return None
    target, tmp = out / MCAP_NAME, out / f"{MCAP_NAME}.part"
    previous = [(target, False)] if target.exists() else []
    already: set[tuple[str, int, int, bytes]] = set()
    with tmp.open("wb") as f:
        writer = McapWriter(f, compression=CompressionType.ZSTD)
        writer.start(profile="ros2", library="gsrmr.recording")
        schema_ids: dict[tuple[str, bytes], int] = {}
        channel_ids: dict[str, int] = {}
        for path, salvage in previous + sources:
            for schema, channel, message in _records(path, salvage):
                if schema is None:
                    continue
                ident = (channel.topic, message.log_time, message.sequence,
                         hashlib.blake2b(message.data, digest_size=16).digest())
                if path == target:
                    already.add(ident)
                elif ident in already:
                    continue
                key = (schema.name, schema.data)
                if key not in schema_ids:
                    schema_ids[key] = writer.register_schema(schema.name, schema.encoding, schema.data)
                if channel.topic not in channel_ids:
                    # The MCAP ros2 profile requires offered_qos_profiles; "[]" (no publisher QoS known)
                    # parses as an empty list in rosbag2, whose player then uses its default QoS.
                    metadata = {"offered_qos_profiles": "[]", **channel.metadata}
                    channel_ids[channel.topic] = writer.register_channel(
                        channel.topic, channel.message_encoding, schema_ids[key], metadata)
                writer.add_message(channel_ids[channel.topic], message.log_time, message.data,
                                   message.publish_time, message.sequence)
        writer.finish()
        f.flush()
        os.fsync(f.fileno())
    tmp.replace(target)
    if delete:
        for path, _ in sources:
            path.unlink()
    return target


def recover_run(out_dir: str | os.PathLike[str]) -> Path | None:
    """After a crash: merge finished segments plus the salvageable part of the open one into
    ``run.mcap`` and delete them. Safe to call on a cleanly closed directory (returns None)."""
    return merge_segments(out_dir, salvage_parts=True, delete=True)


def read_mcap(path: str | os.PathLike[str]) -> list[tuple[str, int, Any]]:
    """Every message of an MCAP file as ``(topic, log_time_ns, decoded ROS message)`` in log-time order.

    Decoded messages are mcap-ros2-support dynamic objects (attribute access like the ROS classes).
    """
    with Path(path).open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        return [(channel.topic, message.log_time, decoded)
                for _, channel, message, decoded in reader.iter_decoded_messages(log_time_order=True)]
