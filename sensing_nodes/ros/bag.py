"""rosbag2 bags of rclpy messages, written (MCAP) and read (MCAP or sqlite3, and ROS 1 .bag
files) with rosbags.

Every message is written in canonical CDR: the fields exactly as rclpy/DDS serialise them, but
with every alignment padding byte zero and no bytes after the last field (`canonical_cdr`).
rclpy's serialiser leaves padding uninitialised (process memory) and appends 4 alignment bytes
after a trailing empty sequence of 8-byte elements (JointState's `effort`), which rosbags'
strict reader rejects; canonical bytes make same-seed recordings byte-identical and decode with
rosbags, mcap-ros2-support and rclpy alike.
"""

from __future__ import annotations

import heapq
import importlib
import signal
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.rosbag2 import CompressionFormat, CompressionMode, Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

_DEFERRED_SIGNALS = {signal.SIGINT, signal.SIGTERM}

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)


class BagError(Exception):
    """A bag that cannot be read: the message names the file and what is wrong."""


def canonical_cdr(raw: bytes | memoryview, msgtype: str) -> bytes:
    """CDR bytes of a 'pkg/msg/Name' message -> the same message in canonical CDR (same byte
    order and values, padding zero, nothing after the last field), through rosbags' typestore."""
    msgdef = TYPESTORE.get_msgdef(msgtype)
    if len(raw) < 4 or bytes(raw[:2]) not in (b'\x00\x00', b'\x00\x01'):
        raise ValueError(f'{msgtype}: not a CDR message (encapsulation header {bytes(raw[:4])!r})')
    little_endian = bool(raw[1])
    decode = msgdef.deserialize_cdr_le if little_endian else msgdef.deserialize_cdr_be
    # Bytes after the last field are dropped: Fast-CDR aligns before the (absent) elements of
    # each empty sequence of doubles, so an all-empty JointState ends in 8 such bytes.
    message, _ = decode(memoryview(raw)[4:], 0, msgdef.cls, TYPESTORE)
    return bytes(TYPESTORE.serialize_cdr(message, msgtype, little_endian=little_endian))


def type_name(msg_or_class: Any) -> str:
    """rclpy message (or class) -> 'pkg/msg/Name'."""
    cls = msg_or_class if isinstance(msg_or_class, type) else type(msg_or_class)
    return f"{cls.__module__.split('.')[0]}/msg/{cls.__name__}"


def message_class(name: str) -> type:
    """'pkg/msg/Name' -> the rclpy message class."""
    package, _, cls = name.split('/')
    return getattr(importlib.import_module(f'{package}.msg'), cls)


def bag_qos(profile: Any) -> Any:
    """rclpy QoSProfile -> the rosbags QoS record of a bag's offered_qos_profiles (a rosbags
    record, e.g. read from another bag, is kept as it is)."""
    from rosbags.interfaces import (
        Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime,
    )

    if isinstance(profile, Qos):
        return profile

    def duration(d) -> QosTime:
        sec, nsec = divmod(int(d.nanoseconds), 1_000_000_000)
        return QosTime(sec, nsec)

    return Qos(QosHistory(int(profile.history)), int(profile.depth),
               QosReliability(int(profile.reliability)), QosDurability(int(profile.durability)),
               duration(profile.deadline), duration(profile.lifespan),
               QosLiveliness(int(profile.liveliness)), duration(profile.liveliness_lease_duration),
               bool(profile.avoid_ros_namespace_conventions))


