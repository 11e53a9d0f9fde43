"""CPU per message of the per-message paths outside the fusion and the matcher: decoding the
high-rate messages (ros/cdr.py), and the wheel odometry, gyro integrator and line extractor
processors (what their nodes run per message, without DDS).

A bag is recorded with `sensor_sim --record` (60 s, seed 5; 20 s with --quick). Decoding: every
message of each input type of the bag, decoded in turn by cdr_decoder (the nodes' decoder) and
by rosbags' own generated decoder. Processors: each node is built as sensing_pipeline builds it
(config/ parameters), its inputs decoded beforehand (the gyro's /wheel/odom from the wheel
processor's outputs, in bag order), and the handlers timed with what publishing their outputs
converts (an rclpy message is serialised by rclpy's publish; packed bytes go as they are). CPU
time of this process (time.process_time), the best of 3 passes; warm caches, so a running node
costs several times this per message (docs/performance.md). Compare figures of one run only.
"""

from __future__ import annotations

import heapq
import os
import sys
import tempfile
import time
from pathlib import Path

PASSES = 3


def _best_us(function, count: int) -> float:
    """Fastest of PASSES calls of function() (which handles `count` messages), us per message."""
    best = float('inf')
    for _ in range(PASSES):
        started = time.process_time()
        function()
        best = min(best, time.process_time() - started)
    return round(1e6 * best / max(count, 1), 2)


def decoding(bag) -> dict:
    """us per message: cdr_decoder's and rosbags' decoder, per input type of the bag."""
    from sensing_nodes.bags.storage import TYPESTORE, message_class
    from sensing_nodes.ros.cdr import cdr_decoder

    out = {}
    for topic, name in (('/imu/data_raw', 'imu'), ('/joint_states', 'joint_state'),
                        ('/scan', 'laser_scan'), ('/ground_truth/odom', 'odometry')):
        msgtype = bag.types[topic]
        raws = [raw for t, _, raw in bag.messages if t == topic]
        ours = cdr_decoder(message_class(msgtype))
        msgdef = TYPESTORE.get_msgdef(msgtype)

        def rosbags(raws=raws, msgdef=msgdef):
            for raw in raws:
                msgdef.deserialize_cdr_le(memoryview(raw)[4:], 0, msgdef.cls, TYPESTORE)

        def generated(raws=raws, ours=ours):
            for raw in raws:
                ours(raw)

        out[f'decode_{name}_us'] = _best_us(generated, len(raws))
        out[f'decode_{name}_rosbags_us'] = _best_us(rosbags, len(raws))
    return out


def _handlers(node: str):
    """The node built as sensing_pipeline builds it, and its (topic -> (handler, decode))."""
    from rclpy.serialization import deserialize_message

    from sensing_nodes.graph.pipeline import build_nodes
    from sensing_nodes.ros.cdr import cdr_decoder

    built = build_nodes((node,), [], {})
    handlers = {}
    for i in built[node].processor.inputs():
        decode = cdr_decoder(i.msg_type) if i.decoded else \
            (lambda raw, cls=i.msg_type: deserialize_message(raw, cls))
        handlers[i.topic] = (i.handler, decode)
    return built, handlers


def _time_node(node: str, rows) -> tuple[float, int, list]:
    """Best-of-PASSES CPU seconds of the node's handlers over rows (topic, bag time, bytes) it
    takes, the number of messages, and its outputs of the last pass as such rows."""
    from rclpy.serialization import serialize_message

    from sensing_nodes.graph.pipeline import close

    best, outputs = float('inf'), []
    for _ in range(PASSES):
        built, handlers = _handlers(node)
        messages = [(s, handlers[t][0], handlers[t][1](raw)) for t, s, raw in rows
                    if t in handlers]
        produced = []
        started = time.process_time()
        for s, handler, msg in messages:
            outs = handler(msg)
            for _, out in outs:   # what publishing converts: rclpy messages are serialised
                if not isinstance(out, bytes):
                    serialize_message(out)
            produced.append((s, outs))
        best = min(best, time.process_time() - started)
        close(built)
        outputs = [(topic, s, out) for s, outs in produced for topic, out in outs]
    return best, len(messages), outputs


def processors(bag) -> dict:
    """us per input message of the wheel odometry, gyro integrator and line extractor
    processors (handlers only, inputs decoded beforehand); the gyro's /wheel/odom is the wheel
    processor's output, in bag order."""
    out = {}
    rows = [(t, s, raw) for t, s, raw in bag.messages]
    wheel_odom: list = []
    for node in ('wheel_odometry', 'gyro_integrator', 'line_extractor'):
        fed = rows if node != 'gyro_integrator' else list(heapq.merge(
            [row for row in rows if row[0] != '/wheel/odom'], wheel_odom,
            key=lambda row: row[1]))   # the wheel processor's, not a recorded /wheel/odom
        seconds, count, outputs = _time_node(node, fed)
        if node == 'wheel_odometry':
            wheel_odom = [row for row in outputs if row[0] == '/wheel/odom']
        out[f'{node}_us_per_message'] = round(1e6 * seconds / max(count, 1), 2)
        out[f'{node}_messages'] = count
    return out


def run(quick: bool = False) -> dict:
    """Record the bag, then the decoding and processor figures."""
    from sensing_nodes.bags.input_bag import load_bag
    from sensing_nodes.bench.pipeline import record_sim_bag

    duration_s = 20.0 if quick else 60.0
    with tempfile.TemporaryDirectory() as tmp:
        record_sim_bag(Path(tmp) / 'bag', duration_s)
        bag = load_bag(Path(tmp) / 'bag')
    figures = {'messages_bag_seconds': duration_s,
               'messages_load_average_1min_start': round(os.getloadavg()[0], 2)}
    figures.update(decoding(bag))
    figures.update(processors(bag))
    figures['messages_load_average_1min_end'] = round(os.getloadavg()[0], 2)
    return figures


if __name__ == '__main__':
    import json

    print(json.dumps(run(quick='--quick' in sys.argv), indent=2))
