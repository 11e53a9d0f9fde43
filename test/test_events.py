"""core/events.py: the one event order (stamp, then the streams' rank, then each stream's own
order), and the fusion's reorder buffer releasing the same order whatever the arrival order."""

import random

import numpy as np

from sensing_nodes.core.events import Event, time_ordered
from sensing_nodes.core.fusion.inputs import IMU, RANK, SCAN, WHEEL
from sensing_nodes.core.fusion.timeline import StampOrderedBuffer


def test_stamp_then_rank_then_index():
    events = time_ordered({'wheel': [10, 20, 20], 'imu': np.array([5, 20]), 'scan': [20, 15]})
    assert events == [Event(5, 'imu', 0), Event(10, 'wheel', 0), Event(15, 'scan', 1),
                      Event(20, 'wheel', 1), Event(20, 'wheel', 2), Event(20, 'imu', 1),
                      Event(20, 'scan', 0)]


def test_rank_is_the_mappings_order_and_stamps_keep_int64():
    big = 1_700_000_000_123_456_789   # beyond float64's exact integers
    assert [e.source for e in time_ordered({'b': [big], 'a': [big]})] == ['b', 'a']
    assert [e.source for e in time_ordered({'a': [big], 'b': [big]})] == ['a', 'b']
    assert time_ordered({'a': [big + 1], 'b': [big]})[0] == Event(big, 'b', 0)


def test_empty_streams():
    assert time_ordered({}) == []
    assert time_ordered({'wheel': [], 'imu': np.zeros(0, dtype=np.int64)}) == []
    assert time_ordered({'wheel': [], 'imu': [3]}) == [Event(3, 'imu', 0)]


def test_the_fusions_reorder_buffer_releases_the_one_event_order():
    rng = random.Random(4)
    streams = {WHEEL: sorted(rng.randrange(0, 50) for _ in range(40)),
               IMU: sorted(rng.randrange(0, 50) for _ in range(80)),
               SCAN: sorted(rng.randrange(0, 50) for _ in range(15))}
    assert list(streams) == sorted(RANK, key=RANK.get)
    expected = [(e.stamp_ns, (e.source, e.index)) for e in time_ordered(streams)]
    # Each input arrives in its own order, the inputs interleaved at random (as over DDS).
    queues = {name: list(enumerate(stamps)) for name, stamps in streams.items()}
    buffer = StampOrderedBuffer(window_ns=1_000)
    while any(queues.values()):
        name = rng.choice([n for n, q in queues.items() if q])
        index, stamp = queues[name].pop(0)
        assert buffer.push(stamp, RANK[name], (name, index))
    assert buffer.flush() == expected
