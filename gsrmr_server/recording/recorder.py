"""The run recorder: one CSV row and a few ROS 2 messages per slot, crash-safe (layout and rules:
``docs/nodes.md``, "The server's recording").
"""

from __future__ import annotations

from collections.abc import Mapping
import csv
import json
import os
from pathlib import Path
import threading
import time
from types import TracebackType
from typing import Any

from geometry_msgs.msg import TwistStamped
from mcap.records import Schema
from mcap.writer import CompressionType
from mcap_ros2.writer import Writer as Ros2Writer
import numpy as np
from sensor_msgs.msg import CompressedImage
from std_msgs.msg import String

from gsrmr_common.jpeg import encode_jpeg
from gsrmr_common.ros_wire import compressed_to_msg, ns_to_stamp, pose_key_pose_msg
from gsrmr_common.tf_tree import CAMERA_OPTICAL_FRAME
from gsrmr_common.wire import PoseKey
from gsrmr_server.recording.mcap_log import (
    MCAP_NAME,
    TOPIC_CMD_VEL,
    TOPIC_MR_IMAGE,
    TOPIC_RECEIVED_IMAGE,
    TOPIC_RECEIVED_POSE,
    TOPIC_SLOT_LOG,
    TOPIC_TYPES,
    _encodable,
    _segment_paths,
    merge_segments,
)
from gsrmr_server.recording.msgdefs import message_definition
from gsrmr_server.recording.slots_csv import (
    CSV_COLUMNS,
    CSV_NAME,
    _cell,
    _json_value,
    _parse_cell,
)
from gsrmr_server.slot_row import SlotRow


