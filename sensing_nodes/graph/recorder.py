"""Recording every topic of a running graph into a rosbag2 MCAP bag, as `ros2 bag record -a` would.

Messages are taken as serialised bytes and written as they are (no deserialisation on the hot
path, so one recorder keeps up with a whole graph). A message's bag time is its header stamp
(simulated or sensor time) read from the CDR bytes (a TFMessage's: its first transform's), or
the newest stamp seen for messages without one, so the bag replays on the data's own timeline.
The wall time each message arrived is handed to listeners for latency measurements.

Each discovered topic is subscribed with its publishers' QoS, as rosbag2 adapts to them: best
effort if any publisher is, transient local if all are (/tf_static: the sensor mounts, latched
before the recorder subscribed, still arrive), and their profiles are stored as the topic's
offered QoS. The bag's open chunk is flushed every wall second (BagWriter.flush), so a crash
loses at most about a second of the recording.
"""

from __future__ import annotations

import time
from collections import defaultdict
from typing import Callable

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from sensing_nodes.bags.stamps import first_field_type, leading_stamp_ns, stamp_reader
from sensing_nodes.bags.storage import BagWriter, message_class

# Graph-internal topics nobody wants in a data bag.
EXCLUDED_TOPICS = {'/rosout', '/parameter_events'}
FLUSH_PERIOD_S = 1.0   # wall seconds between two flushes of the bag's open chunk
_DEPTH = 100           # as the package's own subscriptions (ros/qos.py)


class TopicRecorder:
    """Subscribes `node` to every published topic it discovers and writes what arrives to `bag`.

    `listeners[topic]` callbacks also get (raw bytes, stamp ns, wall ns) of each message.
    `only`, when given, limits recording to those topics (e.g. a replay records the graph's
    outputs, not the inputs it publishes itself).
    """

    def __init__(self, node: Node, bag: BagWriter | None,
                 listeners: dict[str, Callable[[bytes, int, int], None]] | None = None,
                 only: set[str] | None = None) -> None:
        self._node = node
        self._only = None if only is None else set(only)
        self._bag = bag
        self._listeners = listeners or {}
        self._subscriptions: dict[str, object] = {}
        self.counts: dict[str, int] = defaultdict(int)
        self.newest_stamp_ns = 0
        if bag is not None:
            self._flush_timer = node.create_timer(FLUSH_PERIOD_S, bag.flush)

    def discover(self, not_yet: set[str] | frozenset = frozenset()) -> list[str]:
        """Subscribe to topics that appeared (with a publisher) since the last call, except
        `not_yet` (topics to subscribe to later, e.g. when a subscription gates a publisher)."""
        added = []
        for topic, types in self._node.get_topic_names_and_types():
            if topic in self._subscriptions or topic in EXCLUDED_TOPICS or len(types) != 1 \
                    or topic in not_yet:
                continue
            if self._only is not None and topic not in self._only:
                continue
            offered = [p.qos_profile for p in self._node.get_publishers_info_by_topic(topic)]
            if not offered:
                continue  # only subscribers so far: wait for a publisher to choose the QoS
            if self.subscribe(topic, types[0], qos_matching(offered), offered):
                added.append(topic)
        return added

    def subscribe(self, topic: str, type_name: str, qos: QoSProfile,
                  offered: list[QoSProfile] | None = None) -> bool:
        """Record `topic` from now on (before its publisher exists, when the QoS is known);
        `offered`: its publishers' QoS, stored in the bag."""
        try:
            msg_type = message_class(type_name)
        except (ImportError, AttributeError, ValueError):
            return False
        stamp_of = _stamp_reader(type_name)
        if self._bag is not None:
            self._bag.add_topic(topic, type_name, offered or None)
        self._subscriptions[topic] = self._node.create_subscription(
            msg_type, topic,
            lambda raw, topic=topic, stamp_of=stamp_of: self._on_message(topic, raw, stamp_of),
            qos, raw=True)
        return True

    def _on_message(self, topic: str, raw: bytes, stamp_of: Callable[[bytes, int], int]) -> None:
        wall_ns = time.monotonic_ns()
        stamp = stamp_of(raw, 0)
        if stamp <= 0:
            stamp = self.newest_stamp_ns
        self.newest_stamp_ns = max(self.newest_stamp_ns, stamp)
        self.counts[topic] += 1
        if self._bag is not None:
            self._bag.write_raw(topic, raw, stamp)
        listener = self._listeners.get(topic)
        if listener is not None:
            listener(raw, stamp, wall_ns)


def _stamp_reader(type_name: str) -> Callable[[bytes, int], int]:
    """stamps.stamp_reader, and a message that starts with a Time (/clock) carries that."""
    if first_field_type(type_name) == 'builtin_interfaces/Time':
        return lambda raw, fallback_ns: leading_stamp_ns(raw)
    return stamp_reader(type_name)


def qos_matching(offered: list[QoSProfile]) -> QoSProfile:
    """The subscription that matches every publisher's QoS and loses the least, as rosbag2's
    recorder adapts: reliable unless a publisher is best effort, transient local if every
    publisher is (a latched message published before the subscription still arrives)."""
    best_effort = any(p.reliability == ReliabilityPolicy.BEST_EFFORT for p in offered)
    latched = bool(offered) and all(p.durability == DurabilityPolicy.TRANSIENT_LOCAL
                                    for p in offered)
    return QoSProfile(
        reliability=ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
        history=HistoryPolicy.KEEP_LAST, depth=_DEPTH)
