"""Recording every topic of a running graph into a rosbag2 MCAP bag, as `ros2 bag record -a` would.

The bag's time of a message is its header stamp (simulated or sensor time), or the newest stamp
seen for messages without a header, so the bag replays on the data's own timeline. The wall time
each message arrived is kept alongside for latency measurements.
"""

from __future__ import annotations

import time
from collections import defaultdict
from typing import Any, Callable

from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

from sensing_nodes.bag import BagWriter, message_class
from sensing_nodes.ros.conversions import stamp_to_ns
from sensing_nodes.ros.qos import ESTIMATE_QOS, SENSOR_QOS

# Graph-internal topics nobody wants in a data bag.
EXCLUDED_TOPICS = {'/rosout', '/parameter_events'}


def message_stamp_ns(msg: Any) -> int | None:
    """The data time of a message: header stamp, /clock value, or first marker's stamp."""
    header = getattr(msg, 'header', None)
    if header is not None:
        return stamp_to_ns(header.stamp)
    clock = getattr(msg, 'clock', None)
    if clock is not None:
        return stamp_to_ns(clock)
    markers = getattr(msg, 'markers', None)
    if markers:
        return stamp_to_ns(markers[0].header.stamp)
    return None


class TopicRecorder:
    """Subscribes `node` to every topic it discovers and writes what arrives to `bag`.

    `listeners[topic]` callbacks also get (msg, stamp_ns, wall_ns) for live analysis.
    """

    def __init__(self, node: Node, bag: BagWriter | None,
                 listeners: dict[str, Callable[[Any, int, int], None]] | None = None) -> None:
        self._node = node
        self._bag = bag
        self._listeners = listeners or {}
        self._subscriptions: dict[str, Any] = {}
        self.counts: dict[str, int] = defaultdict(int)
        self.newest_stamp_ns = 0

    def discover(self) -> list[str]:
        """Subscribe to topics that appeared since the last call; returns the new ones."""
        added = []
        for topic, types in self._node.get_topic_names_and_types():
            if topic in self._subscriptions or topic in EXCLUDED_TOPICS or len(types) != 1:
                continue
            try:
                msg_type = message_class(types[0])
            except (ImportError, AttributeError, ValueError):
                continue
            qos = self._qos_for(topic)
            self._subscriptions[topic] = self._node.create_subscription(
                msg_type, topic, lambda msg, topic=topic: self._on_message(topic, msg), qos)
            if self._bag is not None:
                self._bag.add_topic(topic, types[0])
            added.append(topic)
        return added

    def _qos_for(self, topic: str) -> QoSProfile:
        publishers = self._node.get_publishers_info_by_topic(topic)
        if any(p.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for p in publishers):
            return SENSOR_QOS
        return ESTIMATE_QOS

    def _on_message(self, topic: str, msg: Any) -> None:
        wall_ns = time.monotonic_ns()
        stamp = message_stamp_ns(msg)
        if stamp is None or stamp == 0:
            stamp = self.newest_stamp_ns
        self.newest_stamp_ns = max(self.newest_stamp_ns, stamp)
        self.counts[topic] += 1
        if self._bag is not None:
            self._bag.write(topic, msg, stamp)
        listener = self._listeners.get(topic)
        if listener is not None:
            listener(msg, stamp, wall_ns)
