"""In-process edges: a message published by one node and subscribed by another node of the same
process (sensing_graph) is handed over without DDS, and goes on DDS only while a subscriber
outside the process matches its publisher.

How (docs/performance.md, "In-process edges"):
- The process's DDS participant is made not to match its own endpoints (Fast DDS's participant
  property `fastdds.ignore_local_endpoints`, from a generated XML profile: `request_profile`
  before rclpy.init; `participant_ignores_own_endpoints` checks that it took). Every node keeps
  its DDS subscriptions, so the graph (`ros2 topic info`, a tool waiting for subscribers) is as
  it was, but a publisher now matches only subscriptions outside the process:
  `get_subscription_count()` counts exactly those.
- `wire` (ros/processor.py) publishes a node's outputs through `InProcessPublisher`: the
  message's CDR bytes go into the process's queue for every subscription of this process on the
  topic (same type, compatible QoS, as DDS would match them), and onto DDS only while
  `get_subscription_count()` > 0 (always for a transient-local publisher, whose late joiners
  need its history). A managed node's inactive publisher sends neither way.
- The queue is drained on the executor's thread once the callback that published has returned
  (breadth first, in publication order, as the DDS path queues them), each subscription's own
  callback called with what DDS would give it: the bytes for a raw subscription (the nodes'
  decoded inputs, ros/cdr.py), an rclpy message otherwise. A managed node's gate
  (`when_active`) is part of that callback: inactive, it drops and counts the message.
"""

from __future__ import annotations

import os
import tempfile
import time
import weakref
from collections import deque
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

from rclpy.qos import DurabilityPolicy, QoSCompatibility, qos_check_compatible
from rclpy.serialization import deserialize_message, serialize_message
from rclpy.subscription import Subscription

# Fast DDS reads its XML profiles from this file (else from DEFAULT_FASTRTPS_PROFILES.xml in the
# working directory, unless SKIP_DEFAULT_XML_FILE=1), once, when the process first uses DDS.
PROFILES_VARIABLE = 'FASTRTPS_DEFAULT_PROFILES_FILE'
DEFAULT_PROFILES_FILE = 'DEFAULT_FASTRTPS_PROFILES.xml'
IGNORE_LOCAL_ENDPOINTS = 'fastdds.ignore_local_endpoints'
_PROFILE = f"""<?xml version="1.0" encoding="UTF-8"?>
<!-- sensing_graph's in-process edges (sensing_nodes/ros/in_process.py): the process's
     participant does not match its own endpoints. -->
<dds xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <profiles>
    <participant profile_name="sensing_graph_in_process" is_default_profile="true">
      <rtps>
        <propertiesPolicy>
          <properties>
            <property>
              <name>{IGNORE_LOCAL_ENDPOINTS}</name>
              <value>true</value>
            </property>
          </properties>
        </propertiesPolicy>
      </rtps>
    </participant>
  </profiles>
</dds>
"""
_CHECK_TOPIC = '/_sensing_graph/in_process_check'   # hidden: ros2 topic list does not show it


def request_profile(directory: Path) -> str | None:
    """Before rclpy.init: point Fast DDS at a profile (written into `directory`) whose default
    participant ignores its own endpoints; None when done, else why not (the user's own
    profile file is in force: it is never replaced)."""
    if os.environ.get(PROFILES_VARIABLE):
        return f'{PROFILES_VARIABLE} is set ({os.environ[PROFILES_VARIABLE]})'
    if Path(DEFAULT_PROFILES_FILE).is_file() and os.environ.get('SKIP_DEFAULT_XML_FILE') != '1':
        return f'{Path(DEFAULT_PROFILES_FILE).resolve()} is in force'
    path = directory / 'sensing_graph_in_process.xml'
    path.write_text(_PROFILE)
    os.environ[PROFILES_VARIABLE] = str(path)
    return None


def participant_ignores_own_endpoints(context) -> bool:
    """Whether the context's DDS participant leaves its own endpoints unmatched (a publisher
    sees no subscription of the same process): checked with a hidden node, publisher and
    subscription, destroyed at once. Local matching is immediate in Fast DDS."""
    from rclpy.node import Node
    from std_msgs.msg import Empty

    node = Node('_sensing_graph_in_process_check', context=context,
                start_parameter_services=False, enable_rosout=False)
    try:
        publisher = node.create_publisher(Empty, _CHECK_TOPIC, 1)
        node.create_subscription(Empty, _CHECK_TOPIC, lambda msg: None, 1)
        return publisher.get_subscription_count() == 0
    finally:
        node.destroy_node()


@dataclass
class TopicCounts:
    """What one topic's in-process publishers did: messages handed to subscriptions of this
    process (any number of them), published on DDS, and not published on DDS (no subscriber
    outside)."""

    handed_over: int = 0
    on_dds: int = 0
    not_on_dds: int = 0


