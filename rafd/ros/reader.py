"""Radar scans out of a bag: a rosbag2 recording (its folder, or its .mcap / .db3 file) or a ROS 1 .bag, read with
rosbags.

The scan topic is the one of a scan type (RadarBScanMsg, else CompressedImage, else Image: the first type with
exactly one topic), or the one named (`topic`). Its geometry comes from the bag's RadarConfigurationMsg (a scan uses
the last configuration before it, else the bag's first), else from the caller's RadarGeometry (flags). Messages are
decoded with the bag's own definitions where it carries them, else with rafd.ros.types' (for configuration messages
without a definition both of Navtech's field layouts are tried).

Bounded: one message is held at a time; before anything is read, an MCAP chunk or an sqlite3 record larger than
MAX_RECORD_BYTES is refused from the file's index, and every message larger than MAX_MESSAGE_BYTES or of a size a
real sensor does not have (rafd.ros.scans) is refused before it is decoded. Every failure (a corrupt or truncated
bag, a topic of another type, a message that does not decode as its type, a scan that disagrees with its
configuration) raises BagError naming the bag, the topic and the message.
"""

from __future__ import annotations

import contextlib
import sqlite3
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rafd.ros import types
from rafd.ros.scans import (
    BagScan,
    RadarGeometry,
    ScanError,
    from_b_scan,
    from_compressed_image,
    from_image,
    geometry_of,
)

SCAN_TYPES = (types.B_SCAN, types.COMPRESSED_IMAGE, types.IMAGE)  # looked for in this order
# A scan message is at most a few megabytes (the largest native scan accepted, 400 x 6859 bytes, is 2.7 MB); this
# leaves room for other sensors while refusing a message that only a broken or hostile bag holds.
MAX_MESSAGE_BYTES = 64 * 2**20
MAX_RECORD_BYTES = 256 * 2**20  # an MCAP chunk (several messages) or an sqlite3 row, from the file's index


class BagError(ValueError):
    """A bag that cannot be read as radar scans, the message saying which bag, topic and message."""


@dataclass(frozen=True)
class BagTopic:
    """The scan topic of a bag and how to read it."""

    path: Path
    topic: str
    msgtype: str
    count: int
    geometries: tuple[tuple[int, RadarGeometry], ...] = ()  # (log time ns, geometry) of each configuration message
    flags: RadarGeometry | None = None

    def geometry_at(self, log_time_ns: int) -> RadarGeometry | None:
        """The configuration in force at a message's log time: the last before it, else the bag's first; without any,
        the caller's flags."""
        if not self.geometries:
            return self.flags
        chosen = self.geometries[0][1]
        for time_ns, geometry in self.geometries:
            if time_ns > log_time_ns:
                break
            chosen = geometry
        return chosen


@dataclass
class _Decoder:
    """Deserialises one bag's messages with the right definitions (the bag's own, else the shipped ones)."""

    ros1: bool
    stores: dict[int, Any] = field(default_factory=dict)

    def store(self, connection: Any) -> Any:
        if connection.id not in self.stores:
            from rosbags.interfaces import MessageDefinitionFormat
            from rosbags.typesys import get_types_from_idl, get_types_from_msg

            own: dict[str, tuple] = {}
            definition = connection.msgdef
            try:
                if definition.format == MessageDefinitionFormat.MSG and definition.data:
                    own = dict(get_types_from_msg(definition.data, connection.msgtype))
                elif definition.format == MessageDefinitionFormat.IDL and definition.data:
                    own = dict(get_types_from_idl(definition.data))
            except Exception as error:  # rosbags' parser errors: a definition that does not parse
                raise BagError(
                    f"topic {connection.topic}: the bag's definition of {connection.msgtype} does not parse: {error}"
                ) from error
            self.stores[connection.id] = types.typestore(own)
        return self.stores[connection.id]

    def decode(self, connection: Any, raw: bytes, msgtype: str | None = None) -> Any:
        store = self.store(connection)
        name = msgtype or connection.msgtype
        if self.ros1:
            return store.deserialize_ros1(raw, name)
        return store.deserialize_cdr(raw, name)


