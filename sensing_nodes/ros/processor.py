"""A node's per-message logic as a plain object (no rclpy node, no publishers): messages in,
(topic, message) pairs out, in the order the node publishes them.

The node wraps it (`wire`: one subscription per input, one publisher per output) and
`sensing_pipeline` drives it over a bag without DDS, so both run the same code.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

from rclpy.qos import QoSProfile

from sensing_nodes.ros.cdr import create_decoded_subscription
from sensing_nodes.ros.in_process import InProcessPublisher, edges_of
from sensing_nodes.ros.processing_node import ProcessingNode

# (topic, rclpy message or its CDR bytes), in publication order; bytes a processor returns are
# canonical CDR (ros/cdr.py's encoders), which sensing_pipeline stores as they are.
Outputs = list[tuple[str, Any]]


@dataclass(frozen=True)
class Input:
    """One input of a processor: its topic, message class, QoS and handler."""

    topic: str
    msg_type: type
    qos: QoSProfile
    handler: Callable[[Any], Outputs]
    decoded: bool = False   # high-rate input: rosbags decodes it (ros/cdr.py; read-only message)


@dataclass(frozen=True)
class Output:
    """One output of a processor: its topic, message class and QoS."""

    topic: str
    msg_type: type
    qos: QoSProfile


def subscribed(publishers: dict[str, Any]) -> Callable[[str], bool]:
    """topic -> whether a subscription matches its publisher now (in this process, through an
    in-process edge or DDS, or another): an output nobody takes need not be made
    (sensing_pipeline, which records every output, asks nothing of the kind)."""
    def taken(topic: str) -> bool:
        publisher = publishers[topic]
        if isinstance(publisher, InProcessPublisher):
            return publisher.taken()
        return publisher.get_subscription_count() > 0
    return taken


def wire(node: ProcessingNode, inputs: list[Input], outputs: list[Output]) -> dict[str, Any]:
    """Subscribe `node` to each input and publish what its handler returns, in order; returns
    the publishers (topic -> publisher), for outputs of the node's own timers and services.
    Managed (ros/processing_node.py), the publishers send only while the node is active, and
    inputs arriving while it is not are dropped and counted. In a process with in-process edges
    (sensing_graph, ros/in_process.py) the publishers hand their messages to the process's
    subscriptions directly, once the callback has returned, and use DDS only for subscribers
    outside the process."""
    publishers = {o.topic: node.create_publisher(o.msg_type, o.topic, o.qos) for o in outputs}
    edges = edges_of(node.context)
    if edges is not None:
        publishers = {topic: edges.publisher(p) for topic, p in publishers.items()}
        edges.add_node(node)

    def callback(handler: Callable[[Any], Outputs]) -> Callable[[Any], None]:
        def on_message(msg: Any) -> None:
            for topic, out in handler(msg):
                publishers[topic].publish(out)

        if edges is not None:
            def on_message_in_process(msg: Any) -> None:
                with edges.batch():
                    on_message(msg)
            return node.when_active(on_message_in_process)
        return node.when_active(on_message)

    for i in inputs:
        if i.decoded:
            create_decoded_subscription(node, i.msg_type, i.topic, callback(i.handler), i.qos)
        else:
            node.create_subscription(i.msg_type, i.topic, callback(i.handler), i.qos)
    return publishers