class BagWriter:
    """Writes rclpy messages to a new rosbag2 (format 9, MCAP storage) at `path`; with
    `compress`, MCAP chunks are zstd-compressed (storage-level, as rosbag2's MCAP presets do)."""

    def __init__(self, path: str | Path, compress: bool = False) -> None:
        self.path = Path(path)
        self._writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        if compress:
            self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        self._connections: dict[str, Any] = {}
        self.counts: dict[str, int] = {}

    def __enter__(self) -> BagWriter:
        self._writer.open()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self._writer.close()

    def add_topic(self, topic: str, msg_type: str, qos: Any = None) -> None:
        """Register a topic up front, so it is in the bag even when no message arrives; `qos`
        (an rclpy QoSProfile, or a list of them) is stored as its offered QoS, which
        `ros2 bag play` publishes with."""
        if topic not in self._connections:
            profiles = [] if qos is None else [qos] if not isinstance(qos, (list, tuple)) else qos
            self._connections[topic] = self._writer.add_connection(
                topic, msg_type, typestore=TYPESTORE,
                offered_qos_profiles=[bag_qos(p) for p in profiles])
            self.counts[topic] = 0

    def write(self, topic: str, msg: Any, stamp_ns: int) -> None:
        """Append one message, with `stamp_ns` as its bag (receive) time."""
        self.add_topic(topic, type_name(msg))
        self.write_raw(topic, serialize_message(msg), stamp_ns)

    def write_raw(self, topic: str, data: bytes, stamp_ns: int) -> None:
        """Append one CDR-serialised message (as rclpy or DDS gave it) of a topic registered
        with add_topic; it is stored in canonical CDR."""
        connection = self._connections[topic]
        raw = canonical_cdr(data, connection.msgtype)
        # SIGINT/SIGTERM held off for the one write: raised inside the writer, after it counted
        # the message and before it stored it, the bag's metadata counted one message more than
        # it held (seen: 4471 counted, 4470 read back after a SIGINT).
        held = signal.pthread_sigmask(signal.SIG_BLOCK, _DEFERRED_SIGNALS)
        try:
            self._writer.write(connection, int(stamp_ns), raw)
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, held)
        self.counts[topic] += 1


@dataclass(frozen=True)
class TopicInfo:
    """One topic of a bag: message type, message count, offered QoS (rosbags records)."""

    msgtype: str
    count: int
    qos: tuple


