"""Typed messages of chosen topics from a recorded bag — rosbag2 (MCAP or sqlite3), a bare ``.mcap``/``.db3`` file or a
ROS 1 ``.bag`` — read with ``rosbags`` (pure Python, no ROS install): :class:`BagReader`. Message types, ROS 1 field
names and damaged bags: docs/dataset_tool.md, "Reading the bag".
"""

from __future__ import annotations

from collections.abc import Collection, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mcap.exceptions import EndOfFile, McapError
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag1 import ReaderError as Ros1ReaderError
from rosbags.rosbag2 import ReaderError as Ros2ReaderError
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, TypesysError, get_types_from_idl, get_types_from_msg, get_typestore

NS_PER_S = 1_000_000_000
_READ_ERRORS = (AnyReaderError, Ros1ReaderError, Ros2ReaderError, McapError, OSError, EOFError, ValueError,
                KeyError, AssertionError)
_IDL_SEPARATOR = "=" * 80 + "\n"


class BagError(ValueError):
    """A bag that cannot be read at all (the message says what and how to fix it, on one line)."""


@dataclass(frozen=True)
class BagTopic:
    """A topic of the bag: its name, message type (``sensor_msgs/msg/Image``) and message count."""

    name: str
    msgtype: str
    count: int


@dataclass(frozen=True)
class BagMessage:
    """One deserialised message: topic, type, the recorder's log time [ns] (never a message's own stamp) and
    the message object."""

    topic: str
    msgtype: str
    log_time_ns: int
    msg: Any


def _mb(n_bytes: int) -> str:
    return f"{n_bytes / 1e6:.2f} MB"


def storage_files(path: Path) -> list[Path]:
    """The storage files of a rosbag2 folder (``*.mcap``, ``*.db3``; sorted by name) — split bags included."""
    return sorted(p for p in path.iterdir() if p.suffix in (".mcap", ".db3") and p.is_file())


class _McapScan:
    """A record-by-record scan of MCAP files that stops at the first unreadable record (the fallback)."""

    def __init__(self, files: list[Path]) -> None:
        self.files = files
        self.schemas: dict[tuple[int, int], Schema] = {}
        self.channels: dict[tuple[int, int], Channel] = {}
        self.counts: dict[tuple[int, int], int] = {}
        self.notes: list[str] = []
        for index, path in enumerate(files):
            readable, total, n_messages, last_ns, error = 0, path.stat().st_size, 0, None, None
            for record, offset, failure in self._records(index):
                if failure is not None:
                    error = failure
                    break
                readable = offset
                if isinstance(record, Message):
                    key = (index, record.channel_id)
                    self.counts[key] = self.counts.get(key, 0) + 1
                    n_messages += 1
                    last_ns = record.log_time if last_ns is None else max(last_ns, record.log_time)
            if error is not None:
                until = "no message" if last_ns is None else f"log time {last_ns / NS_PER_S:.3f} s"
                self.notes.append(f"{path.name} is damaged ({error or 'no MCAP footer'}): read {_mb(readable)} of "
                                  f"{_mb(total)} ({100.0 * readable / max(total, 1):.0f} %), {n_messages} messages "
                                  f"up to {until}; the rest is lost")
        self.typestore = get_typestore(Stores.EMPTY)
        types: dict = {}
        for schema in self.schemas.values():
            try:
                types.update(_types_of_schema(schema))
            except (TypesysError, ValueError, AssertionError) as err:
                self.notes.append(f"schema {schema.name} cannot be parsed ({err}); its messages are skipped")
        try:
            self.typestore.register(types)
        except TypesysError as err:
            raise BagError(f"the bag's message definitions disagree with each other ({err})") from None
        self.default_typestore = get_typestore(Stores.LATEST)

    def _records(self, index: int) -> Iterator[tuple[Any, int, str | None]]:
        """(record, byte offset after it, None) per readable record, then (None, 0, error) if one fails."""
        path = self.files[index]
        with path.open("rb") as stream:
            reader = StreamReader(stream, record_size_limit=path.stat().st_size)
            records = iter(reader.records)
            while True:
                try:
                    record = next(records)
                except StopIteration:
                    return
                except EndOfFile:
                    yield None, 0, "the file ends in the middle of a record"
                    return
                except Exception as err:  # any malformed record ends the readable part: say which
                    yield None, 0, f"{type(err).__name__}: {err}" if str(err) else type(err).__name__
                    return
                if isinstance(record, Schema):
                    self.schemas[(index, record.id)] = record
                elif isinstance(record, Channel):
                    self.channels[(index, record.id)] = record
                yield record, stream.tell(), None

    def topics(self) -> dict[str, BagTopic]:
        out: dict[str, BagTopic] = {}
        for key, channel in sorted(self.channels.items()):
            msgtype = self._msgtype(key)
            count = self.counts.get(key, 0) + (out[channel.topic].count if channel.topic in out else 0)
            out[channel.topic] = BagTopic(channel.topic, msgtype, count)
        return dict(sorted(out.items()))

    def _msgtype(self, key: tuple[int, int]) -> str:
        channel = self.channels[key]
        schema = self.schemas.get((key[0], channel.schema_id))
        return schema.name if schema is not None else ""

    def messages(self, topics: Collection[str], skipped: dict[str, int]) -> Iterator[BagMessage]:
        for index in range(len(self.files)):
            for record, _offset, failure in self._records(index):
                if failure is not None or not isinstance(record, Message):
                    continue
                channel = self.channels.get((index, record.channel_id))
                if channel is None or channel.topic not in topics:
                    continue
                msgtype = self._msgtype((index, record.channel_id))
                store = self.typestore if msgtype in self.typestore.types else self.default_typestore
                try:
                    msg = store.deserialize_cdr(record.data, msgtype)
                except (SerdeError, KeyError, ValueError, IndexError, AssertionError, TypesysError):
                    skipped[channel.topic] = skipped.get(channel.topic, 0) + 1
                    continue
                yield BagMessage(channel.topic, msgtype, int(record.log_time), msg)