def _describe(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__


def _storage_files(path: Path) -> list[Path]:
    if path.is_dir():
        return sorted(p for p in path.iterdir() if p.suffix in (".mcap", ".db3"))
    return [path]


def check_record_sizes(path: Path, limit: int = MAX_RECORD_BYTES) -> None:
    """BagError when the file's index says a chunk (MCAP) or a message (sqlite3) holds more than `limit` bytes: found
    before anything is read into memory. Files without an index are left to the reader, which bounds what it reads
    by the file's size."""
    for storage in _storage_files(path):
        if storage.suffix == ".mcap":
            from mcap.reader import make_reader

            try:
                with storage.open("rb") as handle:
                    summary = make_reader(handle).get_summary()
            except Exception:  # no summary (truncated, unindexed): the reader says what is wrong
                continue
            if summary is None:
                continue
            for chunk in summary.chunk_indexes:
                if chunk.uncompressed_size > limit:
                    raise BagError(
                        f"{storage}: a chunk at offset {chunk.chunk_start_offset} holds {chunk.uncompressed_size} "
                        f"bytes, more than {limit} (no radar scan is that large: a broken or hostile bag)"
                    )
        elif storage.suffix == ".db3":
            try:
                with contextlib.closing(sqlite3.connect(f"file:{storage}?mode=ro", uri=True)) as db:
                    row = db.execute(
                        "SELECT topics.name, messages.timestamp, length(messages.data) FROM messages "
                        "JOIN topics ON topics.id = messages.topic_id WHERE length(messages.data) > ? LIMIT 1",
                        (limit,),
                    ).fetchone()
            except sqlite3.Error:
                continue  # not a database we can query: the reader says what is wrong
            if row is not None:
                raise BagError(
                    f"{storage}: topic {row[0]}, the message logged at {row[1]} ns holds {row[2]} bytes, more than "
                    f"{limit} (no radar scan is that large: a broken or hostile bag)"
                )


@contextlib.contextmanager
def open_bag(path: str | Path) -> Iterator[tuple[Any, _Decoder]]:
    """An open rosbags reader of the bag at `path` and its decoder; BagError / FileNotFoundError naming the bag."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"bag {path} not found")
    check_record_sizes(path)
    ros1 = path.suffix == ".bag"
    try:
        if ros1:
            from rosbags.rosbag1 import Reader as Reader1

            reader: Any = Reader1(path)
        else:
            from rosbags.rosbag2 import Reader as Reader2

            reader = Reader2(path)
        reader.open()
    except FileNotFoundError:
        raise
    except Exception as exc:  # rosbags', sqlite's and yaml's errors on a corrupt, truncated or foreign file
        raise BagError(f"{path} is not a readable bag ({_describe(exc)})") from exc
    try:
        yield reader, _Decoder(ros1)
    finally:
        with contextlib.suppress(Exception):
            reader.close()


def _guarded(iterator: Iterator[Any], path: Path, what: str) -> Iterator[tuple[Any, int, bytes]]:
    """rosbags' messages, its errors (a truncated file, a corrupt chunk, a record too large to read) as BagError."""
    count = 0
    while True:
        try:
            connection, log_time, raw = next(iterator)
        except StopIteration:
            return
        except MemoryError as exc:
            raise BagError(f"{path}: {what}: after message {count}, a record too large to read") from exc
        except Exception as exc:
            raise BagError(f"{path}: {what}: reading stopped after message {count} ({_describe(exc)})") from exc
        count += 1
        yield connection, log_time, bytes(raw)


def _is_legacy(configuration: Any) -> bool:
    """Whether a decoded configuration has the older drivers' byte-array fields."""
    return not isinstance(configuration.azimuth_samples, int)


def read_geometries(
    reader: Any, decoder: _Decoder, path: Path, rotation_hz: float | None = None
) -> tuple[tuple[int, RadarGeometry], ...]:
    """(log time, geometry) of every RadarConfigurationMsg in the bag, in time order."""
    connections = [c for c in reader.connections if c.msgtype == types.CONFIGURATION]
    if not connections:  # (rosbags reads every topic when given no connection)
        return ()
    found = []
    messages = _guarded(reader.messages(connections=connections), path, "configuration")
    for index, (connection, log_time, raw) in enumerate(messages):
        where = f"{path}: topic {connection.topic}, message {index}"
        if len(raw) > MAX_MESSAGE_BYTES:
            raise BagError(f"{where}: {len(raw)} bytes, more than a configuration message can be")
        try:
            message = decoder.decode(connection, raw)
        except Exception as typed_error:
            if connection.msgdef.data:  # the bag defines it: that definition must read it
                raise BagError(f"{where}: does not decode as {connection.msgtype}: {typed_error}") from typed_error
            try:
                message = decoder.decode(connection, raw, types.LEGACY_CONFIGURATION)
            except Exception as error:
                raise BagError(
                    f"{where}: decodes in neither of Navtech's layouts of {connection.msgtype}: {error}"
                ) from error
        try:
            found.append(
                (
                    log_time,
                    geometry_of(message, f"configuration {connection.topic}", _is_legacy(message), rotation_hz or 4.0),
                )
            )
        except (ScanError, AttributeError) as error:
            raise BagError(f"{where}: {_describe(error)}") from error
    return tuple(sorted(found, key=lambda pair: pair[0]))


def find_scan_topic(reader: Any, path: Path, topic: str | None) -> Any:
    """The connection of the scan topic (named, or found by type); BagError naming what the bag holds otherwise."""
    connections = list(reader.connections)
    held = ", ".join(sorted({f"{c.topic} ({c.msgtype})" for c in connections})) or "nothing"
    if topic is not None:
        named = [c for c in connections if c.topic == topic]
        if not named:
            raise BagError(f"{path}: no topic {topic}; the bag holds {held}")
        kinds = {c.msgtype for c in named}
        if len(kinds) > 1 or named[0].msgtype not in SCAN_TYPES:
            raise BagError(
                f"{path}: topic {topic} is of type {', '.join(sorted(kinds))}; rafd reads radar scans of type "
                f"{', '.join(SCAN_TYPES)}"
            )
        if len(named) > 1:
            raise BagError(f"{path}: topic {topic} is recorded on {len(named)} connections; rafd reads one")
        return named[0]
    for msgtype in SCAN_TYPES:
        of_type = sorted({c.topic for c in connections if c.msgtype == msgtype})
        if len(of_type) == 1:
            return next(c for c in connections if c.topic == of_type[0])
        if len(of_type) > 1:
            raise BagError(
                f"{path}: {len(of_type)} topics of type {msgtype} ({', '.join(of_type)}): name one with --topic"
            )
    raise BagError(f"{path}: no radar scan topic (of type {', '.join(SCAN_TYPES)}); the bag holds {held}")


def header_stamp_ns(raw: bytes, ros1: bool) -> int:
    """The header stamp of a serialised scan message, whose first field is (or starts with) a std_msgs/Header: read
    from its bytes without decoding the rest (CDR: after the 4-byte encapsulation; ROS 1: after the header's seq)."""
    if ros1:
        sec, nanosec = struct.unpack_from("<II", raw, 4)
    else:
        order = "<" if raw[1] else ">"
        sec, nanosec = struct.unpack_from(f"{order}iI", raw, 4)
    return int(sec) * 1_000_000_000 + int(nanosec)


def decode_scan(topic: BagTopic, decoder: _Decoder, connection: Any, log_time: int, raw: bytes, index: int) -> BagScan:
    """One scan message -> BagScan; BagError naming the topic and message."""
    where = f"{topic.path}: topic {topic.topic}, message {index}"
    if len(raw) > MAX_MESSAGE_BYTES:
        raise BagError(f"{where}: {len(raw)} bytes, more than {MAX_MESSAGE_BYTES} (no radar scan is that large)")
    try:
        message = decoder.decode(connection, raw)
    except BagError:
        raise
    except Exception as error:
        raise BagError(f"{where}: does not decode as {connection.msgtype} ({_describe(error)})") from error
    geometry = topic.geometry_at(log_time)
    convert = {types.B_SCAN: from_b_scan, types.IMAGE: from_image, types.COMPRESSED_IMAGE: from_compressed_image}
    try:
        return convert[connection.msgtype](message, geometry)
    except (ScanError, AttributeError, TypeError) as error:  # AttributeError: a definition without the fields
        raise BagError(f"{where}: {_describe(error) if not isinstance(error, ScanError) else error}") from error


def scan_topic(path: str | Path, topic: str | None = None, flags: RadarGeometry | None = None) -> BagTopic:
    """The bag's scan topic and its configuration (no scan is read)."""
    path = Path(path)
    with open_bag(path) as (reader, decoder):
        connection = find_scan_topic(reader, path, topic)
        geometries = read_geometries(reader, decoder, path, None if flags is None else flags.rotation_hz)
        return BagTopic(path, connection.topic, connection.msgtype, int(connection.msgcount), geometries, flags)


def read_scans(
    topic: BagTopic, start_ns: int | None = None, stop_ns: int | None = None
) -> Iterator[tuple[int, BagScan]]:
    """(log time ns, BagScan) of the topic's messages in log-time order (those logged in [start_ns, stop_ns) when
    given), one message held at a time."""
    with open_bag(topic.path) as (reader, decoder):
        connections = [c for c in reader.connections if c.topic == topic.topic and c.msgtype == topic.msgtype]
        if not connections:
            raise BagError(f"{topic.path}: topic {topic.topic} ({topic.msgtype}) is gone")
        iterator = reader.messages(connections=connections, start=start_ns, stop=stop_ns)
        index = 0
        for connection, log_time, raw in _guarded(iterator, topic.path, f"topic {topic.topic}"):
            yield log_time, decode_scan(topic, decoder, connection, log_time, raw, index)
            index += 1
        if start_ns is None and stop_ns is None:
            _check_count(topic, connections, index)


def _check_count(topic: BagTopic, connections: list[Any], read: int) -> None:
    """BagError when fewer messages were read than the bag's index lists: a corrupt record was skipped."""
    listed = sum(int(c.msgcount) for c in connections)
    if listed and read != listed:
        raise BagError(
            f"{topic.path}: topic {topic.topic}: the bag's index lists {listed} messages, {read} could be read "
            "(corrupt records)"
        )


def list_stamps(topic: BagTopic) -> list[tuple[int, int]]:
    """(log time ns, header stamp ns) of every scan message, from the messages' first bytes (nothing is decoded)."""
    with open_bag(topic.path) as (reader, decoder):
        connections = [c for c in reader.connections if c.topic == topic.topic]
        listed = []
        messages = _guarded(reader.messages(connections=connections), topic.path, f"topic {topic.topic}")
        for index, (_, log_time, raw) in enumerate(messages):
            if len(raw) > MAX_MESSAGE_BYTES:
                raise BagError(f"{topic.path}: topic {topic.topic}, message {index}: {len(raw)} bytes, too large")
            try:
                listed.append((log_time, header_stamp_ns(raw, decoder.ros1)))
            except struct.error as error:
                raise BagError(f"{topic.path}: topic {topic.topic}, message {index}: too short for a header") from error
        _check_count(topic, connections, len(listed))
        return listed
