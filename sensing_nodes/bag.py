"""rosbag2 MCAP bags of rclpy messages, written and read with rosbags.

Messages are serialised by rclpy itself (CDR, exactly what goes over DDS), so a bag holds the
bytes a ROS 2 recorder would have written and reads back into the same message classes.
"""

from __future__ import annotations

import importlib
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from rclpy.serialization import deserialize_message, serialize_message
from rosbags.rosbag2 import CompressionFormat, CompressionMode, Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)


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
        """Append one already CDR-serialised message of a topic registered with add_topic."""
        self._writer.write(self._connections[topic], int(stamp_ns), data)
        self.counts[topic] += 1


def read_messages(
    path: str | Path, topics: Iterable[str] | None = None
) -> Iterator[tuple[str, int, Any]]:
    """(topic, bag time ns, rclpy message) for every message in the bag, in bag-time order."""
    with Reader(Path(path)) as reader:
        connections = [c for c in reader.connections if topics is None or c.topic in set(topics)]
        classes = {c.id: message_class(c.msgtype) for c in connections}
        for connection, timestamp, raw in reader.messages(connections=connections):
            yield connection.topic, timestamp, deserialize_message(raw, classes[connection.id])


def topic_counts(path: str | Path) -> dict[str, tuple[str, int]]:
    """topic -> (type, message count) from the bag's metadata."""
    with Reader(Path(path)) as reader:
        return {c.topic: (c.msgtype, c.msgcount) for c in reader.connections}