def _types_of_schema(schema: Schema) -> dict:
    text = schema.data.decode()
    if schema.encoding == "ros2msg":
        return get_types_from_msg(text, schema.name)
    if schema.encoding == "ros2idl":
        if text.startswith(f"{_IDL_SEPARATOR}IDL: "):
            types: dict = {}
            for part in text.split(_IDL_SEPARATOR)[1:]:
                types.update(get_types_from_idl(part.split("\n", 1)[1]))
            return types
        return get_types_from_idl(text)
    return {}


class BagReader:
    """One bag, opened for reading (a context manager). ``path``: a rosbag2 folder, a ``.mcap`` or ``.db3``
    file, or a ROS 1 ``.bag`` file. Raises :class:`BagError` when nothing of it can be read."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.notes: list[str] = []
        self.skipped: dict[str, int] = {}  # topic → messages that could not be deserialised
        self._any: AnyReader | None = None
        self._scan: _McapScan | None = None
        if not self.path.exists():
            raise BagError(f"{self.path} does not exist (give a rosbag2 folder, a .mcap/.db3 file or a ROS 1 .bag)")
        paths = self._paths()
        try:
            reader = AnyReader(paths, default_typestore=get_typestore(Stores.LATEST))
            reader.open()
            self._any = reader
            self.kind = "ROS 1 bag" if not reader.is2 else "rosbag2"
        except (*_READ_ERRORS, TypesysError, FileNotFoundError) as err:
            mcaps = [p for p in paths if p.suffix == ".mcap"] or (
                [p for p in storage_files(self.path) if p.suffix == ".mcap"] if self.path.is_dir() else [])
            if not mcaps:
                hint = ("; an unindexed ROS 1 bag (recording killed) is repaired with `rosbag reindex`"
                        if self.path.suffix == ".bag" else "")
                raise BagError(f"cannot read {self.path}: {err}{hint}") from None
            self._scan = _McapScan(mcaps)
            self.kind = "MCAP (scanned record by record)"
            if not self._scan.notes:
                self.notes.append(f"rosbags refused {self.path.name} ({err}); read it record by record instead")
            self.notes.extend(self._scan.notes)

    def _paths(self) -> list[Path]:
        if not self.path.is_dir():
            return [self.path]
        if (self.path / "metadata.yaml").exists():
            return [self.path]
        files = storage_files(self.path)
        if not files:
            raise BagError(f"{self.path} is a folder without metadata.yaml and without .mcap/.db3 files: not a "
                           "rosbag2 bag")
        self.notes.append(f"{self.path.name} has no metadata.yaml (recording not closed?): reading "
                          f"{', '.join(p.name for p in files)} directly")
        return files

    def __enter__(self) -> BagReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the files."""
        if self._any is not None:
            self._any.close()
            self._any = None

    @property
    def topics(self) -> dict[str, BagTopic]:
        """Every topic of the bag by name (sorted), with its type and message count."""
        if self._scan is not None:
            return self._scan.topics()
        assert self._any is not None
        return {name: BagTopic(name, info.msgtype or "", int(info.msgcount))
                for name, info in sorted(self._any.topics.items())}

    def messages(self, topics: Collection[str]) -> Iterator[BagMessage]:
        """The messages of ``topics`` (names as in :attr:`topics`), in log-time order for a readable bag, in file
        order for a scanned one. Messages that fail to deserialise are skipped and counted in :attr:`skipped`;
        a read error part-way ends the iteration with a note."""
        wanted = set(topics)
        if self._scan is not None:
            yield from self._scan.messages(wanted, self.skipped)
            return
        reader = self._any
        assert reader is not None
        connections = [c for c in reader.connections if c.topic in wanted]
        if not connections:
            return
        last_ns = None
        stream = reader.messages(connections=connections)
        while True:
            try:
                connection, log_time_ns, raw = next(stream)
            except StopIteration:
                return
            except _READ_ERRORS as err:
                where = "before the first message" if last_ns is None else f"after log time {last_ns / NS_PER_S:.3f} s"
                self.notes.append(f"reading {', '.join(sorted(wanted))} stopped {where}: {err}; the rest is lost")
                return
            try:
                msg = reader.deserialize(raw, connection.msgtype)
            except (AnyReaderError, SerdeError, KeyError, ValueError, IndexError, AssertionError):
                self.skipped[connection.topic] = self.skipped.get(connection.topic, 0) + 1
                continue
            last_ns = log_time_ns
            yield BagMessage(connection.topic, connection.msgtype, int(log_time_ns), msg)

    def first(self, topic: str) -> BagMessage | None:
        """The first message of ``topic`` (``None`` when it has none)."""
        stream = self.messages([topic])
        try:
            return next(stream, None)
        finally:
            stream.close()