class RunRecorder:
    """Writes ``slots.csv`` and the MCAP recording of one run into ``out_dir`` (created if missing).

    ``jpeg_quality`` (1..100) encodes m̂_t for the bag; ``image_frame_id`` is the frame of the MR image
    (the camera optical frame), ``cmd_frame_id`` that of u_t. ``segment_slots`` bounds what a crash can
    lose from the MCAP; within the open segment, complete chunks of ``chunk_bytes`` are salvageable by
    :func:`recover_run`. ``fsync`` syncs every CSV row to disk. One recorder per directory; calls
    are thread-safe.
    """

    def __init__(self, out_dir: str | os.PathLike[str], *, segment_slots: int = 50, jpeg_quality: int = 80,
                 image_frame_id: str = CAMERA_OPTICAL_FRAME, cmd_frame_id: str = "base_link",
                 fsync: bool = False, chunk_bytes: int = 256 * 1024) -> None:
        if segment_slots < 1:
            raise ValueError(f"segment_slots must be >= 1, got {segment_slots}")
        if not 1 <= jpeg_quality <= 100:
            raise ValueError(f"jpeg_quality must be in 1..100, got {jpeg_quality}")
        self.out_dir = Path(out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        done, parts = _segment_paths(self.out_dir)
        if done or parts or (self.out_dir / MCAP_NAME).exists() or (self.out_dir / CSV_NAME).exists():
            raise FileExistsError(f"{self.out_dir} already holds a recording; use a fresh directory")
        self.segment_slots = int(segment_slots)
        self.jpeg_quality = int(jpeg_quality)
        self.image_frame_id = image_frame_id
        self.cmd_frame_id = cmd_frame_id
        self.fsync = fsync
        self.chunk_bytes = int(chunk_bytes)
        self.csv_path = self.out_dir / CSV_NAME
        self.mcap_path = self.out_dir / MCAP_NAME
        self._topic_types: dict[str, str] = dict(TOPIC_TYPES)
        self._definitions = {t: message_definition(t) for t in sorted(set(TOPIC_TYPES.values()))}
        self._lock = threading.Lock()
        self._csv_file = self.csv_path.open("w", newline="", encoding="utf-8")
        self._csv = csv.writer(self._csv_file, lineterminator="\n")
        self._csv.writerow(CSV_COLUMNS)
        self._csv_file.flush()
        self._segment_index = 0
        self._segment_count = 0
        self._segment_file: Any = None
        self._writer: Ros2Writer | None = None
        self._schemas: dict[str, Schema] = {}
        self.slots_written = 0
        self._closed = False

    # -- segments
    def _segment_name(self, index: int) -> Path:
        return self.out_dir / f"run-{index:04d}.mcap"

    def _open_segment(self) -> None:
        path = self._segment_name(self._segment_index).with_suffix(".mcap.part")
        self._segment_file = path.open("wb")
        self._writer = Ros2Writer(self._segment_file, chunk_size=self.chunk_bytes,
                                  compression=CompressionType.ZSTD)
        self._schemas = {}  # per segment: type name -> schema record, registered on first use
        self._segment_count = 0

    def _write(self, topic: str, msg: Any, stamp_ns: int, seq: int) -> None:
        """Write one message into the open segment (opening one if needed); caller holds the lock."""
        if self._writer is None:
            self._open_segment()
        assert self._writer is not None
        type_name = self._topic_types[topic]
        schema = self._schemas.get(type_name)
        if schema is None:
            schema = self._writer.register_msgdef(type_name, self._definitions[type_name])
            self._schemas[type_name] = schema
        self._writer.write_message(topic, schema, _encodable(msg), log_time=stamp_ns, publish_time=stamp_ns,
                                   sequence=seq)

    def _finish_segment(self) -> None:
        if self._writer is None:
            return
        self._writer.finish()
        self._segment_file.flush()
        os.fsync(self._segment_file.fileno())
        self._segment_file.close()
        part = self._segment_name(self._segment_index).with_suffix(".mcap.part")
        part.replace(self._segment_name(self._segment_index))
        self._writer, self._segment_file = None, None
        self._segment_index += 1

    # -- public API
    def write_slot(self, row: SlotRow | Mapping[str, Any], mr_image: np.ndarray | bytes | CompressedImage | None,
                   cmd: tuple[float, float] | None, *, stamp_ns: int | None = None) -> None:
        """Record one slot.

        ``row`` is a :class:`~gsrmr_server.slot_row.SlotRow` or maps (a subset of) :data:`CSV_COLUMNS` to
        values; ``slot`` is required, unknown keys are refused. ``mr_image`` is the MR image m̂_t: the
        ``sensor_msgs/CompressedImage`` already published (stored as it is), JPEG bytes, an H×W×3 RGB
        array (``uint8`` or float in [0, 1]), or None. ``cmd`` is u_t = (v_mps, w_radps) or None. The time
        stamp is ``stamp_ns`` if given, else ``row["stamp_s"]`` (slot start, s), else the wall clock.
        The CSV row is flushed before this returns.
        """
        if isinstance(row, SlotRow):
            row = {c: getattr(row, c) for c in CSV_COLUMNS}
        unknown = set(row) - set(CSV_COLUMNS)
        if unknown:
            raise ValueError(f"slot row: unknown columns {sorted(unknown)}")
        if row.get("slot") is None:
            raise ValueError("slot row: 'slot' is required")
        cells = [_cell(c, row.get(c)) for c in CSV_COLUMNS]
        if stamp_ns is None:
            stamp_s = row.get("stamp_s")
            stamp_ns = round(float(stamp_s) * 1e9) if stamp_s is not None else time.time_ns()
        image_msg = mr_image if isinstance(mr_image, CompressedImage) else None
        if mr_image is not None and image_msg is None:
            jpeg = bytes(mr_image) if isinstance(mr_image, (bytes, bytearray)) \
                else encode_jpeg(mr_image, self.jpeg_quality)
            image_msg = compressed_to_msg(jpeg, stamp_ns, self.image_frame_id)
        # The JSON row is exactly what read_slots_csv returns for this line (non-finite -> null).
        log_json = json.dumps({c: _json_value(_parse_cell(c, cell)) for c, cell in zip(CSV_COLUMNS, cells,
                                                                                      strict=True)},
                              allow_nan=False)
        with self._lock:
            if self._closed:
                raise RuntimeError("RunRecorder is closed")
            self._csv.writerow(cells)
            self._csv_file.flush()
            if self.fsync:
                os.fsync(self._csv_file.fileno())
            seq = self.slots_written
            if image_msg is not None:
                self._write(TOPIC_MR_IMAGE, image_msg, stamp_ns, seq)
            if cmd is not None:
                twist = TwistStamped()
                twist.header.stamp = ns_to_stamp(stamp_ns)
                twist.header.frame_id = self.cmd_frame_id
                twist.twist.linear.x = float(cmd[0])
                twist.twist.angular.z = float(cmd[1])
                self._write(TOPIC_CMD_VEL, twist, stamp_ns, seq)
            self._write(TOPIC_SLOT_LOG, String(data=log_json), stamp_ns, seq)
            self._segment_file.flush()
            self.slots_written += 1
            self._segment_count += 1
            if self._segment_count >= self.segment_slots:
                self._finish_segment()

    def write_received(self, jpeg: bytes, key: PoseKey, stamp_ns: int) -> None:
        """Record what the robot paid to send in an image slot (training data for a model update): the JPEG as it
        arrived on :data:`TOPIC_RECEIVED_IMAGE` and its pose key as a PoseStamped on :data:`TOPIC_RECEIVED_POSE`,
        both stamped with the slot start ``stamp_ns``."""
        self.write_message(TOPIC_RECEIVED_IMAGE, compressed_to_msg(jpeg, stamp_ns, CAMERA_OPTICAL_FRAME), stamp_ns)
        self.write_message(TOPIC_RECEIVED_POSE, pose_key_pose_msg(key, stamp_ns), stamp_ns)

    def write_message(self, topic: str, msg: Any, stamp_ns: int) -> None:
        """Record any other ROS 2 message (e.g. the pose key or the schedule) into the MCAP.

        ``msg`` is an instance of a generated message class (``pkg.msg.Type``); its definition is read
        from the installed ``.msg`` files on first use. A topic keeps the type it was first written
        with (``ValueError`` otherwise). The message lands in the open segment; segments still rotate
        by slot count only.
        """
        cls = type(msg)
        type_name = f"{cls.__module__.split('.')[0]}/msg/{cls.__name__}"
        with self._lock:
            if self._closed:
                raise RuntimeError("RunRecorder is closed")
            known = self._topic_types.get(topic)
            if known is not None and known != type_name:
                raise ValueError(f"topic {topic} is recorded as {known}, not {type_name}")
            if type_name not in self._definitions:
                self._definitions[type_name] = message_definition(type_name)
            self._topic_types[topic] = type_name
            self._write(topic, msg, int(stamp_ns), self.slots_written)
            self._segment_file.flush()

    def close(self) -> Path | None:
        """Finish the open segment, merge all segments into ``run.mcap`` and close the CSV.

        Returns the MCAP path (None if no slot was written). Idempotent.
        """
        with self._lock:
            if self._closed:
                return self.mcap_path if self.mcap_path.exists() else None
            self._closed = True
            self._csv_file.flush()
            os.fsync(self._csv_file.fileno())
            self._csv_file.close()
            self._finish_segment()
            return merge_segments(self.out_dir, delete=True)

    def __enter__(self) -> RunRecorder:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()
