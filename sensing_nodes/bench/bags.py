"""What crash safety costs the bag writer, and what reading an unclosed bag costs the reader.

One stream of messages (the simulated robot's sensors, encoded as `sensor_sim --record` encodes
them: message_cdr, canonical CDR) is written by BagWriter with 1 s chunks (chunk_s=1.0, the
default: a crash loses at most the open chunk) and with 1 MiB chunks written at close
(chunk_s=None), plain and
zstd-compressed: CPU time per simulated second and file size, side by side from one run (best of
3 on a shared machine); the wall time of the live recorder's flush (the chunk closed, written
and fsynced) per second of data. Then the bag is read whole through BagReader, closed and cut in
the middle of its file (the recovery path of bags/recovery.py).
"""

from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path


def _stream(duration_s: float) -> tuple[list[tuple[str, bytes, int]], dict[str, str]]:
    """(topic, canonical CDR bytes, bag time ns) of duration_s simulated seconds, and topic ->
    type."""
    from sensing_nodes.bags.storage import message_cdr
    from sensing_nodes.core.sim import simulator as core
    from sensing_nodes.core.sim.world import load_world
    from sensing_nodes.paths import config_file
    from sensing_nodes.ros.sim_robot import TOPICS, NodeSettings, SimMessages

    params, settings = core.SimParams(), NodeSettings()
    sim = core.SensorSim(params, load_world(str(config_file('default_world.yaml'))), 0)
    convert = SimMessages(params, settings)
    end_ns = params.start_ns + int(duration_s * core.NS_PER_S)
    rows = []
    while sim.time_ns < end_ns:
        for t, kind, msg in convert.messages(sim.advance()):
            if t <= end_ns:
                rows.append((TOPICS[kind][0], message_cdr(msg), t))
    return rows, {topic: kind for topic, kind in TOPICS.values()}


def _write(folder: Path, rows, types, chunk_s, compress) -> tuple[float, int]:
    """CPU seconds (best of 3) and file size (bytes) of writing `rows` into a new bag."""
    from sensing_nodes.bags.storage import BagWriter

    best = float('inf')
    for attempt in range(3):
        path = folder / f'bag-{chunk_s}-{compress}-{attempt}'
        started = time.process_time()
        with BagWriter(path, compress=compress, chunk_s=chunk_s) as bag:
            for topic, kind in types.items():
                bag.add_topic(topic, kind)
            bag.write_raw_many(rows, canonical_topics=set(types))
        best = min(best, time.process_time() - started)
        size = (path / f'{path.name}.mcap').stat().st_size
    return best, size


def _flush_ms(folder: Path, rows, types, duration_s: float) -> float:
    """Median wall ms of BagWriter.flush() with its fsync, after each simulated second of
    `rows` (what the live recorder does every wall second)."""
    from sensing_nodes.bags.storage import BagWriter

    per_second = max(1, int(len(rows) / duration_s))
    times = []
    with BagWriter(folder / 'flushed', chunk_s=None) as bag:
        for topic, kind in types.items():
            bag.add_topic(topic, kind)
        for start in range(0, len(rows), per_second):
            bag.write_raw_many(rows[start:start + per_second], canonical_topics=set(types))
            started = time.perf_counter()
            bag.flush()
            times.append(time.perf_counter() - started)
    return 1e3 * sorted(times)[len(times) // 2]


def _read_s(path: Path) -> float:
    """CPU seconds to read every message of a bag (best of 3)."""
    from sensing_nodes.bags.storage import BagReader

    best = float('inf')
    for _ in range(3):
        started = time.process_time()
        for _ in BagReader(path).raw():
            pass
        best = min(best, time.process_time() - started)
    return best


def run(quick: bool = False) -> dict:
    """Measure and return a flat dict of figures."""
    duration_s = 20.0 if quick else 120.0
    rows, types = _stream(duration_s)
    out: dict = {'simulated_s': duration_s, 'messages': len(rows)}
    with tempfile.TemporaryDirectory(prefix='sensing_bench_bags-') as tmp:
        folder = Path(tmp)
        for compress in (False, True):
            name = 'zstd' if compress else 'plain'
            chunked_cpu, chunked_size = _write(folder, rows, types, 1.0, compress)
            whole_cpu, whole_size = _write(folder, rows, types, None, compress)
            out[f'{name}_chunk_1s_cpu_ms_per_sim_s'] = 1e3 * chunked_cpu / duration_s
            out[f'{name}_chunk_1mib_cpu_ms_per_sim_s'] = 1e3 * whole_cpu / duration_s
            out[f'{name}_cpu_ratio_1s_to_1mib'] = chunked_cpu / whole_cpu
            out[f'{name}_chunk_1s_bytes_per_sim_s'] = chunked_size / duration_s
            out[f'{name}_size_ratio_1s_to_1mib'] = chunked_size / whole_size
        out['flush_with_fsync_wall_ms_per_s'] = _flush_ms(folder, rows, types, duration_s)
        closed = folder / 'bag-1.0-False-0'
        cut = folder / 'cut'
        shutil.copytree(closed, cut)
        (cut / 'metadata.yaml').unlink()     # as a crash leaves it
        mcap = cut / f'{closed.name}.mcap'
        with mcap.open('r+b') as handle:
            handle.truncate(mcap.stat().st_size // 2)
        out['read_closed_us_per_message'] = 1e6 * _read_s(closed) / len(rows)
        out['read_cut_in_half_us_per_message'] = 1e6 * _read_s(cut) / (len(rows) / 2)
    return out
