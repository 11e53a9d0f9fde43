"""Recording every topic of a running graph into a rosbag2 MCAP bag, as `ros2 bag record -a` would.

Messages are taken as serialised bytes and written as they are (no deserialisation on the hot
path, so one recorder keeps up with a whole graph). A message's bag time is its header stamp
(simulated or sensor time) read from the CDR bytes, or the newest stamp seen for messages
without one, so the bag replays on the data's own timeline. The wall time each message arrived
is handed to listeners for latency measurements.
"""

from __future__ import annotations

import time
from collections import defaultdict
from typing import Callable

from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

from sensing_nodes.bags.stamps import leading_stamp_ns
from sensing_nodes.bags.storage import BagWriter, message_class
from sensing_nodes.ros.qos import ESTIMATE_QOS, SENSOR_QOS

# Graph-internal topics nobody wants in a data bag.
EXCLUDED_TOPICS = {'/rosout', '/parameter_events'}
_STAMP_FIRST = {'std_msgs/Header', 'builtin_interfaces/Time'}


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
            if not self._node.get_publishers_info_by_topic(topic):
                continue  # only subscribers so far: wait for a publisher to choose the QoS
            if self.subscribe(topic, types[0], self._qos_for(topic)):
                added.append(topic)
        return added

    def subscribe(self, topic: str, type_name: str, qos: QoSProfile) -> bool:
        """Record `topic` from now on (before its publisher exists, when the QoS is known)."""
        try:
            msg_type = message_class(type_name)
        except (ImportError, AttributeError, ValueError):
            return False
        first_field = next(iter(msg_type.get_fields_and_field_types().values()), '')
        stamped = first_field in _STAMP_FIRST
        if self._bag is not None:
            self._bag.add_topic(topic, type_name)
        self._subscriptions[topic] = self._node.create_subscription(
            msg_type, topic,
            lambda raw, topic=topic, stamped=stamped: self._on_message(topic, raw, stamped),
            qos, raw=True)
        return True

    def _qos_for(self, topic: str) -> QoSProfile:
        publishers = self._node.get_publishers_info_by_topic(topic)
        if any(p.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for p in publishers):
            return SENSOR_QOS
        return ESTIMATE_QOS

    def _on_message(self, topic: str, raw: bytes, stamped: bool) -> None:
        wall_ns = time.monotonic_ns()
        stamp = leading_stamp_ns(raw) if stamped else 0
        if stamp <= 0:
            stamp = self.newest_stamp_ns
        self.newest_stamp_ns = max(self.newest_stamp_ns, stamp)
        self.counts[topic] += 1
        if self._bag is not None:
            self._bag.write_raw(topic, raw, stamp)
        listener = self._listeners.get(topic)
        if listener is not None:
            listener(raw, stamp, wall_ns)
