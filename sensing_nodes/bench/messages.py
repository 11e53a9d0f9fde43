"""CPU per message of the per-message paths outside the fusion and the matcher: decoding the
high-rate messages (ros/cdr.py), and the wheel odometry, gyro integrator and line extractor
processors (what their nodes run per message, without DDS).

A bag is recorded with `sensor_sim --record` (60 s, seed 5; 20 s with --quick). Decoding: every
message of each input type of the bag, decoded in turn by cdr_decoder (the nodes' decoder) and
by rosbags' own generated decoder. Processors: each node is built as sensing_pipeline builds it
(config/ parameters) and driven as sensing_pipeline drives it (graph/pipeline.Driver), its
inputs decoded beforehand (the gyro's /wheel/odom from the wheel processor's outputs, in the one
event order: core/events.py), and the handlers timed with the driver's keeping of their outputs
(each node packs its outputs into CDR bytes itself: ros/cdr.py). CPU
time of this process (time.process_time), the best of 3 passes; warm caches, so a running node
costs several times this per message (docs/performance.md). Compare figures of one run only.
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

from sensing_nodes.core.events import time_ordered

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


def _time_node(node: str, rows) -> tuple[float, int, list]:
    """Best-of-PASSES CPU seconds of the node driven as sensing_pipeline drives it
    (graph/pipeline.Driver) over rows (topic, bag time, bytes) it takes, decoded beforehand, the
    number of messages, and its outputs of the last pass as such rows (in bag time)."""
    from sensing_nodes.graph.pipeline import close, node_driver

    best, outputs = float('inf'), []
    for _ in range(PASSES):
        built, driver = node_driver(node)
        messages = driver.decoded(rows)
        started = time.process_time()
        for topic, stamp_ns, msg in messages:
            driver.take(topic, msg, stamp_ns)
        best = min(best, time.process_time() - started)
        close(built)
        outputs = sorted(((topic, s, raw) for topic, recorded in driver.result.outputs.items()
                          for s, raw in recorded), key=lambda row: row[1])
    return best, len(messages), outputs


def merged_rows(*streams: list[tuple]) -> list[tuple]:
    """(topic, bag time, ...) rows of several streams as one, in the one event order
    (core/events.py: bag time, then the streams' order)."""
    return [streams[int(e.source)][e.index] for e in time_ordered(
        {str(k): [row[1] for row in stream] for k, stream in enumerate(streams)})]


def processors(bag) -> dict:
    """us per input message of the wheel odometry, gyro integrator and line extractor
    processors (handlers only, inputs decoded beforehand); the gyro's /wheel/odom is the wheel
    processor's output, in bag order."""
    out = {}
    rows = [(t, s, raw) for t, s, raw in bag.messages]
    wheel_odom: list = []
    for node in ('wheel_odometry', 'gyro_integrator', 'line_extractor'):
        fed = rows if node != 'gyro_integrator' else merged_rows(
            [row for row in rows if row[0] != '/wheel/odom'], wheel_odom)
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
