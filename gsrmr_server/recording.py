"""Run recorder: one CSV row and a few ROS 2 messages per slot, crash-safe (pure: no rclpy import).

Output directory layout
-----------------------
``slots.csv``
    One row per slot with the columns :data:`CSV_COLUMNS` (units in the names; ``stamp_s`` is the slot
    start in seconds of ROS time, ``x`` 1 = image / 0 = pose key, ``source`` ∈ {image, render,
    fallback}, pose in ``map`` per REP-103, ``loss`` = MR loss of m̂_t against the true m_t (simulation
    only), ``gs_loss`` = the GS loss L_t measured in an image slot, ``energy_upload_all_j`` = what the
    upload-all reference (RoboMR) would have spent on this slot's frame; empty cell = not available).
    The file is flushed after every row, so a killed process (``kill -9``) loses no row that
    :meth:`RunRecorder.write_slot`
    returned from. ``fsync=True`` makes rows survive power loss as well (costs a disk sync per slot).
``run.mcap``
    After :meth:`RunRecorder.close`: ROS 2 (``ros2msg`` schemas, ``cdr`` messages, zstd chunks) with
    the topics :data:`TOPIC_MR_IMAGE` (``sensor_msgs/msg/CompressedImage``: the MR image m̂_t as JPEG,
    ``format = wire.JPEG_FORMAT``), :data:`TOPIC_CMD_VEL` (``geometry_msgs/msg/TwistStamped``: u_t in
    ``base_link``, m/s and rad/s) and :data:`TOPIC_SLOT_LOG` (``std_msgs/msg/String``: the CSV row as
    JSON). Every message's ``log_time``/``publish_time`` and header stamp is the slot start. Other
    topics come through :meth:`RunRecorder.write_message`, e.g. :data:`TOPIC_CAMERA_INFO`
    (``sensor_msgs/msg/CameraInfo``, the robot's calibration, logged when it arrives). Opens in
    Foxglove and ``ros2 bag info/play`` (MCAP storage plugin); channels carry
    ``offered_qos_profiles = "[]"`` (the player then uses its default QoS).

Crash safety of the MCAP
------------------------
While running, messages go to segments: ``run-0000.mcap``, ``run-0001.mcap`` … of ``segment_slots``
slots each. The segment being written is named ``run-NNNN.mcap.part`` and renamed when it is finished,
so every ``run-NNNN.mcap`` is a complete, indexed MCAP file. A crash therefore loses at most the slots
of the open ``.part`` segment (default 50 slots = 5 s at τ = 0.1 s), and :func:`recover_run` salvages
its complete chunks too. :meth:`RunRecorder.close` merges the segments into ``run.mcap`` (via
``run.mcap.part`` + rename) and deletes them. After a crash run :func:`recover_run` (same merge).

Message definitions are generated from the installed ``.msg`` files (:func:`message_definition`):
the top-level definition, then each nested type after a line of 80 ``=`` and ``MSG: pkg/msg/Type``,
the rosbag2 ``ros2msg`` encoding.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
import contextlib
import csv
import hashlib
import importlib
import json
import math
import os
from pathlib import Path
import re
import sys
import threading
import time
from types import TracebackType
from typing import Any

from geometry_msgs.msg import TwistStamped
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer as Ros2Writer
import numpy as np
from sensor_msgs.msg import CompressedImage
from std_msgs.msg import String

from gsrmr_common.jpeg import encode_jpeg
from gsrmr_common.ros_wire import compressed_to_msg, ns_to_stamp
from gsrmr_common.wire import RealSource
from gsrmr_server.slot_row import SLOT_ROW_COLUMNS, SlotRow

CSV_COLUMNS = SLOT_ROW_COLUMNS  # the fields of gsrmr_server.slot_row.SlotRow, in order
_INT_COLUMNS = frozenset({"slot", "x", "bytes_sent"})
_STR_COLUMNS = frozenset({"source", "faults"})
SOURCES = tuple(s.value for s in RealSource)  # the source column: where r̂_t came from

TOPIC_MR_IMAGE = "/gsrmr/mr/image/compressed"
TOPIC_CMD_VEL = "/gsrmr/cmd_vel"
TOPIC_SLOT_LOG = "/gsrmr/slot_log"
# Written by the server through write_message when the robot's calibration arrives (not per slot).
TOPIC_CAMERA_INFO = "/gsrmr/camera_info"
TOPIC_TYPES = {
    TOPIC_MR_IMAGE: "sensor_msgs/msg/CompressedImage",
    TOPIC_CMD_VEL: "geometry_msgs/msg/TwistStamped",
    TOPIC_SLOT_LOG: "std_msgs/msg/String",
}
MCAP_NAME = "run.mcap"
CSV_NAME = "slots.csv"
_SEGMENT_RE = re.compile(r"^run-(\d{4,})\.mcap(\.part)?$")
_PRIMITIVES = frozenset({"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
                         "int32", "uint32", "int64", "uint64", "string", "wstring"})
_SEPARATOR = "=" * 80


# ----------------------------------------------------------------------------- message definitions

def _msg_file(package: str, name: str) -> Path:
    """Locate ``<prefix>/share/<package>/msg/<name>.msg`` of an installed interface package."""
    prefixes = [Path(sys.prefix)]
    prefixes += [Path(p) for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    with contextlib.suppress(ImportError, TypeError):
        module_file = importlib.import_module(package).__file__
        if module_file is not None:  # <prefix>/lib/pythonX.Y/site-packages/<package>/__init__.py
            prefixes.append(Path(module_file).resolve().parents[4])
    for prefix in prefixes:
        candidate = prefix / "share" / package / "msg" / f"{name}.msg"
        if candidate.is_file():
            return candidate
    raise FileNotFoundError(f"{package}/msg/{name}.msg not found under {[str(p) for p in prefixes]}")


def _strip_comments(text: str) -> list[str]:
    """Definition lines without comments and blank lines (string constants keep a literal '#')."""
    lines = []
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        first = line.split()[0]
        if "#" in line and not (first.startswith(("string", "wstring")) and "=" in line.split("#")[0]):
            line = line.split("#", 1)[0].rstrip()
        lines.append(line)
    return lines


def _field_dependencies(package: str, lines: Sequence[str]) -> list[str]:
    """Nested message types (``pkg/msg/Type``) used by the fields of a definition."""
    deps = []
    for line in lines:
        parts = line.split()
        if len(parts) < 2 or "=" in parts[1] or (len(parts) > 2 and parts[2].startswith("=")):
            continue  # constants are always primitive
        base = re.sub(r"\[.*\]$", "", parts[0])
        base = re.sub(r"<=\d+$", "", base)
        if base in _PRIMITIVES:
            continue
        pieces = base.split("/")
        pkg, name = (pieces[0], pieces[-1]) if len(pieces) > 1 else (package, pieces[0])
        deps.append(f"{pkg}/msg/{name}")
    return deps


def message_definition(type_name: str) -> str:
    """Complete ``ros2msg`` definition of ``pkg/msg/Type`` from the installed ``.msg`` files.

    The top-level definition comes first; every nested type follows once, after a line of 80 ``=`` and
    ``MSG: pkg/msg/Type`` (rosbag2's encoding, read by Foxglove and mcap-ros2-support).
    Comments are stripped.
    """
    pieces = type_name.split("/")
    if len(pieces) not in (2, 3):
        raise ValueError(f"message type must look like pkg/msg/Type, got {type_name!r}")
    order: list[str] = []
    texts: dict[str, str] = {}

    def visit(full: str) -> None:
        if full in texts:
            return
        pkg, _, name = full.split("/")
        lines = _strip_comments(_msg_file(pkg, name).read_text())
        texts[full] = "\n".join(lines)
        order.append(full)
        for dep in _field_dependencies(pkg, lines):
            visit(dep)

    visit(f"{pieces[0]}/msg/{pieces[-1]}")
    out = [texts[order[0]]]
    for dep in order[1:]:
        out.append(f"{_SEPARATOR}\nMSG: {dep}\n{texts[dep]}")
    return "\n".join(out) + "\n"


# -------------------------------------------------------------------------------------------- CSV

def _cell(column: str, value: Any) -> str:
    """One CSV cell: '' for None/NaN, exact repr for floats, ';'-joined faults."""
    if value is None:
        return ""
    if column == "faults":
        if isinstance(value, str):
            return value
        return ";".join(str(v) for v in value)
    if column == "source":
        if value not in SOURCES:
            raise ValueError(f"slot row: source must be one of {SOURCES}, got {value!r}")
        return str(value)
    if column in _INT_COLUMNS:
        if isinstance(value, bool) or int(value) != value:
            raise ValueError(f"slot row: {column} must be an integer, got {value!r}")
        if column == "x" and value not in (0, 1):
            raise ValueError(f"slot row: x must be 0 (pose key) or 1 (image), got {value!r}")
        return str(int(value))
    number = float(value)
    return "" if math.isnan(number) else repr(number)


def _parse_cell(column: str, text: str) -> Any:
    if text == "":
        return None
    if column in _STR_COLUMNS:
        return text
    if column in _INT_COLUMNS:
        return int(text)
    return float(text)


def read_slots_csv(path: str | os.PathLike[str]) -> list[dict[str, Any]]:
    """Rows of a ``slots.csv`` as dicts: ints for slot/x/bytes_sent, str for source/faults, float
    otherwise, ``None`` for empty cells. A last line without its newline (torn write) is dropped."""
    with Path(path).open(newline="", encoding="utf-8") as f:
        text = f.read()
    if text and not text.endswith("\n"):
        text = text[: text.rfind("\n") + 1]
    reader = csv.DictReader(text.splitlines(keepends=True))
    if tuple(reader.fieldnames or ()) != CSV_COLUMNS:
        raise ValueError(f"{path}: header {reader.fieldnames} is not {list(CSV_COLUMNS)}")
    return [{c: _parse_cell(c, row[c]) for c in CSV_COLUMNS} for row in reader]


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


def _json_value(value: Any) -> Any:
    return None if isinstance(value, float) and not math.isfinite(value) else value


# ------------------------------------------------------------------------------------------- MCAP

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


# ------------------------------------------------------------------------------------------ recorder

class RunRecorder:
    """Writes ``slots.csv`` and the MCAP recording of one run into ``out_dir`` (created if missing).

    ``jpeg_quality`` (1..100) encodes m̂_t for the bag; ``image_frame_id`` is the frame of the MR image
    (the camera optical frame), ``cmd_frame_id`` that of u_t. ``segment_slots`` bounds what a crash can
    lose from the MCAP; within the open segment, complete chunks of ``chunk_bytes`` are salvageable by
    :func:`recover_run`. ``fsync`` syncs every CSV row to disk. One recorder per directory; calls
    are thread-safe.
    """

    def __init__(self, out_dir: str | os.PathLike[str], *, segment_slots: int = 50, jpeg_quality: int = 80,
                 image_frame_id: str = "camera_optical_frame", cmd_frame_id: str = "base_link",
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


__all__ = ["CSV_COLUMNS", "SOURCES", "TOPIC_CAMERA_INFO", "TOPIC_CMD_VEL", "TOPIC_MR_IMAGE", "TOPIC_SLOT_LOG",
           "TOPIC_TYPES", "RunRecorder", "merge_segments", "message_definition", "read_mcap", "read_slots_csv",
           "recover_run"]


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m gsrmr_server.recording {recover,info} PATH``: salvage a crashed run / summarise one."""
    import argparse

    parser = argparse.ArgumentParser(prog="python -m gsrmr_server.recording", description=main.__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("recover", help="merge run-NNNN.mcap(.part) segments of a crashed run into run.mcap") \
        .add_argument("out_dir")
    sub.add_parser("info", help="messages per topic of an MCAP file and rows of slots.csv") \
        .add_argument("path", help="a run directory or an .mcap file")
    args = parser.parse_args(argv)
    if args.command == "recover":
        merged = recover_run(args.out_dir)
        print(f"recovered {merged}" if merged else f"nothing to recover in {args.out_dir}")
        return 0
    path = Path(args.path)
    mcap_path = path / MCAP_NAME if path.is_dir() else path
    with mcap_path.open("rb") as f:
        summary = make_reader(f).get_summary()
    if summary is None or summary.statistics is None:
        print(f"{mcap_path}: no summary section (unfinished file? try 'recover')")
        return 1
    stats = summary.statistics
    print(f"{mcap_path}: {stats.message_count} messages, log time "
          f"{stats.message_start_time / 1e9:.3f} … {stats.message_end_time / 1e9:.3f} s")
    for cid, channel in sorted(summary.channels.items(), key=lambda item: item[1].topic):
        schema = summary.schemas.get(channel.schema_id)
        print(f"  {channel.topic} [{schema.name if schema else '?'}]: "
              f"{stats.channel_message_counts.get(cid, 0)}")
    if path.is_dir() and (path / CSV_NAME).exists():
        print(f"{path / CSV_NAME}: {len(read_slots_csv(path / CSV_NAME))} slot rows")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