class BagReader:
    """Reads a rosbag2 bag folder (metadata.yaml + MCAP or sqlite3 storage, metadata versions 4
    to 9, as written by rosbag2 itself or by BagWriter); BagError when it cannot.

    Each storage file is opened with the topics it declares itself: rosbags' folder reader
    matches them against metadata.yaml's QoS and silently yields nothing when the two disagree
    (rosbag2's own test bags store 'infinite' deadlines in the file, zero in metadata.yaml).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise BagError(f'{self.path}: no such bag')
        self._ros1: Ros1Bag | None = None
        if self.path.is_file():
            self._ros1 = Ros1Bag(self.path)
            self.topics = self._ros1.topics
            return
        if not (self.path / 'metadata.yaml').is_file():
            raise BagError(f'{self.path}: not a rosbag2 bag (no metadata.yaml)')
        try:
            with Reader(self.path) as folder:   # checks metadata.yaml and the storage files
                self._compressed = bool(folder.compression_mode)
            metadata = yaml.safe_load((self.path / 'metadata.yaml').read_text())
            files = [self.path / Path(p).name
                     for p in metadata['rosbag2_bagfile_information']['relative_file_paths']]
            self.topics: dict[str, TopicInfo] = {}
            counts: dict[str, int] = {}
            self._files = files
            for connection in self._connections():
                counts[connection.topic] = counts.get(connection.topic, 0) + connection.msgcount
                if connection.topic not in self.topics:
                    qos = tuple(getattr(connection.ext, 'offered_qos_profiles', None) or ())
                    self.topics[connection.topic] = TopicInfo(connection.msgtype, 0, qos)
            for topic, info in self.topics.items():
                self.topics[topic] = TopicInfo(info.msgtype, counts[topic], info.qos)
        except BagError:
            raise
        except Exception as exc:  # rosbags raises several types for damaged files
            raise BagError(f'{self.path}: cannot read the bag ({type(exc).__name__}: {exc}); '
                           'truncated or damaged?') from None

    def _connections(self):
        if self._compressed:   # file- or message-compressed: only the folder reader unpacks it
            with Reader(self.path) as reader:
                return list(reader.connections)
        connections = []
        for file in self._files:
            with Reader(file) as reader:
                connections += reader.connections
        return connections

    def _file_messages(self, file: Path | None, topics: set[str] | None):
        with Reader(self.path if file is None else file) as reader:
            wanted = [c for c in reader.connections if topics is None or c.topic in topics]
            if not wanted:   # rosbags reads every connection when given none
                return
            for connection, stamp, raw in reader.messages(connections=wanted):
                yield stamp, connection.topic, raw

    def raw(self, topics: Iterable[str] | None = None) -> Iterator[tuple[str, int, bytes]]:
        """(topic, bag time ns, CDR bytes) of every message (of `topics`), in bag-time order."""
        wanted = None if topics is None else set(topics)
        if self._ros1 is not None:
            for topic, stamp, msg in self._ros1.messages(wanted):
                yield topic, stamp, serialize_message(msg)
            return
        streams = [self._file_messages(None, wanted)] if self._compressed else \
            [self._file_messages(f, wanted) for f in self._files]
        for stamp, topic, raw in heapq.merge(*streams, key=lambda row: row[0]):
            yield topic, stamp, bytes(raw)

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[tuple[str, int, Any]]:
        """(topic, bag time ns, rclpy message) for every message (of `topics`)."""
        wanted = None if topics is None else set(topics)
        if self._ros1 is not None:
            yield from self._ros1.messages(wanted)
            return
        classes = {t: message_class(i.msgtype) for t, i in self.topics.items()
                   if wanted is None or t in wanted}
        for topic, stamp, raw in self.raw(classes):
            yield topic, stamp, deserialize_message(raw, classes[topic])


class Ros1Bag:
    """A ROS 1 bag (v2.0 .bag file) read with rosbags, its messages as the ROS 2 Jazzy rclpy
    messages of the same name, field by field (ROS 1's header.seq has no ROS 2 field: dropped)."""

    def __init__(self, path: Path) -> None:
        from rosbags.highlevel import AnyReader

        self.path = path
        try:
            with AnyReader([path], default_typestore=TYPESTORE) as reader:
                connections = list(reader.connections)
        except Exception as exc:  # rosbags raises several types for damaged or foreign files
            raise BagError(f'{path}: cannot read the bag ({type(exc).__name__}: {exc}); a '
                           'rosbag2 folder or a ROS 1 .bag file expected') from None
        self.topics: dict[str, TopicInfo] = {}
        for c in connections:
            count = self.topics[c.topic].count if c.topic in self.topics else 0
            self.topics[c.topic] = TopicInfo(c.msgtype, count + c.msgcount, ())

    def messages(self, topics: set[str] | None) -> Iterator[tuple[str, int, Any]]:
        """(topic, bag time ns, rclpy message), in bag-time order."""
        from rosbags.highlevel import AnyReader

        with AnyReader([self.path], default_typestore=TYPESTORE) as reader:
            wanted = [c for c in reader.connections if topics is None or c.topic in topics]
            if not wanted:   # rosbags reads every connection when given none
                return
            classes = {c.msgtype: message_class(c.msgtype) for c in wanted}
            for connection, stamp, raw in reader.messages(connections=wanted):
                msg = reader.deserialize(raw, connection.msgtype)
                yield connection.topic, stamp, to_rclpy(msg, classes[connection.msgtype])


def to_rclpy(value: Any, cls: type) -> Any:
    """A rosbags message object -> an instance of the rclpy message class cls, copying the
    fields cls has (a field cls lacks, e.g. ROS 1's header.seq, is dropped)."""
    out = cls()
    for name, kind in cls.get_fields_and_field_types().items():
        field = getattr(value, name)
        element = _message_element(kind)
        if element is not None and isinstance(field, list):
            setattr(out, name, [to_rclpy(item, element) for item in field])
        elif hasattr(field, '__msgtype__'):
            setattr(out, name, to_rclpy(field, type(getattr(out, name))))
        else:
            setattr(out, name, field)      # numbers, strings, numpy arrays of numbers
    return out


def _message_element(kind: str) -> type | None:
    """The rclpy class of a sequence or array field of messages ('sequence<pkg/Name>',
    'pkg/Name[3]'), None for any other field."""
    if not (kind.startswith('sequence<') or kind.endswith(']')) or '/' not in kind:
        return None
    package, name = kind.removeprefix('sequence<').split('[')[0].rstrip('>').split('/')
    return message_class(f'{package}/msg/{name.split(",")[0]}')


def read_messages(
    path: str | Path, topics: Iterable[str] | None = None
) -> Iterator[tuple[str, int, Any]]:
    """(topic, bag time ns, rclpy message) for every message in the bag, in bag-time order."""
    yield from BagReader(path).messages(topics)


def topic_counts(path: str | Path) -> dict[str, tuple[str, int]]:
    """topic -> (type, message count) of every topic in the bag."""
    return {t: (i.msgtype, i.count) for t, i in BagReader(path).topics.items()}
