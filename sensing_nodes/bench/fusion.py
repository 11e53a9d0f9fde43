"""complementary_fusion's own cost per message: its processor alone, no DDS and no bag I/O.

A bag is recorded with `sensor_sim --record` (300 s, seed 5; 60 s with --quick) and run through
`sensing_pipeline` (all five nodes) for the fusion's inputs (`/wheel/odom`, `/imu/data`,
`/scan_match/keyframe_odom`). Then a fresh fusion node (default method `ekf`, config/ parameters)
built as sensing_pipeline builds it takes them in bag order from sensing_pipeline's driver
(graph/pipeline.Driver, which hands them to its processor's handlers: ros/processor.py), each
decoded beforehand as its subscription decodes it, with the flush at the end; three passes, the
fastest one's CPU time (this process's) gives the figures. Decoding, DDS and writing are not
counted: this is the node's per-message logic (reading conversion, reorder buffer, EKF, packing
the outputs) and the driver's keeping of them. The load average is reported with the figures.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from sensing_nodes.bench.pipeline import executable, record_sim_bag

PASSES = 3


def fusion_pass(rows: list[tuple[str, int, bytes]]) -> tuple[float, int, int]:
    """One fresh fusion node over (topic, bag time, CDR bytes) rows in order, driven as
    sensing_pipeline drives it (graph/pipeline.Driver), its inputs decoded beforehand:
    (CPU s, inputs, outputs)."""
    from sensing_nodes.graph.pipeline import close, node_driver

    built, driver = node_driver('complementary_fusion')
    try:
        inputs = driver.decoded(rows)
        start = time.process_time()
        for topic, stamp_ns, msg in inputs:
            driver.take(topic, msg, stamp_ns)
        driver.finish(inputs[-1][1] if inputs else 0)
        cpu_s = time.process_time() - start
        return cpu_s, len(inputs), sum(len(out) for out in driver.result.outputs.values())
    finally:
        close(built)


def run(quick: bool = False) -> dict:
    """Record the bag, make the fusion's inputs, time the fusion's processor over them."""
    from sensing_nodes.bags.input_bag import load_bag

    duration_s = 60.0 if quick else 300.0
    with tempfile.TemporaryDirectory() as tmp:
        bag, inputs = Path(tmp) / 'bag', Path(tmp) / 'inputs'
        record_sim_bag(bag, duration_s)
        subprocess.run([executable('sensing_pipeline'), str(bag), str(inputs), '--no-progress'],
                       check=True, capture_output=True)
        rows = load_bag(inputs).messages
    load_start = os.getloadavg()[0]
    passes = [fusion_pass(rows) for _ in range(PASSES)]
    cpu, count, outputs = min(passes)
    return {
        'fusion_bag_seconds': duration_s,
        'fusion_input_messages': count,
        'fusion_output_messages': outputs,
        'fusion_cpu_seconds': round(cpu, 3),
        'fusion_cpu_us_per_input_message': round(cpu / count * 1e6, 1),
        'fusion_x_real_time_cpu': round(duration_s / cpu, 1),
        'fusion_load_average_1min_start': round(load_start, 2),
        'fusion_load_average_1min_end': round(os.getloadavg()[0], 2),
    }


if __name__ == '__main__':
    print(run(quick='--quick' in sys.argv))