class InProcessEdges:
    """A process's in-process transport: its nodes (those `wire` built), the queue of messages
    handed over, and per-topic counts. One executor thread only (sensing_graph refuses the
    multi-threaded executor with it)."""

    def __init__(self) -> None:
        self._nodes: list[Any] = []
        self._queue: deque = deque()
        self._busy = False
        self.version = 0            # bumped when a node (re)configures: subscriptions made
        self.counts: dict[str, TopicCounts] = {}
        self._handed: weakref.WeakSet = weakref.WeakSet()   # the publishers wrapped here

    def add_node(self, node) -> None:
        """A node whose subscriptions may take in-process messages (again: it reconfigured)."""
        if node not in self._nodes:
            self._nodes.append(node)
        self.version += 1
        for topic in self.unserved():
            node.get_logger().error(
                f'{topic} is published in this process outside the in-process edges and '
                'subscribed here: its subscribers here will not hear it (sensing_graph '
                '--over-dds)')

    def unserved(self) -> list[str]:
        """Topics a node here subscribes and a publisher here not handing over publishes with
        the same type (none among the processing nodes' own: their only other publisher is
        /diagnostics): the participant ignores its own endpoints, so those subscriptions would
        hear nothing from it."""
        subscribed = {(s.topic_name, s.msg_type) for node in self._nodes
                      for s in node.subscriptions}
        return sorted({p.topic_name for node in self._nodes for p in node.publishers
                       if p not in self._handed and (p.topic_name, p.msg_type) in subscribed})

    def layout(self) -> tuple[int, int]:
        """Changes when a node's subscriptions are made (add_node) or destroyed (a managed
        node cleaned up: its subscriptions no longer take anything, as over DDS)."""
        return self.version, sum(1 for node in self._nodes for _ in node.subscriptions)

    def publisher(self, publisher) -> InProcessPublisher:
        """`publisher`, publishing through the in-process edges."""
        self._handed.add(publisher)
        return InProcessPublisher(self, publisher)

    def consumers(self, topic: str, msg_type: type, qos) -> list[Subscription]:
        """This process's subscriptions DDS would match with a publisher of (topic, type, QoS):
        same resolved topic name and type, compatible QoS."""
        return [s for node in self._nodes for s in node.subscriptions
                if s.msg_type is msg_type and s.topic_name == topic
                and qos_check_compatible(qos, s.qos_profile)[0] != QoSCompatibility.ERROR]

    def hand_over(self, subscriptions: list[Subscription], raw: bytes) -> None:
        """Queue a message's CDR bytes for each subscription; delivered by drain."""
        for subscription in subscriptions:
            self._queue.append((subscription, raw))

    @contextmanager
    def batch(self) -> Iterator[None]:
        """Around a callback that publishes: what it hands over is delivered once it returns
        (breadth first); nested (a callback run by drain), only queued."""
        if self._busy:
            yield
            return
        self._busy = True
        try:
            yield
            self._drain()
        finally:
            self._busy = False
            self._queue.clear()   # only non-empty when a callback raised: the error goes up

    def drain(self) -> None:
        """Deliver what is queued unless a callback is running (it delivers when it returns)."""
        if self._busy:
            return
        with self.batch():
            pass

    def _drain(self) -> None:
        queue = self._queue
        while queue:
            subscription, raw = queue.popleft()
            msg = raw if subscription.raw else deserialize_message(raw, subscription.msg_type)
            if getattr(subscription, '_callback_type', None) is \
                    Subscription.CallbackType.WithMessageInfo:
                now = time.time_ns()
                subscription.callback(msg, {'source_timestamp': now, 'received_timestamp': now,
                                            'publication_sequence_number': 0,
                                            'reception_sequence_number': 0})
            else:
                subscription.callback(msg)


class InProcessPublisher:
    """A publisher whose messages reach this process's subscriptions through the in-process
    edges, and DDS only while a subscriber outside the process matches (the participant ignores
    its own endpoints: get_subscription_count() counts only those)."""

    def __init__(self, edges: InProcessEdges, publisher) -> None:
        self._edges = edges
        self._publisher = publisher
        self.topic = publisher.topic_name          # resolved: namespace and remapping applied
        self._type = publisher.msg_type
        self._qos = publisher.qos_profile
        self._latched = publisher.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
        self.counts = edges.counts.setdefault(self.topic, TopicCounts())
        self._consumers: list[Subscription] = []
        self._layout = (-1, -1)   # of the edges when _consumers was found

    def publish(self, msg: Any) -> None:
        """Hand `msg` (an rclpy message or its CDR bytes) to this process's subscriptions of the
        topic and, while one outside matches, publish it on DDS."""
        publisher = self._publisher
        if not getattr(publisher, 'is_activated', True):   # an inactive lifecycle publisher
            return
        edges = self._edges
        consumers = self._current_consumers()
        if consumers:
            if not isinstance(msg, bytes):
                msg = serialize_message(msg)   # now, as DDS would: the node may reuse msg
            edges.hand_over(consumers, msg)
            self.counts.handed_over += 1
        if self._latched or publisher.get_subscription_count():
            publisher.publish(msg)
            self.counts.on_dds += 1
        else:
            self.counts.not_on_dds += 1
        edges.drain()

    def taken(self) -> bool:
        """Whether a subscription takes the topic now: one of this process's (an in-process
        edge) or one outside it (DDS)."""
        return bool(self._current_consumers()) or self._publisher.get_subscription_count() > 0

    def _current_consumers(self) -> list[Subscription]:
        """This process's subscriptions of the topic, found again only when a node or a
        subscription came or went (the edges' layout changed)."""
        layout = self._edges.layout()
        if self._layout != layout:
            self._consumers = self._edges.consumers(self.topic, self._type, self._qos)
            self._layout = layout
        return self._consumers

    def __getattr__(self, name: str) -> Any:
        return getattr(self._publisher, name)


_EDGES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def enable(context) -> InProcessEdges:
    """In-process edges for the nodes `wire` builds in `context` from now on."""
    edges = _EDGES.get(context)
    if edges is None:
        edges = _EDGES[context] = InProcessEdges()
    return edges


def edges_of(context) -> InProcessEdges | None:
    """The context's in-process edges; None: every topic over DDS (the default)."""
    return _EDGES.get(context)


def profile_directory() -> tempfile.TemporaryDirectory:
    """A private folder for the generated profile (removed when the process ends)."""
    return tempfile.TemporaryDirectory(prefix='sensing_graph-')
